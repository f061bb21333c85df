"""
Initial camera estimates from 3-D/2-D correspondences, with no hand-given guess.

Per camera: the Direct Linear Transform with Hartley normalisation (Hartley and Zisserman, 2nd
ed., sec. 7.1 and 4.4.4) inside RANSAC on the robot's measured points, then an RQ decomposition
P = K [R | t] with signs fixed so that diag(K) > 0, det(R) = +1 and the points lie in front of the
camera.  Distortion starts at zero; the DLT absorbs little of it, so the RANSAC inlier threshold is
generous (a fraction of the image diagonal) and the bundle adjustment does the rest.

Degenerate data are refused with a reason rather than turned into garbage: too few points, points
nearly coplanar or collinear (the DLT of a plane is rank-deficient: a homography, not a camera),
too few RANSAC inliers, or a decomposition whose points fall behind the camera.

A camera whose intrinsics are given (:class:`~armcal_ros.core.intrinsics_prior.IntrinsicsPrior`)
needs only its pose: :func:`initialise_with_intrinsics` solves the perspective-n-point problem
(EPnP inside RANSAC, then Levenberg-Marquardt on the inliers, ``cv2.solvePnPRansac``), which
works from six points, coplanar ones included, where the eleven-parameter DLT is ill-posed.
"""

from dataclasses import dataclass
from typing import Optional

import cv2
import numpy as np
from scipy.linalg import rq

from armcal_ros.core.camera import Camera
from armcal_ros.core.intrinsics_prior import IntrinsicsPrior

MIN_POINTS = 8
MIN_POINTS_PNP = 6


@dataclass
class InitResult:
    """Outcome of one camera's initialisation: ``camera`` is None unless ``success``."""

    success: bool
    status: str
    message: str
    camera: Optional[Camera] = None
    inliers: Optional[np.ndarray] = None
    rms_px: float = float('nan')


def _normalise(points):
    """Hartley normalisation: centroid to the origin, mean distance sqrt(dim)."""
    c = points.mean(axis=0)
    d = np.sqrt(np.sum((points - c) ** 2, axis=1)).mean()
    dim = points.shape[1]
    s = np.sqrt(dim) / max(d, 1e-12)
    T = np.eye(dim + 1)
    T[:dim, :dim] *= s
    T[:dim, dim] = -s * c
    return T


def dlt(X, uv):
    """
    Projection matrix P (3x4) from >= 6 correspondences by the normalised DLT.

    Each correspondence gives two rows of A p = 0; p is the right singular vector of the
    smallest singular value, de-normalised as P = T_2d^-1 P_n T_3d.
    """
    X = np.asarray(X, float)
    uv = np.asarray(uv, float)
    T3 = _normalise(X)
    T2 = _normalise(uv)
    Xh = np.column_stack([X, np.ones(len(X))]) @ T3.T
    xh = np.column_stack([uv, np.ones(len(uv))]) @ T2.T
    n = len(X)
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -xh[:, 0:1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -xh[:, 1:2] * Xh
    _, _, Vt = np.linalg.svd(A, full_matrices=False)
    Pn = Vt[-1].reshape(3, 4)
    return np.linalg.inv(T2) @ Pn @ T3


def project_P(P, X):
    """Project points (N, 3) with a 3x4 matrix; returns pixels (N, 2) and depths-sign (N,)."""
    Xh = np.column_stack([X, np.ones(len(X))])
    x = Xh @ P.T
    return x[:, :2] / x[:, 2:3], x[:, 2]


def decompose(P):
    """
    Split P into K, R, t with diag(K) > 0 and det(R) = +1 (P known only up to scale and sign).

    RQ of the left 3x3 block M = K R; a diagonal sign matrix D (D^2 = I) moves signs between K
    and R so that K's diagonal is positive; if then det(R) = -1 the whole P is negated.
    """
    M = P[:, :3]
    if np.linalg.det(M) < 0:
        P = -P
        M = -M
    K, R = rq(M)
    signs = np.sign(np.diag(K))
    signs[signs == 0] = 1.0
    D = np.diag(signs)
    K = K @ D
    R = D @ R
    t = np.linalg.solve(K, P[:, 3])
    K = K / K[2, 2]
    if np.linalg.det(R) < 0:
        R = -R
        t = -t
    return K, R, t


def planarity(X):
    """Return s3 / s1 of the centred points' singular values (0 for a plane, 0 for a line)."""
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False)
    return float(s[2] / max(s[0], 1e-300))


