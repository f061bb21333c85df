"""The published pose and triangulation covariances against the scatter of perturbed cameras."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.core.uncertainty import pose_covariance
from armcal_ros.sim.synthetic import make_problem


def test_pose_covariance_matches_monte_carlo():
    prob = make_problem(10, 1)
    cam = prob.cameras[0]
    rng = np.random.default_rng(0)
    A = rng.normal(0, 1e-3, (6, 6))
    cov = A @ A.T
    draws = rng.multivariate_normal(np.zeros(6), cov, 20000)
    out = []
    R_wc = cam.rotation.T
    for d in draws:
        c = cam.copy()
        c.apply_pose_increment(d[:3], d[3:])
        dr = Rotation.from_matrix(c.rotation.T @ R_wc.T).as_rotvec()
        out.append(np.concatenate([c.center - cam.center, dr]))
    emp = np.cov(np.array(out).T)
    ref = pose_covariance(cam, cov)
    assert np.allclose(emp, ref, atol=0.05 * np.max(np.abs(ref)))


def test_triangulation_covariance_matches_monte_carlo():
    # Cameras perturbed by draws from a parameter covariance (cross-camera terms included),
    # the exact projections of fixed points triangulated with them: the scatter of the
    # triangulated points is the propagated covariance.
    from armcal_ros.core.evaluation import triangulate
    from armcal_ros.core.uncertainty import rms_error_mm, triangulation_covariance
    prob = make_problem(10, 3)
    cams = prob.cameras
    local = ['fx', 'fy', 'cx', 'cy', 'k1', 'wx', 'wy', 'wz', 'tx', 'ty', 'tz']
    names = [f'{c.name}/{p}' for c in cams for p in local]
    scale = np.tile([0.5, 0.5, 0.5, 0.5, 1e-3, 2e-4, 2e-4, 2e-4, 5e-4, 5e-4, 5e-4], len(cams))
    rng = np.random.default_rng(1)
    A = rng.normal(size=(len(names), len(names)))
    corr = A @ A.T / len(names) + np.eye(len(names))
    d = np.sqrt(np.diag(corr))
    cov = corr / np.outer(d, d) * np.outer(scale, scale)
    X = prob.true_points[:5]
    uv = [c.project(X) for c in cams]
    pred, own, seen = triangulation_covariance(cams, cov, names, X)
    assert np.all(seen == len(cams))
    draws = rng.multivariate_normal(np.zeros(len(names)), cov, 4000)
    out = []
    k = len(local)
    for dv in draws:
        moved = []
        for j, c in enumerate(cams):
            e = dv[j * k:(j + 1) * k]
            m = c.copy()
            m.set_intrinsics(c.intrinsics() + e[:4])
            m.dist = c.dist + np.array([e[4], 0, 0, 0, 0])
            m.apply_pose_increment(e[5:8], e[8:11])
            moved.append(m)
        out.append(triangulate(moved, uv) - X)
    out = np.array(out)                                   # (draws, n, 3)
    for i in range(len(X)):
        emp = np.cov(out[:, i].T)
        np.testing.assert_allclose(emp, pred[i], atol=0.08 * np.max(np.abs(pred[i])))
    assert rms_error_mm(pred) == pytest.approx(
        1e3 * np.sqrt(np.mean(np.sum(out ** 2, axis=2))), rel=0.05)
    # One camera's own part is part of the whole.
    for name, part in own.items():
        assert np.all(np.trace(part, axis1=1, axis2=2) > 0)
