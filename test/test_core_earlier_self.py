"""
A changed camera and its earlier self: one lens or one pose shared, and the tests that allow it.

A camera knocked (or refocused) half-way: its views before the change are camera ``cam1#1``,
those after it ``cam1``; the lens the same unless ``focal_percent`` changes it, the pose the
same unless ``knock``.
"""
import numpy as np
import pytest

from armcal_ros.core.adjustment import _Problem, adjust, Observations, SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.priors import PointPrior, PriorSettings
from armcal_ros.core.earlier_self import lens_test, pose_test
from armcal_ros.sim.synthetic import make_problem


def _knocked(pixel_sigma, seed=3, focal_percent=0.0, knock=True):
    """Return (specs, points, obs, true cameras): cam1 knocked by 1 deg and 5 mm half-way."""
    prob = make_problem(200, seed, bias_sigma=0.0, pixel_sigma=0.0)
    cams = [c.copy() for c in prob.cameras]
    old = cams[0].copy()
    old.name = 'cam1#1'
    new = cams[0]
    if knock:
        new.apply_pose_increment(np.radians([0.6, -0.5, 0.5]), np.array([0.003, -0.002, 0.003]))
    new.set_intrinsics(new.intrinsics() * np.array([1 + focal_percent / 100] * 2 + [1, 1]))
    cams.append(old)
    rng = np.random.default_rng(seed)
    X = prob.true_points
    first = np.arange(len(X)) < len(X) // 2
    ci, pi, uvs = [], [], []
    for j, c in enumerate(cams):
        uv = c.project(X)
        ok = (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & \
            (uv[:, 1] < c.height) & c.in_front(X)
        if c.name == 'cam1':
            ok &= ~first
        elif c.name == 'cam1#1':
            ok &= first
        idx = np.flatnonzero(ok)
        ci.append(np.full(idx.size, j))
        pi.append(idx)
        uvs.append(uv[idx] + rng.normal(0.0, pixel_sigma, (idx.size, 2)))
    obs = Observations(np.concatenate(ci), np.concatenate(pi), np.vstack(uvs))
    specs = list(prob.specs) + [type(prob.specs[0])('cam1#1', old.width, old.height)]
    return specs, X, obs, cams


def _recovers_exactly(specs, X, obs, truth, settings):
    """Calibrate noise-free views; assert every camera is its truth; return the result."""
    res = calibrate(specs, X, obs, PriorSettings('fixed'), settings)
    assert res.success, res.message
    for cam in truth:
        got = res.cameras[cam.name]
        assert np.allclose(got.intrinsics(), cam.intrinsics(), rtol=1e-6)
        assert np.allclose(got.center, cam.center, atol=1e-7)
        assert np.allclose(got.rotation, cam.rotation, atol=1e-8)
    return res


def test_two_epochs_of_one_lens_are_recovered_exactly_from_noise_free_views():
    specs, X, obs, truth = _knocked(0.0)
    s = SolverSettings(pixel_sigma=0.3, distortion_sigma=None, shared_lens={'cam1#1': 'cam1'})
    _recovers_exactly(specs, X, obs, truth, s)


def test_the_shared_lens_terms_gradient_is_half_the_costs():
    """g_c (J^T W r plus the shared-lens term) against central differences of F / 2."""
    specs, X, obs, truth = _knocked(0.2)
    cams = [c.copy() for c in truth]
    cams[-1].set_intrinsics(cams[-1].intrinsics() + [2.0, -1.5, 0.8, 0.4])
    cams[-1].dist = cams[-1].dist + np.array([0.01, -0.02, 0.001, 0.0, 0.0])
    s = SolverSettings(pixel_sigma=0.3, loss='none', distortion_sigma=None,
                       shared_lens={'cam1#1': 'cam1'}).validate()
    ps = PriorSettings('fixed')
    prob = _Problem(cams, X, obs, PointPrior(X, ps), s, np.ones(len(obs), bool))
    _, g_c, *_ = prob.normal_equations(cams, X)
    pc = prob.layout.per_camera
    for j in (0, len(cams) - 1):
        for k, h in ((0, 1e-3), (2, 1e-3), (4, 1e-7)):
            def cost(delta, j=j, k=k):
                moved = [c.copy() for c in cams]
                step = np.zeros(pc)
                step[k] = delta
                head = prob.layout.intrinsic_vector(moved[j]) + step[:4 + 4]
                moved[j].set_intrinsics(head[:4])
                d = moved[j].dist.copy()
                d[prob.layout.dist_idx] = head[4:]
                moved[j].dist = d
                return prob.cost(moved, X)
            fd = (cost(h) - cost(-h)) / (2 * h)
            assert g_c[j * pc + k] == pytest.approx(fd / 2, rel=1e-4, abs=1e-6)


def test_the_lens_test_keeps_one_lens_and_parts_a_refocused_one():
    # At 0.05 px a focal length is known to about 0.1 %: this workspace is shallow, so a
    # focal length trades with the distance along the axis.
    specs, X, obs, truth = _knocked(0.05)
    s = SolverSettings(pixel_sigma=0.05)
    same = lens_test(adjust(truth, X, obs, PriorSettings('fixed'), s), 'cam1#1', 'cam1')
    assert same.same, same.message
    assert same.dof == 8 and same.wald < same.wald_limit
    specs, X, obs, truth = _knocked(0.05, focal_percent=1.0)
    parted = lens_test(adjust(truth, X, obs, PriorSettings('fixed'), s), 'cam1#1', 'cam1')
    assert not parted.same and abs(parted.focal_z) > parted.focal_limit, parted.message


def test_a_lens_test_or_a_shared_lens_with_wrong_names_is_refused_by_name():
    specs, X, obs, truth = _knocked(0.3)
    adj = adjust(truth, X, obs, PriorSettings('fixed'), SolverSettings(pixel_sigma=0.3))
    with pytest.raises(ValueError, match="'cam9'"):
        lens_test(adj, 'cam9', 'cam1')
    with pytest.raises(ValueError, match='alpha'):
        lens_test(adj, 'cam1#1', 'cam1', alpha=0.0)
    with pytest.raises(ValueError, match="'cam9'"):
        pose_test(adj, 'cam1#1', 'cam9')
    for bad in ({'cam1': 'cam1'}, {'cam1': 3}):
        with pytest.raises(ValueError, match='shared_lens'):
            SolverSettings(shared_lens=bad).validate()
        with pytest.raises(ValueError, match='shared_pose'):
            SolverSettings(shared_pose=bad).validate()


def test_two_epochs_of_one_pose_are_recovered_exactly_from_noise_free_views():
    specs, X, obs, truth = _knocked(0.0, focal_percent=2.0, knock=False)
    s = SolverSettings(pixel_sigma=0.3, distortion_sigma=None, shared_pose={'cam1#1': 'cam1'})
    res = _recovers_exactly(specs, X, obs, truth, s)
    assert not np.allclose(res.cameras['cam1'].intrinsics(), res.cameras['cam1#1'].intrinsics())


def test_the_shared_pose_terms_gradient_is_half_the_costs():
    """g_c's pose entries (J^T W r plus the shared-pose term) against central differences."""
    specs, X, obs, truth = _knocked(0.2, focal_percent=2.0, knock=False)
    cams = [c.copy() for c in truth]
    cams[-1].apply_pose_increment(np.radians([0.05, -0.03, 0.02]), [0.001, -0.002, 0.0005])
    s = SolverSettings(pixel_sigma=0.3, loss='none', distortion_sigma=None,
                       shared_pose={'cam1#1': 'cam1'}).validate()
    prob = _Problem(cams, X, obs, PointPrior(X, PriorSettings('fixed')), s,
                    np.ones(len(obs), bool))
    _, g_c, *_ = prob.normal_equations(cams, X)
    pc = prob.layout.per_camera
    for j in (0, len(cams) - 1):
        for k in range(6):
            def cost(delta, j=j, k=k):
                moved = [c.copy() for c in cams]
                step = np.zeros(6)
                step[k] = delta
                moved[j].apply_pose_increment(step[:3], step[3:])
                return prob.cost(moved, X)
            h = 1e-7
            fd = (cost(h) - cost(-h)) / (2 * h)
            assert g_c[j * pc + pc - 6 + k] == pytest.approx(fd / 2, rel=1e-4), (j, k)


def test_the_pose_test_keeps_one_pose_through_a_refocus_and_parts_a_knocked_one():
    s = SolverSettings(pixel_sigma=0.05)
    specs, X, obs, truth = _knocked(0.05, focal_percent=1.0, knock=False)
    same = pose_test(adjust(truth, X, obs, PriorSettings('fixed'), s), 'cam1#1', 'cam1')
    assert same.same and same.dof == 6 and same.wald < same.wald_limit, same.message
    specs, X, obs, truth = _knocked(0.05, focal_percent=1.0)
    parted = pose_test(adjust(truth, X, obs, PriorSettings('fixed'), s), 'cam1#1', 'cam1')
    assert not parted.same and parted.rotation_deg > 0.5, parted.message
