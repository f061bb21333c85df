"""
Uncertainty of the published results, propagated from the solver's parameter covariance.

Two kinds: a camera's pose in the base frame (:func:`pose_covariance`), and the error the
calibration puts into points triangulated with the cameras (:func:`triangulation_covariance`),
the figure a user of a metric workspace reads.

The solver parameterises each camera world-to-camera (x_cam = R X + t) and perturbs it as
R <- exp([w]x) R, t <- t + dt.  Users receive the camera's pose in the base frame
(T_base_camera, the TF convention), so its covariance is mapped through the Jacobian of that
change of parameters.
"""

from typing import Sequence

import numpy as np

from armcal_ros.core.camera import (Camera, DISTORTION_NAMES, INTRINSIC_NAMES,
                                    project_with_jacobians)
from armcal_ros.core.geometry import skew

#: The solver's pose parameters, in its order (R <- exp([w]x) R, t <- t + dt).
POSE_NAMES = ('wx', 'wy', 'wz', 'tx', 'ty', 'tz')


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


def _camera_block(cam: Camera, names, X):
    """Projections of X (n, 3) and their derivatives (n, 2, p) over a camera's ``names``."""
    J = project_with_jacobians(cam.intrinsics(), cam.dist, cam.rotation, cam.translation, X)
    cols = []
    for name in names:
        if name in INTRINSIC_NAMES:
            cols.append(J.d_intr[:, :, INTRINSIC_NAMES.index(name)])
        elif name in DISTORTION_NAMES:
            cols.append(J.d_dist[:, :, DISTORTION_NAMES.index(name)])
        else:
            cols.append(J.d_pose[:, :, POSE_NAMES.index(name)])
    return J, np.stack(cols, axis=2)


def triangulation_covariance(cameras: Sequence[Camera], covariance, parameter_names, points,
                             margin_px=0.0):
    """
    Covariance of points triangulated with cameras whose parameters are uncertain.

    ``covariance`` is the solver's over ``parameter_names`` ('<camera>/<parameter>', the
    layout of :class:`~armcal_ros.core.adjustment.AdjustmentResult`).  A point X (of
    ``points``, (n, 3), in the base frame) seen at its exact projections u_j by the cameras j
    that have it in front and inside the image (``margin_px`` from the border) is
    triangulated by minimising sum_j |pi_j(X) - u_j|^2.  A change dc of the camera
    parameters moves it, to first order, by

        dX = -(A^T A)^-1 A^T J_c dc,   A = [d pi_j / d X]_j,   J_c = [d pi_j / d c_j]_j,

    so Cov(X) = G Sigma G^T with G = -(A^T A)^-1 A^T J_c: the error the calibration itself puts
    into every 3-D measurement made with these cameras, image noise of the new measurement
    aside.  Returns (covariance (n, 3, 3), per-camera part {name: (n, 3, 3)} - each camera's
    own parameters alone - and the number of cameras seeing each point (n,)); points seen by
    fewer than two cameras get NaN.
    """
    X = np.asarray(points, float).reshape(-1, 3)
    names = list(parameter_names)
    cov = np.asarray(covariance, float)
    n = len(X)
    blocks, A_rows, Jc_rows, seen = [], [], [], []
    for cam in cameras:
        idx = [k for k, p in enumerate(names) if p.split('/', 1)[0] == cam.name]
        local = [names[k].split('/', 1)[1] for k in idx]
        J, Jc = _camera_block(cam, local, X)
        ok = cam.in_front(X)
        uv = J.uv
        ok &= (uv[:, 0] >= margin_px) & (uv[:, 0] <= cam.width - 1 - margin_px) & \
            (uv[:, 1] >= margin_px) & (uv[:, 1] <= cam.height - 1 - margin_px)
        blocks.append((cam.name, idx))
        A_rows.append(np.where(ok[:, None, None], J.d_point, 0.0))
        Jc_rows.append(np.where(ok[:, None, None], Jc, 0.0))
        seen.append(ok)
    seen = np.array(seen)
    n_seen = seen.sum(axis=0)
    AtA = sum(np.einsum('nak,nal->nkl', A, A) for A in A_rows)
    good = n_seen >= 2
    inv = np.full((n, 3, 3), np.nan)
    inv[good] = np.linalg.inv(AtA[good])
    # G_j = -(A^T A)^-1 A_j^T J_cj, (n, 3, p_j) for each camera.
    G = [-np.einsum('nkl,nal,nap->nkp', inv, A, Jc) for A, Jc in zip(A_rows, Jc_rows)]
    total = np.zeros((n, 3, 3))
    own = {}
    for a, (name_a, ia) in enumerate(blocks):
        for b, (_, ib) in enumerate(blocks):
            part = np.einsum('nkp,pq,nlq->nkl', G[a], cov[np.ix_(ia, ib)], G[b])
            total += part
            if a == b:
                own[name_a] = part
    total[~good] = np.nan
    for name in own:
        own[name][~good] = np.nan
    return total, own, n_seen


def rms_error_mm(cov):
    """Root mean square 3-D error (mm) of points with covariances ``cov`` (n, 3, 3)."""
    tr = np.trace(np.asarray(cov), axis1=1, axis2=2)
    tr = tr[np.isfinite(tr)]
    # A negative mean trace is a covariance that is not one (a pseudo-inverse of a singular
    # normal matrix): no figure rather than the root of a negative number.
    return float(1e3 * np.sqrt(np.mean(tr))) if tr.size and np.mean(tr) >= 0 else float('nan')
