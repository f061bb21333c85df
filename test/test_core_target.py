"""
Rigid targets on a link: the mount's Jacobian, the hand-eye closed form, pose conversions.

``MOUNT`` is a board mount T_link_target; the poses around it are drawn at random.
"""
import numpy as np
import pytest

from armcal_ros.core.target import (correct_mount, hand_eye, mount_jacobian, mount_points,
                                    pose_matrix, rotation_angle_deg)
from helpers.board_scene import transform

MOUNT = transform([0.3, -2.0, 0.4], [0.05, 0.11, 0.20])


def test_mount_jacobian_matches_finite_differences():
    rng = np.random.default_rng(0)
    poses = np.array([transform(rng.normal(0, 1, 3), rng.normal(0, 0.5, 3)) for _ in range(3)])
    view = np.array([0, 1, 2, 2])
    pts = rng.normal(0, 0.1, (4, 3))
    J = mount_jacobian(poses, MOUNT, view, pts)
    X0 = mount_points(poses, MOUNT, view, pts)
    h = 1e-7
    for k in range(6):
        dp = np.zeros(6)
        dp[k] = h
        Xk = mount_points(poses, correct_mount(MOUNT, dp), view, pts)
        assert np.allclose((Xk - X0) / h, J[:, :, k], atol=1e-6)


def test_hand_eye_recovers_exact_transforms_and_tolerates_noise():
    rng = np.random.default_rng(2)
    T_cb = transform([0.2, 2.5, -0.3], [0.1, -0.3, 1.2])
    B = np.array([transform(rng.normal(0, 0.7, 3), rng.normal(0, 0.3, 3)) for _ in range(8)])
    A = np.array([T_cb @ b @ MOUNT for b in B])
    he = hand_eye(B, A)
    assert np.allclose(he.T_camera_base, T_cb, atol=1e-9)
    assert np.allclose(he.T_link_target, MOUNT, atol=1e-9)
    assert he.residual_m < 1e-9
    noisy = np.array([a @ transform(rng.normal(0, 2e-3, 3), rng.normal(0, 1e-3, 3)) for a in A])
    he = hand_eye(B, noisy)
    assert np.linalg.norm(he.T_link_target[:3, 3] - MOUNT[:3, 3]) < 0.01
    assert rotation_angle_deg(he.T_link_target[:3, :3], MOUNT[:3, :3]) < 0.5
    with pytest.raises(ValueError, match='3 or more'):
        hand_eye(B[:2], A[:2])


def test_pose_matrix_checks_its_quaternion():
    T = pose_matrix([1, 2, 3], [0, 0, np.sin(0.25), np.cos(0.25)])
    assert np.allclose(T[:3, 3], [1, 2, 3])
    with pytest.raises(ValueError, match='unit length'):
        pose_matrix([0, 0, 0], [0, 0, 0, 2])
