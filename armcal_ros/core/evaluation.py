"""
Accuracy measures against ground truth, used by tests and benchmarks.

* :func:`triangulate` - multi-view triangulation: linear (DLT on undistorted normalised rays,
  Hartley and Zisserman sec. 12.2), then Gauss-Newton on the reprojection error.
* :func:`similarity_fit` - the least-squares similarity (scale, rotation, translation) between two
  point sets (Umeyama, 1991).
* :func:`score_cameras` - absolute and shape triangulation error on fresh true points,
  camera-centre error and focal error: the accuracy numbers of docs/BENCHMARKS.md.

Images fix the cameras only up to a similarity; only the robot's positions pin the absolute
frame.  So both are reported: absolute error in the robot base frame, and shape error after the
best 7-DoF similarity fit of the triangulated points to the truth.
"""

from dataclasses import dataclass
from typing import Dict, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from armcal_ros.core.camera import Camera, project_with_jacobians, undistort_normalized


def triangulate(cameras: Sequence[Camera], uv_per_camera, iterations=10):
    """
    Triangulate N points seen by several cameras.

    ``uv_per_camera`` is a list (one per camera) of (N, 2) pixel arrays with NaN rows where the
    camera does not see the point.  Points seen by fewer than two cameras come back NaN.
    Returns (N, 3).
    """
    uvs = [np.asarray(u, float) for u in uv_per_camera]
    if len(uvs) != len(cameras):
        raise ValueError(f'uv_per_camera has {len(uvs)} entries for {len(cameras)} cameras')
    n = uvs[0].shape[0]
    seen = np.stack([np.all(np.isfinite(u), axis=1) for u in uvs], axis=1)   # (N, J)
    rays = []
    for c, u in zip(cameras, uvs):
        r = np.full((n, 2), np.nan)
        ok = np.all(np.isfinite(u), axis=1)
        if ok.any():
            r[ok] = undistort_normalized(c, u[ok])
        rays.append(r)
    X = np.full((n, 3), np.nan)
    # Linear: for each view, x (P3 X) - P1 X = 0 and y (P3 X) - P2 X = 0 on normalised rays.
    A = np.zeros((n, 2 * len(cameras), 4))
    for j, c in enumerate(cameras):
        P = np.hstack([c.rotation, c.translation[:, None]])
        r = np.where(seen[:, j:j + 1], rays[j], 0.0)
        A[:, 2 * j] = r[:, :1] * P[2] - P[0]
        A[:, 2 * j + 1] = r[:, 1:2] * P[2] - P[1]
        A[~seen[:, j], 2 * j:2 * j + 2] = 0.0
    enough = seen.sum(axis=1) >= 2
    if enough.any():
        _, _, Vt = np.linalg.svd(A[enough])
        h = Vt[:, -1, :]
        X[enough] = h[:, :3] / h[:, 3:4]
    # Nonlinear refinement of the reprojection error (3x3 normal equations per point).
    for _ in range(iterations):
        H = np.zeros((n, 3, 3))
        g = np.zeros((n, 3))
        for j, c in enumerate(cameras):
            m = seen[:, j] & enough
            if not m.any():
                continue
            J = project_with_jacobians(c.intrinsics(), c.dist, c.rotation, c.translation, X[m])
            r = J.uv - uvs[j][m]
            H[m] += np.einsum('mki,mkj->mij', J.d_point, J.d_point)
            g[m] += np.einsum('mki,mk->mi', J.d_point, r)
        if not enough.any():
            break
        dx = np.linalg.solve(H[enough] + 1e-12 * np.eye(3), -g[enough][..., None])[..., 0]
        X[enough] += dx
        if np.max(np.abs(dx)) < 1e-12:
            break
    return X


@dataclass
class Similarity:
    """x -> scale * R x + t."""

    scale: float
    rotation: np.ndarray
    translation: np.ndarray

    def apply(self, X):
        """Map points (N, 3)."""
        return self.scale * np.asarray(X) @ self.rotation.T + self.translation


def similarity_fit(source, target, with_scale=True) -> Similarity:
    """
    Least-squares similarity mapping ``source`` onto ``target`` (Umeyama, 1991).

    Minimises sum |target_i - (s R source_i + t)|^2 over s > 0, R in SO(3), t.
    """
    A = np.asarray(source, float)
    B = np.asarray(target, float)
    if A.shape != B.shape or A.ndim != 2 or A.shape[1] != 3:
        raise ValueError(f'source and target must both be (N, 3), got {A.shape}, {B.shape}')
    ma, mb = A.mean(axis=0), B.mean(axis=0)
    a, b = A - ma, B - mb
    C = b.T @ a / len(A)
    U, S, Vt = np.linalg.svd(C)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1.0
    R = U @ D @ Vt
    var_a = np.sum(a * a) / len(A)
    s = float(np.trace(np.diag(S) @ D) / var_a) if with_scale else 1.0
    return Similarity(s, R, mb - s * R @ ma)


