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


def _rms_z(adj, truth):
    """Return the z-scores of fx, fy, cx, cy, the centre and the rotation of every camera."""
    from armcal_ros.core.evaluation import z_scores
    skip = ('k1', 'k2')
    return np.array([v for name, e in adj.cameras.items()
                     for k, v in z_scores(e.camera, e.std, truth[name]).items() if k not in skip])


@pytest.mark.slow
def test_published_standard_deviations_cover_the_truth():
    # bench/uncertainty.py in small: three seeds of the PUMA cell under linkage errors, the
    # image noise estimated.  A covariance off by a factor 2 in variance puts the RMS z at
    # 1.41 or 0.71: the bounds.  The fixed model alone ignores the arm's errors and is
    # overconfident (1.76 here, 2.25 over 20 seeds); published (widened under auto's choice)
    # it and auto itself are honest (0.96 and 1.00 here).
    from armcal_ros.core.adjustment import SolverSettings
    from armcal_ros.core.calibration import calibrate
    from armcal_ros.core.priors import PriorSettings
    from armcal_ros.sim.robot_points import make_robot_problem
    s = SolverSettings(pixel_sigma=0.5, estimate_noise=True)
    z = {'fixed alone': [], 'fixed': [], 'auto': []}
    for seed in range(3):
        p = make_robot_problem('geometric', 200, seed, pixel_sigma=0.3, n_test=10)
        truth = p.truth if isinstance(p.truth, dict) else {c.name: c for c in p.truth}
        auto = calibrate(p.specs, p.measured, p.obs, PriorSettings('auto'), s,
                         kinematics=p.kinematics)
        ref = auto.selection.settings
        alone = calibrate(p.specs, p.measured, p.obs, PriorSettings('fixed'), s)
        fixed = calibrate(p.specs, p.measured, p.obs, PriorSettings('fixed'), s,
                          kinematics=p.kinematics, reference=ref)
        assert fixed.uncertainty == f'widened under {ref.model}'
        assert 0.2 < alone.pixel_sigma < 0.5 and alone.noise_source == 'residuals'
        z['fixed alone'] += list(_rms_z(alone.adjustment, truth))
        z['fixed'] += list(_rms_z(fixed.adjustment, truth))
        z['auto'] += list(_rms_z(auto.adjustment, truth))
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in z.items()}
    assert rms['fixed alone'] > 1.5, rms
    assert 0.7 < rms['fixed'] < 1.4, rms
    assert 0.7 < rms['auto'] < 1.4, rms
