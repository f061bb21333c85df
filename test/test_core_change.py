"""
Change detection (core/change.py): threshold, honest innovations, detection and attribution.

The cameras and points come from :mod:`armcal_ros.sim.synthetic` (arm errors 1 mm, image noise
0.3 px); the predictor is given the true cameras, so only the test itself is under test here
(the engine's use of it is in test_engine_changes.py).
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.core.change import (cap_of, ChangeMonitor, ChangeSettings, innovation,
                                    PredictionModel, reference_scales, statistics,
                                    statistics_batch, threshold)
from armcal_ros.sim.synthetic import make_problem

PIXEL_SIGMA = 0.3
ARM_SIGMA = 0.001


def _stream(n, seed, arm_shift=None):
    """Return cameras, true points, measured points and per-point dicts name -> uv."""
    prob = make_problem(n, seed, bias_sigma=0.0, point_sigma=ARM_SIGMA,
                        pixel_sigma=PIXEL_SIGMA)
    names = [c.name for c in prob.cameras]
    uvs = [dict() for _ in range(n)]
    for j, i, uv in zip(prob.obs.camera, prob.obs.point, prob.obs.uv):
        uvs[i][names[j]] = uv
    measured = prob.measured.copy()
    if arm_shift is not None:
        measured = measured + arm_shift
    return prob.cameras, prob.true_points, measured, uvs


def _model(cams):
    return PredictionModel({c.name: c for c in cams}, {c.name: PIXEL_SIGMA for c in cams},
                           ARM_SIGMA)


def test_the_cusum_threshold_gives_one_false_alarm_per_stated_number_of_views():
    rng = np.random.default_rng(0)
    for c, alpha in [(4.0, 1e-3), (3.0, 1e-3), (4.0, 1e-4)]:
        h = threshold(c, alpha)
        g = np.minimum(rng.chisquare(2, 2_000_000), cap_of(c)) - c
        S, alarms = 0.0, 0
        for x in g:
            S = max(0.0, S + x)
            if S > h:
                alarms += 1
                S = 0.0
        assert alarms / len(g) == pytest.approx(alpha, rel=0.3)


def test_innovations_of_an_unchanged_cell_are_chi_square_with_two_degrees():
    cams, _, measured, uvs = _stream(400, 1)
    model = _model(cams)
    d2 = [innovation(model, X, obs, name)[2] for X, obs in zip(measured, uvs) for name in obs
          if len(obs) > 1]
    # chi^2_2 has mean 2; the sample mean of ~1000 values is within 10 % of it.
    assert np.mean(d2) == pytest.approx(2.0, rel=0.1)
    scales = reference_scales(model, measured, uvs)
    assert all(0.8 < k < 1.25 for k in scales.values())


def test_batched_statistics_equal_the_per_sample_ones():
    """Every camera's d^2 over many samples at once equals the per-sample computation."""
    cams, _, measured, uvs = _stream(150, 4)
    rng = np.random.default_rng(4)
    # Some samples seen by one camera only, one camera unknown to the model, and a
    # parameter covariance on one camera (the prediction's extra term).
    for o in uvs[:20]:
        for name in list(o)[1:]:
            del o[name]
    uvs[30]['cam_not_modelled'] = np.array([1.0, 2.0])
    A = rng.normal(size=(14, 14)) * 1e-3
    names = ['fx', 'fy', 'cx', 'cy', 'k1', 'k2', 'p1', 'p2', 'wx', 'wy', 'wz', 'tx', 'ty', 'tz']
    model = PredictionModel({c.name: c for c in cams}, {c.name: PIXEL_SIGMA for c in cams},
                            ARM_SIGMA, {cams[0].name: (names, A @ A.T)})
    batch = statistics_batch(model, measured, uvs)
    compared = 0
    for i, (X, obs) in enumerate(zip(measured, uvs)):
        one = statistics(model, X, obs)
        for name, d2 in batch.items():
            if name in one:
                assert d2[i] == pytest.approx(one[name], rel=1e-9)
                compared += 1
            else:
                assert np.isnan(d2[i])
    assert compared > 300


def test_an_unchanged_cell_raises_no_alarm():
    for seed in range(3):
        cams, _, measured, uvs = _stream(600, 10 + seed)
        model = _model(cams)
        mon = ChangeMonitor(model, reference_scales(model, measured[:100], uvs[:100]))
        events = [mon.observe(X, obs, k) for k, (X, obs) in enumerate(zip(measured, uvs))]
        assert not any(events)


def _knock(cam, deg, rng):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    knocked = cam.copy()
    C = cam.center
    knocked.rotation = Rotation.from_rotvec(np.radians(deg) * axis).as_matrix() @ cam.rotation
    knocked.translation = -knocked.rotation @ C
    return knocked


@pytest.mark.parametrize('deg', [0.25, 1.0])
def test_a_knocked_camera_is_found_within_a_few_samples_and_named(deg):
    cams, X, measured, uvs = _stream(300, 3)
    model = _model(cams)
    mon = ChangeMonitor(model, reference_scales(model, measured[:100], uvs[:100]))
    rng = np.random.default_rng(4)
    knocked = _knock(cams[1], deg, rng)
    change_at = 150
    event = None
    for k in range(len(X)):
        obs = dict(uvs[k])
        if k >= change_at and cams[1].name in obs:
            obs[cams[1].name] = knocked.project(X[k:k + 1])[0] + rng.normal(0, PIXEL_SIGMA, 2)
        event = mon.observe(measured[k], obs, k)
        if event is not None:
            break
    assert event is not None and k < change_at + 10
    assert event.kind == 'camera' and event.camera == cams[1].name
    assert event.onset_ns >= change_at
    # The knocked camera is no longer predicted; the others still are.
    assert cams[1].name not in mon.model.cameras and not mon.paused


def test_a_marker_that_moved_on_the_arm_is_told_from_a_camera_that_moved():
    cams, X, measured, uvs = _stream(300, 5)
    model = _model(cams)
    mon = ChangeMonitor(model, reference_scales(model, measured[:100], uvs[:100]))
    change_at = 120
    event = None
    for k in range(len(X)):
        Xk = measured[k] + (np.array([0.0, 0.006, -0.004]) if k >= change_at else 0.0)
        event = mon.observe(Xk, uvs[k], k)
        if event is not None:
            break
    assert event is not None and k < change_at + 10
    assert event.kind == 'arm', event.evidence
    # It keeps watching: a second alarm in a row confirms an arm change (change_tracking).
    assert not mon.paused and not mon.busy


def test_settings_are_checked_with_their_names():
    with pytest.raises(ValueError, match='reference'):
        ChangeSettings(reference=1.5).validate()
    with pytest.raises(ValueError, match='false_alarm'):
        ChangeSettings(false_alarm=0.7).validate()
    with pytest.raises(ValueError, match='arm_sigma'):
        PredictionModel({}, {}, 0.0)
