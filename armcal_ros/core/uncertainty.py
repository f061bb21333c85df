"""
Uncertainty of the published results, propagated from the solver's parameter covariance.

The solver parameterises each camera world-to-camera (x_cam = R X + t) and perturbs it as
R <- exp([w]x) R, t <- t + dt.  Users receive the camera's pose in the base frame
(T_base_camera, the TF convention), so its covariance is mapped through the Jacobian of that
change of parameters.
"""

import numpy as np

from armcal_ros.core.camera import Camera
from armcal_ros.core.geometry import skew


def pose_covariance(cam: Camera, cov_pose):
    """
    Covariance of T_base_camera over (x, y, z, rx, ry, rz) from the solver's pose covariance.

    ``cov_pose`` (6, 6) is over the solver's (wx, wy, wz, tx, ty, tz).  The optical centre
    C = -R^T t moves by dC = -R^T [t]x w - R^T dt, and the camera's orientation in the base
    frame, R^T, by a base-frame rotation of -R^T w (ROS PoseWithCovariance convention:
    rotations about the fixed parent axes).
    """
    R, t = cam.rotation, cam.translation
    J = np.zeros((6, 6))
    J[:3, :3] = -R.T @ skew(t)
    J[:3, 3:] = -R.T
    J[3:, :3] = -R.T
    return J @ np.asarray(cov_pose) @ J.T
