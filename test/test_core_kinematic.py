"""
The kinematic and hybrid priors: recovery of planted arm errors, observability, limits.

Problems come from :mod:`armcal_ros.sim.robot_points` (PUMA 560, three cameras, joint angles drawn
over a teleoperated arm's ranges).  Noise-free problems must be solved to the linearisation error
of the kinematic model (|dp|^2 x reach, about a micrometre).
"""
from dataclasses import replace

import numpy as np
import pytest

from armcal_ros.core.adjustment import adjust, Observations, SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.evaluation import shape_error
from armcal_ros.core.kinematic_prior import (DEFAULT_KINEMATIC_SCALES, KinematicData,
                                             kinematic_sigmas)
from armcal_ros.core.priors import PriorSettings
from armcal_ros.sim.robot_points import make_robot_problem

DEG = np.pi / 180.0
PLANTED = {'joint_2/offset': 0.08 * DEG, 'joint_3/offset': -0.06 * DEG,
           'joint_5/offset': 0.1 * DEG, 'joint_3/tx': 0.4e-3, 'joint_4/tz': -0.3e-3,
           'joint_4/offset': 0.05 * DEG}


def _planted_problem(n=250, seed=3):
    """Noise-free problem whose true arm differs from the nominal one by PLANTED only."""
    prob = make_robot_problem('geometric', n, seed, pixel_sigma=0.0, n_test=50)
    chain = prob.robot.chain
    errors = np.zeros(chain.n_errors)
    for k, v in PLANTED.items():
        errors[chain.error_names.index(k)] = v
    X = chain.fk(prob.q, prob.robot.point, errors)
    uv = np.zeros_like(prob.obs.uv)
    for j, c in enumerate(prob.cameras):
        m = prob.obs.camera == j
        uv[m] = c.project(X[prob.obs.point[m]])
    obs = Observations(prob.obs.camera, prob.obs.point, uv)
    return prob, X, obs, errors


def test_kinematic_recovers_planted_offsets_and_link_errors():
    prob, X, obs, errors = _planted_problem()
    names = list(PLANTED)
    full = prob.kinematics
    cols = [full.names.index(k) for k in names]
    kin = KinematicData(full.jacobian[:, :, cols], names)
    s = SolverSettings(pixel_sigma=0.3)
    # A wide prior (50 x the defaults) so that no shrinkage hides what the data determine.
    res = calibrate(prob.specs, prob.measured, obs, PriorSettings('kinematic',
                                                                  kinematic_scale=50.0), s,
                    kinematics=kin)
    assert res.success, res.message
    est = res.adjustment.kinematic_errors
    for k, v in PLANTED.items():
        assert abs(est[k] - v) < 0.01 * abs(v) + 2e-7, (k, est[k], v)
    assert np.max(np.linalg.norm(res.adjustment.points - X, axis=1)) < 5e-6
    for cam in prob.cameras:
        assert np.linalg.norm(res.cameras[cam.name].center - cam.center) < 2e-5


def test_full_redundant_error_set_recovers_the_points_and_stays_finite():
    """All 48 parameters (redundant: rz = offset, base frame unobservable): nothing wanders."""
    prob, X, obs, errors = _planted_problem()
    scale = 10.0
    res = calibrate(prob.specs, prob.measured, obs, PriorSettings('kinematic',
                                                                  kinematic_scale=scale),
                    SolverSettings(pixel_sigma=0.3), kinematics=prob.kinematics)
    assert res.success, res.message
    adj = res.adjustment
    bias = np.sqrt(np.mean(np.sum((X - prob.measured) ** 2, axis=1)))
    assert shape_error(adj.points, X) < 0.01 * bias
    sig = dict(zip(prob.kinematics.names, scale * prob.kinematics.sigma))
    # The base joint's origin translation is a rigid motion of everything the images cannot
    # see: its estimate stays at the prior mean and its posterior spread at the prior's.
    for k in ('joint_1/tx', 'joint_1/ty', 'joint_1/tz'):
        assert abs(adj.kinematic_errors[k]) < 0.05 * sig[k]
        assert abs(adj.kinematic_std[k] / sig[k] - 1.0) < 0.05
    # Redundant pair offset / rz of a joint (identical Jacobian columns): the prior shares the
    # correction in proportion to their prior variances.
    a = adj.kinematic_errors['joint_3/offset']
    b = adj.kinematic_errors['joint_3/rz']
    ratio = (sig['joint_3/offset'] / sig['joint_3/rz']) ** 2
    assert abs(a - ratio * b) < 1e-6 * abs(a)
    assert np.all(np.isfinite(adj.covariance))


@pytest.fixture(scope='module')
def noisy():
    prob = make_robot_problem('mixed', 200, 5, n_test=50)
    s = SolverSettings(pixel_sigma=0.3)
    fixed = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)
    return prob, s, fixed


