"""
The adjustment: exact recovery, limits between priors, outliers, and cross-checks with peers.

Tolerances: noise-free problems must be solved to numerical precision (relative 1e-6); where noise
is present, differences are compared with the adjustment's own standard deviations.
"""
from dataclasses import replace

import cv2
import numpy as np
import pytest
from scipy.linalg import cholesky, solve_triangular
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from armcal_ros.core.adjustment import _inv3, adjust, Observations, SolverSettings
from armcal_ros.core.calibration import calibrate, CameraSpec
from armcal_ros.core.camera import Camera, project
from armcal_ros.core.kernels import kernel_matrix
from armcal_ros.core.priors import PriorSettings
from armcal_ros.sim.synthetic import make_problem


def _cam_vector(c):
    return np.concatenate([c.intrinsics(), c.dist, c.center])


@pytest.mark.parametrize('model', ['fixed', 'independent', 'correlated'])
def test_every_prior_recovers_true_cameras_from_noise_free_data(model):
    prob = make_problem(150, 11, bias_sigma=0.0, pixel_sigma=0.0)
    # Without the weak distortion prior, which by design pulls terms the views leave loose.
    res = calibrate(prob.specs, prob.true_points, prob.obs, PriorSettings(model),
                    SolverSettings(pixel_sigma=0.3, distortion_sigma=None))
    assert res.success, res.message
    assert res.adjustment.inliers.all()
    for cam in prob.cameras:
        est = res.cameras[cam.name]
        ref = _cam_vector(cam)
        got = _cam_vector(est)
        scale = np.maximum(np.abs(ref), [1, 1, 1, 1, 1e-2, 1e-2, 1e-3, 1e-3, 1e-2, 1, 1, 1])
        assert np.max(np.abs(got - ref) / scale) < 1e-6, cam.name
    assert np.allclose(res.adjustment.points, prob.true_points, atol=1e-9)


def test_correlated_with_vanishing_bias_equals_independent():
    prob = make_problem(120, 5)
    s = SolverSettings(pixel_sigma=0.3)
    ind = calibrate(prob.specs, prob.measured, prob.obs,
                    PriorSettings('independent', point_sigma=2e-4), s)
    cor = calibrate(prob.specs, prob.measured, prob.obs,
                    PriorSettings('correlated', point_sigma=2e-4, bias_sigma=1e-9), s)
    assert cor.adjustment.covariance is not None
    for name in ind.cameras:
        a, b = ind.adjustment.cameras[name], cor.adjustment.cameras[name]
        for k in ('fx', 'fy', 'cx', 'cy'):
            assert abs(getattr(a.camera, k) - getattr(b.camera, k)) < 1e-3 * a.std[k]
        assert np.linalg.norm(a.camera.center - b.camera.center) < 1e-3 * a.std['center_x']
    assert np.allclose(ind.adjustment.points, cor.adjustment.points, atol=1e-9)


def test_outliers_are_flagged_and_do_not_move_the_answer():
    clean = make_problem(300, 7, pixel_sigma=0.3)
    dirty = make_problem(300, 7, pixel_sigma=0.3, outlier_fraction=0.05)
    s = SolverSettings(pixel_sigma=0.3)
    prior = PriorSettings('independent')
    a = calibrate(clean.specs, clean.measured, clean.obs, prior, s)
    b = calibrate(dirty.specs, dirty.measured, dirty.obs, prior, s)
    assert b.success, b.message
    flagged = ~b.adjustment.inliers
    assert np.all(flagged[dirty.outliers]), 'every planted outlier must be gated'
    assert flagged[~dirty.outliers].mean() < 0.01, 'few good observations may be gated'
    for name, est in a.adjustment.cameras.items():
        other = b.adjustment.cameras[name]
        for k in ('fx', 'fy', 'cx', 'cy'):
            assert abs(getattr(est.camera, k) - getattr(other.camera, k)) < 2 * est.std[k]
        d = np.abs(est.camera.center - other.camera.center)
        sd = np.array([est.std['center_x'], est.std['center_y'], est.std['center_z']])
        assert np.all(d < 2 * sd)


