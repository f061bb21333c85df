"""ROS-free robot model: URDF chain, forward kinematics, kinematic error parameters."""

from .kinematics import KinematicChain, so3_exp, so3_right_jacobian
from .urdf import (load_urdf, origin_matrix, parse_urdf, rpy_to_matrix, UrdfJoint, UrdfLink,
                   UrdfModel)

__all__ = [
    'KinematicChain', 'so3_exp', 'so3_right_jacobian',
    'load_urdf', 'origin_matrix', 'parse_urdf', 'rpy_to_matrix', 'UrdfJoint', 'UrdfLink',
    'UrdfModel',
]
