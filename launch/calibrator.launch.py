"""
Launch the armcal calibrator node with a parameter file.

    ros2 launch armcal_ros calibrator.launch.py
    ros2 launch armcal_ros calibrator.launch.py params_file:=/path/to/cell.yaml \
        namespace:=cell1 use_sim_time:=true log_level:=debug

``params_file`` defaults to the package's ``config/calibrator.yaml``.  Outputs are under the
node's private namespace (``/[namespace/]armcal/<camera>/camera_info`` ...); remap the drivers'
``set_camera_info`` services through the ``set_camera_info_services`` parameter.

A cell with static cameras and cameras on the arm runs one calibrator per group:
``hand_params_file:=/path/to/hand.yaml`` adds a second node, ``armcal_hand``, for the cameras
on the arm (``eye_in_hand: true``, the static target's marker); its file's section is
``armcal_hand:`` or ``/**:``.  The two groups share no unknown (README, "Cameras on the arm").
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node


def generate_launch_description():
    """Return the launch description: calibrator_node armcal (and armcal_hand if asked)."""
    default_params = os.path.join(get_package_share_directory('armcal_ros'), 'config',
                                  'calibrator.yaml')
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS 2 parameter file of the armcal node'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='namespace of the node'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='use /clock (e.g. when replaying a bag with --clock)'),
        DeclareLaunchArgument('log_level', default_value='info',
                              description='debug, info, warn, error'),
        DeclareLaunchArgument('hand_params_file', default_value='',
                              description='parameter file of a second calibrator, armcal_hand, '
                              'for the cameras on the arm (empty: none)'),
        _calibrator('armcal', LaunchConfiguration('params_file')),
        _calibrator('armcal_hand', LaunchConfiguration('hand_params_file'),
                    IfCondition(PythonExpression(
                        ["'", LaunchConfiguration('hand_params_file'), "' != ''"]))),
    ])


def _calibrator(name, params_file, condition=None):
    """Return one calibrator_node named ``name`` reading ``params_file``."""
    return Node(
        package='armcal_ros',
        executable='calibrator_node',
        name=name,
        namespace=LaunchConfiguration('namespace'),
        parameters=[params_file, {'use_sim_time': LaunchConfiguration('use_sim_time')}],
        arguments=['--ros-args', '--log-level', LaunchConfiguration('log_level')],
        output='screen',
        emulate_tty=True,
        condition=condition,
    )