def _same_cameras(a, b, frac):
    for name, ea in a.cameras.items():
        eb = b.cameras[name]
        for k in ('fx', 'fy', 'cx', 'cy'):
            assert abs(getattr(ea.camera, k) - getattr(eb.camera, k)) < frac * ea.std[k], k
        assert np.linalg.norm(ea.camera.center - eb.camera.center) < frac * ea.std['center_x']


def test_hybrid_with_vanishing_field_is_kinematic(noisy):
    prob, s, fixed = noisy
    c0, inl = fixed.adjustment.camera_list(), fixed.adjustment.inliers
    kin = adjust(c0, prob.measured, prob.obs, PriorSettings('kinematic'), s, inliers=inl,
                 kinematics=prob.kinematics)
    hyb = adjust(c0, prob.measured, prob.obs, PriorSettings('hybrid', bias_sigma=1e-9), s,
                 inliers=inl, kinematics=prob.kinematics)
    _same_cameras(kin, hyb, 1e-3)
    assert np.allclose(kin.points, hyb.points, atol=1e-8)


def test_hybrid_with_vanishing_kinematic_scales_is_correlated(noisy):
    prob, s, fixed = noisy
    c0, inl = fixed.adjustment.camera_list(), fixed.adjustment.inliers
    ps = PriorSettings('correlated', bias_sigma=5e-4, coherence_length=0.2,
                       field_form='lattice')
    cor = adjust(c0, prob.measured, prob.obs, ps, s, inliers=inl)
    hyb = adjust(c0, prob.measured, prob.obs, replace(ps, model='hybrid', kinematic_scale=0.0),
                 s, inliers=inl, kinematics=prob.kinematics)
    _same_cameras(cor, hyb, 1e-3)
    assert np.allclose(cor.points, hyb.points, atol=1e-8)
    assert abs(cor.log_evidence - hyb.log_evidence) < 1e-6 * abs(cor.log_evidence)


def test_kinematic_models_need_joint_angles_and_validate_inputs(noisy):
    prob, s, _ = noisy
    with pytest.raises(ValueError, match='kinematics'):
        calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('kinematic'), s)
    with pytest.raises(ValueError, match='jacobian'):
        KinematicData(np.zeros((5, 2, 3)), ['a/offset', 'a/tx', 'a/ty'])
    with pytest.raises(ValueError, match='names'):
        KinematicData(np.zeros((5, 3, 3)), ['a/offset'])
    with pytest.raises(ValueError, match='unknown'):
        kinematic_sigmas(['j/offset'], {'bogus': 1.0})
    with pytest.raises(ValueError, match='kinematic_scale'):
        PriorSettings('kinematic', kinematic_scale=-1).validate()


def test_default_sigmas_by_parameter_kind():
    sig = kinematic_sigmas(['j1/offset', 'j1/tx', 'j1/rz', 'tip/ty', 'tip/rx', 'p/offset'],
                           prismatic=['p'])
    d = DEFAULT_KINEMATIC_SCALES
    assert np.allclose(sig, [d['offset'], d['translation'], d['rotation'],
                             d['tip_translation'], d['tip_rotation'], d['prismatic_offset']])


def test_tip_place_is_the_moved_guess_with_its_propagated_std():
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from armcal_ros.core.kinematic_prior import tip_place, TIP_BLOCK
    names = ['joint_1/offset'] + list(TIP_BLOCK)
    sigma = kinematic_sigmas(names, {'tip_translation': 0.1})
    rng = np.random.default_rng(0)
    A = rng.normal(size=(7, 7))
    cov_g = 1e-3 * (A @ A.T + 7 * np.eye(7))          # whitened posterior covariance
    g = np.array([0.3, 0.2, -0.1, 0.05, 1.0, -2.0, 0.5])
    dp = g * sigma
    result = SimpleNamespace(
        prior=SimpleNamespace(kinematics=SimpleNamespace(names=names, sigma=sigma),
                              global_slices={'kinematic': slice(2, 9)}),
        prior_settings=SimpleNamespace(kinematic_scale=1.0),
        kinematic_errors=dict(zip(names, dp)),
        global_covariance=np.pad(cov_g, ((2, 0), (2, 0))) + np.diag([1, 1] + [0] * 7))
    m0 = np.array([0.05, -0.02, 0.1])
    place, std = tip_place(result, m0)
    np.testing.assert_allclose(place, Rotation.from_rotvec(dp[4:]).apply(m0) + dp[1:4])
    # Monte Carlo through the exact map p = Exp(r) m0 + t.
    draws = rng.multivariate_normal(g, cov_g, 20000) * sigma
    p = Rotation.from_rotvec(draws[:, 4:]).apply(m0) + draws[:, 1:4]
    np.testing.assert_allclose(std, p.std(axis=0), rtol=0.03)
    result.prior.kinematics.names = names[:4]
    assert tip_place(result, m0) is None
