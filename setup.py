"""ament_python / pip build of armcal_ros (the repository root is the ROS package)."""
from glob import glob

from setuptools import find_packages, setup

package_name = 'armcal_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(include=['armcal_ros', 'armcal_ros.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.py')),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/urdf', glob('urdf/*.urdf')),
    ],
    install_requires=['setuptools', 'numpy', 'scipy', 'PyYAML', 'threadpoolctl'],
    zip_safe=True,
    maintainer='armcal_ros developers',
    maintainer_email='armcal@example.com',
    description='Online background camera calibration using a robot arm as the target.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'calibrator_node = armcal_ros.ros.node:main',
            'armcal = armcal_ros.cli:main',
        ],
    },
)
