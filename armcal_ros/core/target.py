"""
Rigid targets on a robot link: their points in the base frame, the mount's Jacobian, hand-eye.

A target is a set of points p_k fixed in a target frame that is rigidly attached to a link at
T_link_target (a board: its corners).  With T_base_link_v the link's pose when view v was taken
(from forward kinematics or a measured pose), the measured position of point k in view v is::

    X^_vk = T_base_link_v  T_link_target  p_k

The mount is corrected on the right, T_link_target <- T_link_target [Exp(r) | t] (the same
convention as the ``tip`` block of :mod:`armcal_ros.robot.kinematics`, here in the target frame),
so with R_v = R_base_link_v R_link_target, to first order at (t, r) = 0::

    d X^_vk / d t = R_v,        d X^_vk / d r = -R_v [p_k]x

That 3x6 block per point is the design of the mount parameters when they are estimated as global
parameters of the adjustment (:class:`~armcal_ros.core.kinematic_prior.KinematicData`).

Initialisation (no guess needed): per view, the board pose in the camera T_cam_target_v from the
corners (Zhang's planar calibration, ``cv2.calibrateCamera``, gives rough intrinsics and every
view's pose at once; ``solvePnP`` with IPPE when intrinsics are given); then the robot-world /
hand-eye problem A_v X = Z B_v (Shah, 2013, closed form) for the static
camera's pose T_camera_base and the mount.  A board seen in one pose is planar, but the union of
views is not, so the adjustment after this has the 3-D structure it needs.
"""

from dataclasses import dataclass
from typing import Dict, Optional, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

import cv2

from armcal_ros.core.geometry import skew

MOUNT_NAMES = ('target/tx', 'target/ty', 'target/tz', 'target/rx', 'target/ry', 'target/rz')


def pose_matrix(translation, quat_xyzw):
    """Return the 4x4 transform of a translation (3,) and a unit quaternion (x, y, z, w)."""
    t = np.asarray(translation, float).reshape(-1)
    q = np.asarray(quat_xyzw, float).reshape(-1)
    if t.shape != (3,) or q.shape != (4,) or not (np.all(np.isfinite(t)) and
                                                  np.all(np.isfinite(q))):
        raise ValueError(f'pose needs a finite translation (3,) and quaternion (4,), got '
                         f'{t.shape} and {q.shape}')
    n = np.linalg.norm(q)
    if abs(n - 1.0) > 1e-3:
        raise ValueError(f'pose quaternion must be unit length, got norm {n:.6f}')
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q / n).as_matrix()
    T[:3, 3] = t
    return T


def pose_vector(T):
    """Return [x, y, z, qx, qy, qz, qw] (floats) of a 4x4 pose: the inverse of pose_matrix."""
    T = np.asarray(T, float)
    return [float(x) for x in T[:3, 3]] + \
        [float(x) for x in Rotation.from_matrix(T[:3, :3]).as_quat()]


def invert(T):
    """Return the inverse of rigid transform(s) T (..., 4, 4)."""
    T = np.asarray(T, float)
    out = np.zeros_like(T)
    Rt = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum('...ij,...j->...i', Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _check_poses(poses, name='poses'):
    poses = np.asarray(poses, float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise ValueError(f'{name} must have shape (V, 4, 4), got {poses.shape}')
    if not np.all(np.isfinite(poses)):
        raise ValueError(f'{name} contains NaN or inf')
    return poses


def mount_points(poses, T_link_target, view, points):
    """
    Return X^ (N, 3) = T_base_link[view] T_link_target points.

    ``poses`` (V, 4, 4) link poses in the base frame, ``view`` (N,) indices into them,
    ``points`` (N, 3) in the target frame.
    """
    poses = _check_poses(poses)
    T = poses[view] @ np.asarray(T_link_target, float)
    p = np.asarray(points, float)
    return np.einsum('nij,nj->ni', T[:, :3, :3], p) + T[:, :3, 3]


def mount_jacobian(poses, T_link_target, view, points):
    """Return d X^ / d (t, r) (N, 3, 6) of the right mount correction (module docstring)."""
    poses = _check_poses(poses)
    R = poses[view][:, :3, :3] @ np.asarray(T_link_target, float)[:3, :3]
    J = np.empty((len(view), 3, 6))
    J[:, :, :3] = R
    J[:, :, 3:] = -R @ skew(np.asarray(points, float))
    return J


def correct_mount(T_link_target, dp):
    """Return T_link_target [Exp(r) | t] for dp = (t, r) (6,)."""
    dp = np.asarray(dp, float).reshape(-1)
    if dp.shape != (6,):
        raise ValueError(f'mount correction must have 6 entries (t, r), got {dp.shape}')
    D = np.eye(4)
    D[:3, :3] = Rotation.from_rotvec(dp[3:]).as_matrix()
    D[:3, 3] = dp[:3]
    return np.asarray(T_link_target, float) @ D


def _rt_to_T(rvec, tvec):
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float).reshape(3))[0]
    T[:3, 3] = np.asarray(tvec, float).reshape(3)
    return T