def test_single_camera_fixed_matches_opencv_calibrate_camera():
    prob = make_problem(200, 3, bias_sigma=0.0, pixel_sigma=0.3, n_cameras=1)
    cam = prob.cameras[0]
    sel = prob.obs.camera == 0
    X = prob.true_points[prob.obs.point[sel]]
    uv = prob.obs.uv[sel]
    s = SolverSettings(pixel_sigma=0.3, loss='none', gate_min_px=1e6, distortion_sigma=None,
                       free_distortion=('k1', 'k2', 'p1', 'p2'))
    ours = calibrate([CameraSpec('cam1', 640, 480)], X,
                     Observations(np.zeros(len(X)), np.arange(len(X)), uv),
                     PriorSettings('fixed'), s)
    est = ours.adjustment.cameras['cam1']
    K0 = ours.init['cam1'].camera.K
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    rms, K, d, rv, tv = cv2.calibrateCamera(
        [X.astype(np.float32)], [uv.astype(np.float32)], (640, 480), K0.copy(), np.zeros(5),
        flags=flags, criteria=crit)
    d = d.reshape(-1)
    for k, v in zip(('fx', 'fy', 'cx', 'cy'), (K[0, 0], K[1, 1], K[0, 2], K[1, 2])):
        assert abs(getattr(est.camera, k) - v) < 0.05 * est.std[k], k
    for i, k in enumerate(('k1', 'k2', 'p1', 'p2')):
        assert abs(est.camera.dist[i] - d[i]) < 0.05 * est.std[k], k
    assert abs(est.rms_px - rms) < 1e-3
    # and both within noise of the truth
    assert abs(est.camera.fx - cam.fx) < 4 * est.std['fx']


def test_correlated_optimum_matches_scipy_least_squares():
    """Same objective (image + whitened correlated prior), minimised by scipy's TRF."""
    prob = make_problem(40, 9, pixel_sigma=0.3)
    prior = PriorSettings('correlated', point_sigma=2e-4, bias_sigma=1e-3, coherence_length=0.3)
    s = SolverSettings(pixel_sigma=0.3, loss='none', gate_min_px=1e6, free_distortion=('k1',),
                       distortion_sigma=None)
    ours = calibrate(prob.specs, prob.measured, prob.obs, prior, s)
    assert ours.success, ours.message
    cams0 = [ours.init[c.name].camera for c in prob.cameras]
    Xm = prob.measured
    n = len(Xm)
    K = 1e-6 * kernel_matrix(Xm, Xm, 0.3) + 4e-8 * np.eye(n)
    Lc = cholesky(K, lower=True)
    obs = prob.obs

    def unpack(x):
        cams = []
        for j in range(len(cams0)):
            v = x[11 * j:11 * (j + 1)]
            R = Rotation.from_rotvec(v[5:8]).as_matrix()
            cams.append((v[:4], np.array([v[4], 0, 0, 0, 0]), R, v[8:11]))
        return cams, x[11 * len(cams0):].reshape(n, 3)

    def fun(x):
        cams, X = unpack(x)
        r = []
        for j, (intr, dist, R, t) in enumerate(cams):
            m = obs.camera == j
            r.append(((project(intr, dist, R, t, X[obs.point[m]]) - obs.uv[m]) / 0.3).ravel())
        r.append(solve_triangular(Lc, X - Xm, lower=True).ravel())
        return np.concatenate(r)

    x0 = np.concatenate([np.concatenate([c.intrinsics(), [0.0], c.rvec, c.translation])
                         for c in cams0] + [Xm.ravel()])
    sol = least_squares(fun, x0, method='trf', x_scale='jac', xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, max_nfev=2000)
    assert np.sum(sol.fun ** 2) == pytest.approx(ours.adjustment.cost, rel=1e-7)
    cams, X = unpack(sol.x)
    for j, c in enumerate(prob.cameras):
        est = ours.adjustment.cameras[c.name]
        assert abs(cams[j][0][0] - est.camera.fx) < 1e-3 * est.std['fx']
        centre = -cams[j][2].T @ cams[j][3]
        assert np.linalg.norm(centre - est.camera.center) < 1e-3 * est.std['center_x']
    # 1 um: far below the points' own uncertainty (about 0.2 mm); our ftol stops earlier.
    assert np.allclose(X, ours.adjustment.points, atol=1e-6)


def test_a_camera_with_too_few_points_is_reported_and_the_rest_calibrate():
    prob = make_problem(150, 2)
    keep = ~((prob.obs.camera == 2) & (prob.obs.point >= 5))
    obs = prob.obs.subset(keep)
    res = calibrate(prob.specs, prob.measured, obs, PriorSettings('independent'),
                    SolverSettings(pixel_sigma=0.3))
    assert res.status == 'partial'
    assert 'cam3' in res.message and 'at least' in res.message
    assert set(res.cameras) == {'cam1', 'cam2'}


def test_bad_arguments_name_themselves():
    prob = make_problem(30, 1)
    with pytest.raises(ValueError, match='measured'):
        adjust(prob.cameras, prob.measured[:, :2], prob.obs)
    with pytest.raises(ValueError, match='pixel_sigma'):
        adjust(prob.cameras, prob.measured, prob.obs, settings=SolverSettings(pixel_sigma=0))
    with pytest.raises(ValueError, match='free_distortion'):
        SolverSettings(free_distortion=('k9',)).validate()
    with pytest.raises(ValueError, match='loss'):
        SolverSettings(loss='tukey').validate()
    with pytest.raises(ValueError, match='uv'):
        Observations([0], [0], [[np.nan, 1.0]])