def shape_error(estimate, truth):
    """RMS distance (same units) after the best similarity fit of ``estimate`` onto ``truth``."""
    sim = similarity_fit(estimate, truth)
    return float(np.sqrt(np.mean(np.sum((sim.apply(estimate) - truth) ** 2, axis=1))))


def absolute_error(estimate, truth):
    """RMS distance between corresponding points."""
    d = np.asarray(estimate) - np.asarray(truth)
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


@dataclass
class Score:
    """Accuracy of a set of estimated cameras against the truth (mm, %, px)."""

    absolute_mm: float
    shape_mm: float
    centre_mm: float
    focal_pct: float
    reprojection_px: float
    per_camera: Dict[str, Dict[str, float]]


def score_cameras(estimated: Dict[str, Camera], truth: Dict[str, Camera], test_points,
                  pixel_noise=0.0, rng=None) -> Score:
    """
    Score cameras by triangulating fresh true points projected by the true cameras.

    ``test_points`` (N, 3) are true points; their true projections (plus ``pixel_noise``) are
    triangulated with the estimated cameras.  Absolute error is the RMS 3-D error (mm), shape error
    the RMS error after the best similarity fit (mm).  Camera-centre error is the RMS over cameras
    (mm) and focal error the mean over cameras of |f_est - f_true| / f_true over fx and fy (%).
    Reprojection is the RMS (px) of projecting the true points with the estimated cameras against
    the true projections: a summary the images alone could measure, and the only point-level
    figure for a single camera (its absolute and shape errors are NaN: one view cannot
    triangulate).
    """
    rng = rng if rng is not None else np.random.default_rng(12345)
    names = [k for k in truth if k in estimated]
    if not names:
        raise ValueError(f'estimated and truth have no camera in common: estimated '
                         f'{sorted(estimated)}, truth {sorted(truth)}')
    P = np.asarray(test_points, float)
    uv_true = [truth[k].project(P) for k in names]
    inside = [(u[:, 0] >= 0) & (u[:, 0] < truth[k].width) & (u[:, 1] >= 0) &
              (u[:, 1] < truth[k].height) & truth[k].in_front(P) for u, k in zip(uv_true, names)]
    uv_obs = []
    for u, m in zip(uv_true, inside):
        v = u + (rng.normal(0.0, pixel_noise, u.shape) if pixel_noise > 0 else 0.0)
        v[~m] = np.nan
        uv_obs.append(v)
    if len(names) >= 2:
        X = triangulate([estimated[k] for k in names], uv_obs)
        ok = np.all(np.isfinite(X), axis=1)
    per = {}
    reproj = []
    for k, u, m in zip(names, uv_true, inside):
        e, t = estimated[k], truth[k]
        d = np.linalg.norm(e.project(P[m]) - u[m], axis=1)
        reproj.append(d)
        per[k] = {'centre_mm': 1000.0 * float(np.linalg.norm(e.center - t.center)),
                  'focal_pct': 50.0 * (abs(e.fx - t.fx) / t.fx + abs(e.fy - t.fy) / t.fy),
                  'reprojection_px': float(np.sqrt(np.mean(d ** 2)))}
    centre = float(np.sqrt(np.mean([v['centre_mm'] ** 2 for v in per.values()])))
    focal = float(np.mean([v['focal_pct'] for v in per.values()]))
    rp = np.concatenate(reproj)
    if len(names) >= 2:
        absolute, shape = absolute_error(X[ok], P[ok]), shape_error(X[ok], P[ok])
    else:
        absolute = shape = float('nan')
    return Score(1000.0 * absolute, 1000.0 * shape, centre, focal,
                 float(np.sqrt(np.mean(rp ** 2))), per)


def z_scores(estimated: Camera, std: Dict[str, float], truth: Camera) -> Dict[str, float]:
    """
    Return (estimate - truth) / reported std of one camera's parameters, by name.

    fx, fy, cx, cy and k1, k2 (those with a std > 0: held values have none); the optical
    centre per axis (``C<x|y|z>``, std ``center_<x|y|z>``); the rotation per axis (``r<x|y|z>``,
    std ``rot_<x|y|z>``), as the solver's increment w with R_est = exp([w]x) R_true.  Honest
    standard deviations give z of unit variance.
    """
    z = {}
    for k in ('fx', 'fy', 'cx', 'cy'):
        if std.get(k, 0) > 0:
            z[k] = (getattr(estimated, k) - getattr(truth, k)) / std[k]
    for i, k in enumerate(('k1', 'k2')):
        if std.get(k, 0) > 0:
            z[k] = (estimated.dist[i] - truth.dist[i]) / std[k]
    w = Rotation.from_matrix(estimated.rotation @ truth.rotation.T).as_rotvec()
    for a, ax in enumerate('xyz'):
        z['C' + ax] = (estimated.center[a] - truth.center[a]) / std['center_' + ax]
        z['r' + ax] = w[a] / std['rot_' + ax]
    return {k: float(v) for k, v in z.items()}