@dataclass
class ViewPoses:
    """
    Board poses in one camera from its views alone.

    ``K`` (3, 3) and ``dist`` (5,) the intrinsics used (estimated or given); ``T_cam_target``
    view index -> (4, 4); ``rms_px`` the per-view fit; ``method`` how they were obtained.
    """

    K: np.ndarray
    dist: np.ndarray
    T_cam_target: Dict[int, np.ndarray]
    rms_px: float
    method: str


def board_view_poses(views: Dict[int, tuple], width, height, K=None, dist=None,
                     min_corners=6) -> ViewPoses:
    """
    Return every view's board pose in the camera, estimating rough intrinsics when K is None.

    ``views`` maps a view index to (object points (K, 3) on the board plane z = 0, image
    points (K, 2)).  Without ``K``: Zhang's method (``cv2.calibrateCamera``, k1 k2 only) over
    the views with at least ``min_corners`` corners - it needs three or more views of the board
    at different tilts; with ``K``: ``solvePnP`` (IPPE, then iterative refinement) per view.
    Views that fail are left out.  Raises ValueError when no view is usable.
    """
    use = {v: (np.asarray(o, np.float64).reshape(-1, 3), np.asarray(i, np.float64).reshape(-1, 2))
           for v, (o, i) in views.items() if len(o) >= min_corners}
    if not use:
        raise ValueError(f'no view has {min_corners} or more board corners')
    if K is None:
        if len(use) < 3:
            raise ValueError(f'rough intrinsics need 3 or more board views, got {len(use)}: '
                             'give an intrinsics guess')
        keys = sorted(use)
        f0 = 0.9 * max(width, height)
        K0 = np.array([[f0, 0, (width - 1) / 2.0], [0, f0, (height - 1) / 2.0], [0, 0, 1]])
        flags = (cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_ZERO_TANGENT_DIST |
                 cv2.CALIB_FIX_K3)
        rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
            [use[k][0].astype(np.float32) for k in keys],
            [use[k][1].astype(np.float32) for k in keys], (int(width), int(height)),
            K0, np.zeros(5), flags=flags)
        poses = {k: _rt_to_T(r, t) for k, r, t in zip(keys, rvecs, tvecs)}
        return ViewPoses(np.asarray(K), np.asarray(dist).reshape(-1)[:5], poses, float(rms),
                         'zhang')
    K = np.asarray(K, float)
    dist = np.zeros(5) if dist is None else np.asarray(dist, float).reshape(-1)
    poses, sq = {}, []
    for v, (o, i) in use.items():
        ok, rvec, tvec = cv2.solvePnP(o, i, K, dist, flags=cv2.SOLVEPNP_IPPE)
        if not ok:
            continue
        rvec, tvec = cv2.solvePnPRefineLM(o, i, K, dist, rvec, tvec)
        proj = cv2.projectPoints(o, rvec, tvec, K, dist)[0].reshape(-1, 2)
        sq.append(np.sum((proj - i) ** 2, axis=1))
        poses[v] = _rt_to_T(rvec, tvec)
    if not poses:
        raise ValueError('solvePnP failed on every view')
    return ViewPoses(K, dist, poses, float(np.sqrt(np.mean(np.concatenate(sq)))), 'pnp')


@dataclass
class HandEye:
    """Static camera and link-mounted target from :func:`hand_eye`; residuals in metres/rad."""

    T_camera_base: np.ndarray
    T_link_target: np.ndarray
    residual_m: float
    residual_rad: float
    n_views: int