@pytest.mark.slow
def test_reported_standard_deviations_match_the_scatter():
    """Over 30 noise draws the scatter of fx and the centre matches the predicted std."""
    base = make_problem(200, 21, bias_sigma=0.0, pixel_sigma=0.0)
    rng = np.random.default_rng(0)
    s = SolverSettings(pixel_sigma=0.5, loss='none', gate_min_px=1e6)
    fx, cz, sd_fx, sd_cz = [], [], [], []
    warm = {c.name: c for c in base.cameras}
    for _ in range(30):
        obs = replace(base.obs, uv=base.obs.uv + rng.normal(0, 0.5, base.obs.uv.shape))
        r = calibrate(base.specs, base.true_points, obs, PriorSettings('fixed'), s, initial=warm)
        e = r.adjustment.cameras['cam1']
        fx.append(e.camera.fx)
        cz.append(e.camera.center[2])
        sd_fx.append(e.std['fx'])
        sd_cz.append(e.std['center_z'])
    assert 0.6 < np.std(fx) / np.mean(sd_fx) < 1.5
    assert 0.6 < np.std(cz) / np.mean(sd_cz) < 1.5
    assert isinstance(base.cameras[0], Camera)


def test_inv3_matches_lapack_on_point_blocks_of_every_conditioning():
    """The adjugate inverse of the 3x3 point blocks is as accurate as LAPACK's LU (cond * eps)."""
    rng = np.random.default_rng(7)
    for cond in (1.0, 1e3, 1e6, 1e9):
        Q = Rotation.random(200, random_state=rng).as_matrix()
        ev = np.exp(rng.uniform(0.0, np.log(cond), (200, 3)))
        ev[:, 0] = 1.0
        V = np.einsum('nij,nj,nkj->nik', Q, ev * 3e6, Q)          # SPD, eigenvalues 3e6..
        ref = np.linalg.inv(V)
        err = np.max(np.abs(_inv3(V) - ref)) / np.max(np.abs(ref))
        assert err < 1e-12 * cond + 1e-14, (cond, err)


def test_a_camera_whose_fit_explains_a_minority_of_its_points_is_degenerate():
    # cam2's views are 70 % gross mismatches (15-40 px, random direction): no calibration of
    # cam2 can come out of that, and its estimate must say so rather than claim 'ok'.
    prob = make_problem(200, 4, pixel_sigma=0.3)
    rng = np.random.default_rng(4)
    obs = prob.obs
    mine = np.flatnonzero(obs.camera == 1)
    bad = rng.choice(mine, int(0.7 * len(mine)), replace=False)
    ang = rng.uniform(0, 2 * np.pi, len(bad))
    uv = obs.uv.copy()
    uv[bad] += rng.uniform(15, 40, len(bad))[:, None] * np.column_stack([np.cos(ang),
                                                                         np.sin(ang)])
    res = calibrate(prob.specs, prob.measured, Observations(obs.camera, obs.point, uv),
                    PriorSettings('independent'), SolverSettings(pixel_sigma=0.3))
    est = res.adjustment.cameras
    assert est['cam2'].status == 'degenerate', (est['cam2'].n_inliers, len(mine))
    assert 'observations fit' in est['cam2'].message
    assert est['cam1'].status == 'ok' and est['cam3'].status == 'ok'


def test_a_camera_with_fewer_equations_than_parameters_is_degenerate():
    prob = make_problem(150, 6, pixel_sigma=0.3)
    obs = prob.obs
    mine = np.flatnonzero(obs.camera == 2)
    keep = np.ones(len(obs.camera), bool)
    keep[mine[6:]] = False           # 6 points: 12 equations for 14 parameters
    sub = Observations(obs.camera[keep], obs.point[keep], obs.uv[keep])
    # From the true cameras: the initialisation would refuse 6 points, a solve that kept only
    # 6 of a camera's points as inliers must not pass them off as a calibration either.
    res = adjust(prob.cameras, prob.measured, sub, PriorSettings('independent'),
                 SolverSettings(pixel_sigma=0.3))
    est = res.cameras['cam3']
    assert est.status == 'degenerate'
    assert '12 equations for its 14 parameters' in est.message
    assert res.cameras['cam1'].status == 'ok'


def test_a_distortion_prior_of_the_wrong_shape_or_sign_is_refused_by_name():
    for bad in ((1.0, 1.0), (1.0, 1.0, 0.1, 0.1, 0.0)):
        with pytest.raises(ValueError, match='distortion_sigma'):
            SolverSettings(distortion_sigma=bad).validate()
    assert SolverSettings(distortion_sigma=None).validate().distortion_sigma is None