def initialise_camera(name, width, height, X, uv, rng=None, inlier_px=None,
                      iterations=500, min_points=MIN_POINTS, min_inlier_ratio=0.5,
                      min_planarity=0.01) -> InitResult:
    """
    Estimate one camera from its points X (N, 3) and pixels uv (N, 2) by DLT + RANSAC.

    ``inlier_px`` defaults to 3 % of the image diagonal: the zero-distortion DLT must accept the
    distortion it cannot model (about 20 px at the corner of a 640x480, f = 800 px, k1 = -0.15
    lens) while still rejecting gross mis-detections.
    """
    X = np.asarray(X, float)
    uv = np.asarray(uv, float)
    if X.ndim != 2 or X.shape[1] != 3 or uv.shape != (X.shape[0], 2):
        raise ValueError(f'X must be (N, 3) and uv (N, 2); got {X.shape} and {uv.shape}')
    rng = rng if rng is not None else np.random.default_rng(0)
    n = len(X)
    if n < min_points:
        return InitResult(False, 'insufficient_points',
                          f'camera {name}: {n} points, at least {min_points} needed')
    flat = planarity(X)
    if flat < min_planarity:
        return InitResult(False, 'degenerate',
                          f'camera {name}: points are nearly coplanar or collinear '
                          f'(thickness ratio {flat:.2g} < {min_planarity}); move the arm '
                          f'through more depth')
    if inlier_px is None:
        inlier_px = 0.03 * float(np.hypot(width, height))
    best = None
    best_count = 0
    sample_size = 6
    for _ in range(iterations if n > sample_size else 1):
        idx = rng.choice(n, sample_size, replace=False) if n > sample_size else np.arange(n)
        if planarity(X[idx]) < 1e-3:
            continue
        P = dlt(X[idx], uv[idx])
        proj, w = project_P(P, X)
        err = np.linalg.norm(proj - uv, axis=1)
        # All inliers must lie on one side of the camera (chirality of P up to sign).
        side = np.sign(np.median(w[err < inlier_px])) if np.any(err < inlier_px) else 1.0
        inl = (err < inlier_px) & (np.sign(w) == side)
        count = int(inl.sum())
        if count > best_count:
            best, best_count = inl, count
            if count == n:
                break
    if best is None or best_count < max(min_points, int(min_inlier_ratio * n)):
        return InitResult(False, 'init_failed',
                          f'camera {name}: DLT+RANSAC found {best_count} of {n} points '
                          f'consistent within {inlier_px:.1f} px')
    inl = best
    for _ in range(3):
        P = dlt(X[inl], uv[inl])
        proj, w = project_P(P, X)
        err = np.linalg.norm(proj - uv, axis=1)
        new = err < inlier_px
        if new.sum() < min_points or np.array_equal(new, inl):
            break
        inl = new
    K, R, t = decompose(P)
    depth = X[inl] @ R[2] + t[2]
    if np.mean(depth > 0) < 0.5:
        return InitResult(False, 'init_failed',
                          f'camera {name}: decomposed camera has the points behind it')
    if not (K[0, 0] > 0 and K[1, 1] > 0) or abs(K[0, 1]) > 0.1 * K[0, 0]:
        return InitResult(False, 'init_failed',
                          f'camera {name}: implausible intrinsics from DLT '
                          f'(fx {K[0, 0]:.1f}, fy {K[1, 1]:.1f}, skew {K[0, 1]:.1f})')
    cam = Camera(name, width, height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.zeros(5), R, t)
    rms = float(np.sqrt(np.mean(np.sum((cam.project(X[inl]) - uv[inl]) ** 2, axis=1))))
    return InitResult(True, 'ok', f'camera {name}: DLT on {int(inl.sum())} of {n} points, '
                      f'{rms:.2f} px rms', cam, inl, rms)


def initialise_with_intrinsics(name, width, height, X, uv, given: IntrinsicsPrior,
                               inlier_px=None, min_points=MIN_POINTS_PNP,
                               min_inlier_ratio=0.5) -> InitResult:
    """
    Estimate one camera's pose from X (N, 3) and uv (N, 2) with its intrinsics given.

    ``inlier_px`` defaults to 2 % of the image diagonal: the lens model is known, so only the
    robot's bias and mis-detections remain (a few pixels at most for the one, far more for
    the other).
    """
    X = np.asarray(X, float)
    uv = np.asarray(uv, float)
    if X.ndim != 2 or X.shape[1] != 3 or uv.shape != (X.shape[0], 2):
        raise ValueError(f'X must be (N, 3) and uv (N, 2); got {X.shape} and {uv.shape}')
    n = len(X)
    if n < min_points:
        return InitResult(False, 'insufficient_points',
                          f'camera {name}: {n} points, at least {min_points} needed with '
                          'given intrinsics')
    if inlier_px is None:
        inlier_px = 0.02 * float(np.hypot(width, height))
    K, dist = given.K, np.asarray(given.dist, float)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(
        X.reshape(-1, 1, 3), uv.reshape(-1, 1, 2), K, dist, iterationsCount=500,
        reprojectionError=float(inlier_px), confidence=0.999, flags=cv2.SOLVEPNP_EPNP)
    count = 0 if inl is None else len(inl)
    if not ok or count < max(min_points, int(min_inlier_ratio * n)):
        return InitResult(False, 'init_failed',
                          f'camera {name}: PnP with the given intrinsics found {count} of {n} '
                          f'points consistent within {inlier_px:.1f} px')
    mask = np.zeros(n, bool)
    mask[np.asarray(inl).reshape(-1)] = True
    rvec, tvec = cv2.solvePnPRefineLM(X[mask].reshape(-1, 1, 3), uv[mask].reshape(-1, 1, 2),
                                      K, dist, rvec, tvec)
    R = cv2.Rodrigues(rvec)[0]
    t = np.asarray(tvec, float).reshape(3)
    if np.mean(X[mask] @ R[2] + t[2] > 0) < 0.5:
        return InitResult(False, 'init_failed',
                          f'camera {name}: PnP put the points behind the camera')
    fx, fy, cx, cy = (float(v) for v in given.intrinsics)
    cam = Camera(name, width, height, fx, fy, cx, cy, dist.copy(), R, t)
    rms = float(np.sqrt(np.mean(np.sum((cam.project(X[mask]) - uv[mask]) ** 2, axis=1))))
    return InitResult(True, 'ok', f'camera {name}: PnP with the given intrinsics on '
                      f'{int(mask.sum())} of {n} points, {rms:.2f} px rms', cam, mask, rms)