def hand_eye(link_poses: Sequence[np.ndarray], T_cam_target: Sequence[np.ndarray]) -> HandEye:
    """
    Solve T_cam_target_v = T_camera_base T_base_link_v T_link_target for the two constants.

    The robot-world/hand-eye problem A_v X = Z B_v (X = T_target_link, Z = T_camera_base,
    A_v = T_cam_target_v, B_v = T_base_link_v) in the closed form of Shah (2013): the rotations
    satisfy R_A R_X = R_Z R_B, linear in (vec R_X, vec R_Z) - (I (x) R_A) vec R_X -
    (R_B^T (x) I) vec R_Z = 0 - so they are the null vector of the stacked system, rescaled
    and projected onto SO(3); then the translations solve R_A t_X - t_Z = R_Z t_B - t_A by
    least squares.  (OpenCV 5 no longer ships ``calibrateRobotWorldHandEye``.)  Needs 3+ views
    with rotations about non-parallel axes.  ``residual_m`` / ``residual_rad`` are the RMS
    translation/rotation misfit over the views.
    """
    A = _check_poses(np.asarray(T_cam_target), 'T_cam_target')
    B = _check_poses(np.asarray(link_poses), 'link_poses')
    if len(A) != len(B) or len(A) < 3:
        raise ValueError(f'hand_eye needs 3 or more paired poses, got {len(A)} and {len(B)}')
    eye = np.eye(3)
    # Column-major vec: vec(M N) = (I (x) M) vec(N) = (N^T (x) I) vec(M).
    M = np.vstack([np.hstack([np.kron(eye, a[:3, :3]), -np.kron(b[:3, :3].T, eye)])
                   for a, b in zip(A, B)])
    x = np.linalg.svd(M)[2][-1]
    Rx = x[:9].reshape(3, 3, order='F')
    Rz = x[9:].reshape(3, 3, order='F')
    det = np.linalg.det(Rx)
    if abs(det) < 1e-12:
        raise ValueError('hand_eye: degenerate rotations (the target must turn about two '
                         'or more non-parallel axes)')
    scale = np.sign(det) / abs(det) ** (1.0 / 3.0)
    Rx, Rz = nearest_rotation(scale * Rx), nearest_rotation(scale * Rz)
    lhs = np.vstack([np.hstack([a[:3, :3], -eye]) for a in A])
    rhs = np.concatenate([Rz @ b[:3, 3] - a[:3, 3] for a, b in zip(A, B)])
    t = np.linalg.lstsq(lhs, rhs, rcond=None)[0]
    T_tl = np.eye(4)
    T_tl[:3, :3], T_tl[:3, 3] = Rx, t[:3]
    T_cb = np.eye(4)
    T_cb[:3, :3], T_cb[:3, 3] = Rz, t[3:]
    T_lt = invert(T_tl)
    pred = T_cb[None] @ B @ T_lt[None]
    dt = pred[:, :3, 3] - A[:, :3, 3]
    dR = np.einsum('nji,njk->nik', pred[:, :3, :3], A[:, :3, :3])
    ang = Rotation.from_matrix(dR).magnitude()
    return HandEye(T_cb, T_lt, float(np.sqrt(np.mean(np.sum(dt * dt, axis=1)))),
                   float(np.sqrt(np.mean(ang ** 2))), len(A))


def rotation_angle_deg(Ra, Rb):
    """Return the angle (degrees) of the rotation between rotation matrices Ra and Rb."""
    return float(np.degrees(Rotation.from_matrix(np.asarray(Ra).T @ np.asarray(Rb)).magnitude()))


def nearest_rotation(R):
    """Return the rotation matrix nearest to R (3, 3) in the Frobenius norm."""
    U, _, Vt = np.linalg.svd(np.asarray(R, float))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def optional_pose(value) -> Optional[np.ndarray]:
    """Return a (4, 4) pose from None, a 4x4 array, or [x, y, z, qx, qy, qz, qw]."""
    if value is None:
        return None
    a = np.asarray(value, float)
    if a.shape == (4, 4):
        return a
    if a.shape == (7,):
        return pose_matrix(a[:3], a[3:])
    raise ValueError(f'a pose must be 4x4 or [x, y, z, qx, qy, qz, qw], got shape {a.shape}')
