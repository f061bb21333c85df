"""
The online engine: when it solves, warm starts, refusing worse results, save and resume.

Point samples come from :mod:`armcal_ros.sim.synthetic`; board samples from the board scene's
Cartesian robot (``board_joint_bag`` of conftest.py, helpers/board_scene.py).
"""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.priors import PriorSettings
from armcal_ros.engine import CalibrationEngine, EngineSettings
from armcal_ros.frontend.samples import BoardTarget, Observation
from armcal_ros.io.results_files import load_calibration
from armcal_ros.offline import collect_samples
from armcal_ros.settings import load_settings
from armcal_ros.sim.synthetic import make_problem
from helpers.board_scene import BOARD, check_mount, joint_params, K
from helpers.point_samples import samples_of as _samples


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _engine(prob, clock, samples=(), model='independent', **kw):
    """Build an engine for the cameras of ``prob`` (pixel sigma 0.3); add ``samples``."""
    s = EngineSettings([c.name for c in prob.cameras], PriorSettings(model),
                       SolverSettings(pixel_sigma=0.3), **kw)
    eng = CalibrationEngine(s, clock=clock)
    for c in prob.cameras:
        eng.set_image_size(c.name, c.width, c.height)
    for smp in samples:
        eng.add_sample(smp)
    return eng


def test_solve_schedule_first_solve_and_warm_start():
    prob = make_problem(160, 3)
    clock = Clock()
    samples = _samples(prob)
    eng = _engine(prob, clock, samples[:59], min_samples=60, solve_period_s=5.0,
                  min_new_samples=10)
    due, why = eng.solve_due()
    assert not due and '59 of 60' in why
    eng.add_sample(samples[59])
    assert eng.solve_due()[0]
    out = eng.solve()
    assert out.accepted, out.reason
    first = eng.current
    assert first.n_samples == 60 and set(first.cameras) == {'cam1', 'cam2', 'cam3'}
    assert not eng.solve_due()[0]
    for s in samples[60:65]:
        eng.add_sample(s)
    clock.t = 10.0
    assert not eng.solve_due()[0], 'five new samples are fewer than min_new_samples'
    for s in samples[65:]:
        eng.add_sample(s)
    assert eng.maybe_solve_async()
    assert eng.wait(60)
    second = eng.current
    assert second is not first and second.n_samples == len(samples)
    assert eng.last_outcome.result.init['cam1'].status == 'warm_start'
    for name in second.cameras:
        assert second.cameras[name].std['fx'] < first.cameras[name].std['fx']


def test_a_clearly_worse_result_does_not_replace_a_good_one():
    prob = make_problem(240, 4)
    samples = _samples(prob)
    eng = _engine(prob, Clock(), samples[:120], min_samples=10, solve_period_s=0.0,
                  min_new_samples=1)
    assert eng.solve().accepted
    good = eng.current
    # cam2's new observations carry 3 px noise: too broad for the gate to call them outliers.
    rng = np.random.default_rng(0)
    for s in samples[120:]:
        if 'cam2' in s.observations:
            o = s.observations['cam2']
            s.observations['cam2'] = Observation(o.uv + rng.normal(0, 3.0, o.uv.shape), o.ids)
        eng.add_sample(s)
    out = eng.solve()
    assert not out.accepted and 'cam2' in out.reason
    assert eng.current is good and eng.n_rejected == 1


def test_a_degenerate_camera_is_left_out_and_keeps_its_previous_calibration():
    prob = make_problem(240, 5)
    samples = _samples(prob)
    rng = np.random.default_rng(1)

    def scramble(batch):
        # cam2 sees something else most of the time (15-40 px off, any direction).
        for s in batch:
            o = s.observations.get('cam2')
            if o is not None and rng.random() < 0.7:
                a = rng.uniform(0, 2 * np.pi)
                s.observations['cam2'] = Observation(
                    o.uv + rng.uniform(15, 40) * np.array([np.cos(a), np.sin(a)]), o.ids)
    scramble(samples[:100])
    eng = _engine(prob, Clock(), samples[:100], min_samples=10, solve_period_s=0.0,
                  min_new_samples=1)
    out = eng.solve()
    # A first solve: cam1 and cam3 published, cam2 not, and everyone told why.
    assert out.accepted, out.reason
    assert set(eng.current.cameras) == {'cam1', 'cam3'}
    assert 'cam2 not calibrated: only' in out.reason
    assert 'observations fit' in eng.current.not_calibrated['cam2']
    # ... and nothing is tested against it: the change monitor waits for a full solve.
    assert eng.changes.enabled and eng.changes.monitor is None
    # Once cam2's views are good it is calibrated; a later degenerate fit of it keeps that one.
    for s in samples[100:180]:
        eng.add_sample(s)
    assert eng.solve().accepted and set(eng.current.cameras) == {'cam1', 'cam2', 'cam3'}
    assert eng.changes.monitor is not None
    kept = eng.current.cameras['cam2']
    bad = samples[180:]
    scramble(bad)
    scramble(bad)
    for s in bad:
        eng.add_sample(s)
    out = eng.solve()
    # Over half of cam2's views are now wrong (118 of 240 fit, measured).
    assert out.accepted and 'cam2 not calibrated: only' in out.reason, out.reason
    assert eng.current.cameras['cam2'] is kept
    # report.json (the summary) says the camera is an earlier solve's, and why.
    assert 'observations fit' in eng.current.summary()['cameras']['cam2']['last_fit_unusable']
    assert 'last_fit_unusable' not in eng.current.summary()['cameras']['cam1']
    assert eng.current.cameras['cam1'].n_observations == 240     # the others moved on


def test_save_and_resume_restores_samples_and_calibration(tmp_path):
    prob = make_problem(80, 6)
    eng = _engine(prob, Clock(), _samples(prob), min_samples=10)
    assert eng.solve().accepted
    files = eng.save(tmp_path)
    assert any(f.endswith('cam1.yaml') for f in files)
    fresh = _engine(prob, Clock())
    msg = fresh.load(tmp_path)
    assert f'{len(eng.store)} samples' in msg and 'calibration' in msg
    a, b = eng.current.cameras['cam2'], fresh.current.cameras['cam2']
    assert np.allclose(a.camera.K, b.camera.K) and np.allclose(a.camera.center, b.camera.center)
    assert np.allclose(a.pose_covariance, b.pose_covariance)
    assert load_calibration(tmp_path).model == 'independent'
    assert len(fresh.store) == len(eng.store)


def test_settings_are_validated():
    with pytest.raises(ValueError, match='camera_names'):
        EngineSettings([]).validate()
    with pytest.raises(ValueError, match='min_samples'):
        EngineSettings(['a'], min_samples=0).validate()
    eng = CalibrationEngine(EngineSettings(['a']))
    with pytest.raises(ValueError, match="camera 'b'"):
        eng.set_image_size('b', 640, 480)


def test_kinematic_model_without_joint_angles_is_refused_with_the_reason():
    prob = make_problem(40, 2)
    eng = _engine(prob, Clock(), _samples(prob), 'kinematic', min_samples=10)
    out = eng.solve()
    assert not out.accepted and 'needs joint angles' in out.reason


def test_resume_does_not_solve_the_same_samples_again(tmp_path):
    prob = make_problem(60, 6)
    samples = _samples(prob)
    eng = _engine(prob, Clock(), samples[:40], min_samples=10, solve_period_s=0.0,
                  min_new_samples=1)
    assert eng.solve().accepted
    eng.save(tmp_path)
    fresh = _engine(prob, Clock(), min_samples=10, solve_period_s=0.0, min_new_samples=1)
    fresh.load(tmp_path)
    due, why = fresh.solve_due()
    assert not due and why == 'no new samples'
    fresh.add_sample(samples[40])
    assert fresh.solve_due()[0]
    # samples saved after the last solve: the restored calibration is older, so solve again
    eng.add_sample(samples[41])
    eng.save(tmp_path)
    again = _engine(prob, Clock(), min_samples=10, solve_period_s=0.0, min_new_samples=1)
    again.load(tmp_path)
    assert again.solve_due()[0]


@pytest.mark.slow
def test_engine_solves_board_samples_and_resumes_its_mount(board_joint_bag, tmp_path):
    front = collect_samples(str(board_joint_bag / 'bag'),
                            load_settings(joint_params(tmp_path / 'p.yaml', board_joint_bag)))
    board = BoardTarget(BOARD.points(), None, estimate_mount=True)
    settings = EngineSettings(['cam'], PriorSettings('correlated'),
                              SolverSettings(pixel_sigma=0.2, free_distortion=()),
                              min_samples=5, board=board, marker_link='tool0')
    eng = CalibrationEngine(settings)
    eng.set_image_size('cam', 800, 600)
    for s in front.store.samples:
        eng.add_sample(s)
    out = eng.solve()
    assert out.accepted, out.reason
    assert out.calibration.model == 'correlated+mount'
    assert abs(out.calibration.cameras['cam'].camera.fx - K[0, 0]) < 3
    T = eng.T_link_target
    check_mount(np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()]))
    eng.save(tmp_path / 'o')
    fresh = CalibrationEngine(settings)
    said = fresh.load(tmp_path / 'o')
    assert 'mount' in said and len(fresh.store) == 8
    np.testing.assert_allclose(fresh.T_link_target, T, atol=1e-6)
    with pytest.raises(ValueError, match='8 saved samples are board samples'):
        CalibrationEngine(EngineSettings(['cam'])).load(tmp_path / 'o')


def test_inlier_fractions_are_compared_as_expected_rates():
    from armcal_ros.engine import inlier_rate
    assert inlier_rate(7, 7) == pytest.approx(8 / 9)
    assert inlier_rate(0, 0) == 0.5
    # A first solve over few observations, then the first outliers found: not a fall of 0.1.
    assert inlier_rate(7, 7) - inlier_rate(12, 14) < 0.1
    # A burst of bad detections over a well-observed camera still is.
    assert inlier_rate(100, 100) - inlier_rate(85, 100) > 0.1


@pytest.mark.parametrize('old,new,clear', [
    ((7, 7), (8, 11), False),      # the real recording's first solves: 2 outliers among few
    ((7, 7), (12, 14), False),     # within the tolerated drop
    ((100, 100), (85, 100), True),   # a burst over a well-observed camera
    ((20, 20), (15, 20), True),
    ((10, 10), (7, 10), True),
    ((100, 100), (93, 100), False),  # significant, but within the tolerated drop
    ((50, 60), (55, 60), False),     # a rise
])
def test_an_inlier_fall_must_exceed_the_drop_and_the_counting_noise(old, new, clear):
    from armcal_ros.engine import inlier_fall_is_clear
    assert inlier_fall_is_clear(old, new, 0.1) is clear


def test_a_fit_without_redundancy_sets_no_yardstick():
    from armcal_ros.core.camera import Camera
    from armcal_ros.core.results import CameraCalibration
    from armcal_ros.engine import _residuals_worse

    def cam(rms, red, sigma):
        return CameraCalibration(Camera('c', 640, 480, 500, 500, 320, 240), {}, np.eye(6), rms,
                                 10, 10, red, sigma)
    # Three views fitted exactly (RMS 0, no redundancy), then an honest fit: accepted.
    assert _residuals_worse(cam(0.0, 0.0, float('nan')), cam(0.99, 20.0, 1.1), 1.5, 0.3) == ''
    # With redundancy on both sides the image noise is compared.
    assert 'image noise' in _residuals_worse(cam(0.4, 20.0, 0.5), cam(1.5, 30.0, 1.6), 1.5, 0.3)
    assert _residuals_worse(cam(0.4, 20.0, 0.5), cam(0.7, 30.0, 0.7), 1.5, 0.3) == ''
    # A calibration saved before redundancy was recorded: the RMS, as before.
    old = cam(0.4, float('nan'), float('nan'))
    assert 'reprojection RMS' in _residuals_worse(old, cam(1.5, 30.0, 1.6), 1.5, 0.3)


def test_while_views_are_disputed_the_noise_rise_allowed_is_relative():
    from armcal_ros.core.camera import Camera
    from armcal_ros.core.results import CameraCalibration
    from armcal_ros.engine import _residuals_worse

    def cam(sigma, red):
        return CameraCalibration(Camera('c', 640, 480, 500, 500, 320, 240), {}, np.eye(6),
                                 sigma, 100, 100, red, sigma)
    # A ball pooled over dwells (0.008 px), then a solve that took in the first views of a
    # knocked camera (0.25 px) while the change test weighed them: refused, though far under
    # the absolute margin of 0.3 px that applies without a dispute.
    assert 'change test' in _residuals_worse(cam(0.008, 200.0), cam(0.25, 210.0), 1.5, 0.3,
                                             disputed=True)
    assert _residuals_worse(cam(0.008, 200.0), cam(0.25, 210.0), 1.5, 0.3) == ''
    # Disputed: a rise within the ratio is accepted, one beyond it refused when both fits are
    # redundant; over five degrees of freedom each two estimates of one noise differ twofold.
    assert _residuals_worse(cam(0.008, 200.0), cam(0.0115, 210.0), 1.5, 0.3, True) == ''
    assert _residuals_worse(cam(0.008, 200.0), cam(0.013, 210.0), 1.5, 0.3, True) != ''
    assert _residuals_worse(cam(0.008, 5.0), cam(0.016, 5.0), 1.5, 0.3, True) == ''
    # The false-refusal rate at equal noise (ratio 1): 1e-3, whatever the redundancies.
    rng = np.random.default_rng(3)
    for r_old, r_new in ((10.0, 10.0), (4.0, 40.0), (200.0, 20.0)):
        a = np.sqrt(rng.chisquare(r_old, 20000) / r_old)
        b = np.sqrt(rng.chisquare(r_new, 20000) / r_new)
        refused = sum(_residuals_worse(cam(x, r_old), cam(y, r_new), 1.0, 0.3, True) != ''
                      for x, y in zip(a, b))
        assert 3 <= refused <= 45, (r_old, r_new, refused)


def test_a_single_model_publishes_its_noise_reference_and_workspace_error():
    # The fixed model on points with a smooth bias: its image noise estimated from its own
    # residuals, its covariance widened under the prior auto chooses on the same samples
    # (searched once, reused until the samples grow by half), and every camera carries the
    # 3-D error its calibration adds over the workspace.
    from dataclasses import replace
    prob = make_problem(120, 5, bias_sigma=1e-3)
    eng = _engine(prob, Clock(), _samples(prob), model='fixed', min_samples=10)
    eng.settings = replace(eng.settings, solver=SolverSettings(pixel_sigma=0.5,
                                                               estimate_noise=True))
    out = eng.solve()
    assert out.accepted, out.reason
    h = out.calibration.hyperparameters
    assert h['pixel_sigma_source'] == 'residuals' and 0.1 < h['pixel_sigma'] < 0.6
    assert h['uncertainty'].startswith('widened under'), h
    assert h['triangulation_error_mm'] > 0
    assert all(np.isfinite(c.workspace_error_mm) and c.workspace_error_mm > 0
               for c in out.calibration.cameras.values())
    ref = eng._reference
    assert eng.solve().accepted and eng._reference is ref       # not searched again


def test_problem_inputs_are_the_samples_as_the_solver_sees_them():
    prob = make_problem(40, 3)
    eng = _engine(prob, Clock())
    assert eng.problem_inputs() is None
    for smp in _samples(prob):
        eng.add_sample(smp)
    inputs = eng.problem_inputs()
    assert [s.name for s in inputs.specs] == [c.name for c in prob.cameras]
    order = np.lexsort((prob.obs.camera, prob.obs.point))
    got = np.lexsort((inputs.obs.camera, inputs.obs.point))
    np.testing.assert_allclose(inputs.points[inputs.obs.point[got]],
                               prob.measured[prob.obs.point[order]])
    np.testing.assert_allclose(inputs.obs.uv[got], prob.obs.uv[order])
    assert inputs.kinematics is None


def _lit_samples(prob, seed, observe):
    """Return samples at ``prob``'s points, each camera's view ``observe(name, uv, rng)``."""
    from armcal_ros.frontend.samples import Sample
    rng = np.random.default_rng(seed)
    names = [c.name for c in prob.cameras]
    samples = []
    for i, X in enumerate(prob.measured):
        sel = prob.obs.point == i
        obs = {names[j]: observe(names[j], uv, rng)
               for j, uv in zip(prob.obs.camera[sel], prob.obs.uv[sel])}
        samples.append(Sample(X, obs, stamp_ns=i))
    return samples


def test_under_auto_the_kind_of_centre_taken_is_solved_at_its_own_image_noise():
    """
    Centres that change kind bring their own image noise: the search of the kind taken is kept.

    Every camera's centroids carry an unsmooth 0.3 px that its pooled centres keep; its fits
    are 0.05 px off.  The first search is made with the pooled centres and estimates their
    noise; every camera then takes its fits, which must be solved at theirs, not at the pooled
    centres' (that weighs the images six times too little against the arm), in the solve
    published and in the solves between searches.
    """
    prob = make_problem(120, 4, pixel_sigma=0.0, bias_sigma=1e-6)     # exact arm points
    names = [c.name for c in prob.cameras]
    samples = _lit_samples(prob, 5, lambda name, uv, rng: Observation(
        uv + rng.normal(0, 0.05, 2), [0], n_frames=2, spread_px=0.05, centroid_spread_px=0.2,
        centroid_uv=uv + rng.normal(0, 0.3, 2)))
    eng = _engine(prob, Clock(), samples, model='auto', min_samples=10, pool_light_shift=True)
    out = eng.solve()
    assert out.accepted, out.reason
    assert {k for k, v in eng.light_pooling.items() if v.status == 'fits_kept'} == set(names)
    assert out.calibration.hyperparameters['pixel_sigma'] < 0.1
    assert eng._auto_pixel_sigma < 0.1
    again = eng.solve()                    # between searches: the fits' noise still
    assert again.accepted and again.calibration.hyperparameters['pixel_sigma'] < 0.1


def test_each_camera_uses_the_kind_of_lit_ball_centre_a_calibration_fits_better(tmp_path):
    """
    Pooled centres where they are the better, the fits where the centroids carry clutter.

    cam1's centroids are off by an unsmooth 0.3 px (a textured background), which its pooled
    centres carry, and its fits by 0.05 px; cam2's centroids are off by 0.01 px plus a
    lamp's constant shift, its fits by 0.15 px; cam3 has plain centres.  The shifts of both
    pool (their leave-one-out errors are within their frames' noise): only a calibration
    tells which kind is better.  Started the wrong way round in cam2, the choice turns back;
    it is made again when the views have doubled or after a reset, and a restart keeps when
    it was made.
    """
    prob = make_problem(120, 4, pixel_sigma=0.0, bias_sigma=1e-6)     # exact arm points

    def observe(name, uv, rng):
        if name == 'cam1':
            return Observation(uv + rng.normal(0, 0.05, 2), [0], n_frames=2, spread_px=0.05,
                               centroid_spread_px=0.2, centroid_uv=uv + rng.normal(0, 0.3, 2))
        if name == 'cam2':
            return Observation(uv + rng.normal(0, 0.15, 2), [0], n_frames=2, spread_px=0.15,
                               centroid_spread_px=0.01,
                               centroid_uv=uv + [0.3, -0.2] + rng.normal(0, 0.01, 2))
        return Observation(uv + rng.normal(0, 0.05, 2), [0])
    samples = _lit_samples(prob, 2, observe)
    eng = _engine(prob, Clock(), samples, min_samples=10, pool_light_shift=True)
    eng._fitted_centres = {'cam2'}
    out = eng.solve()
    assert out.accepted, out.reason
    pooling = eng.light_pooling
    assert set(pooling) == {'cam1', 'cam2'}
    assert pooling['cam1'].status == 'fits_kept', pooling['cam1'].message
    assert 'fitted centres are used' in pooling['cam1'].message
    assert pooling['cam2'].status == 'ok', pooling['cam2'].message
    assert 'pooled centres fit a calibration better' in pooling['cam2'].message
    # The solve published is the one with the better centres: cam1 fits its 0.05 px fits.
    assert out.calibration.cameras['cam1'].rms_px < 0.1
    # The choice stands at the next solve without being made again.
    assert eng.solve().accepted
    assert eng.light_pooling['cam1'].status == 'fits_kept'
    assert eng.light_pooling['cam2'].status == 'ok'
    eng.save(tmp_path)
    again = _engine(prob, Clock(), min_samples=10, pool_light_shift=True)
    assert 'fitted centres for' in again.load(tmp_path)
    assert again._fitted_centres == {'cam1'}
    assert 'fitted centres are used' in again._centre_notes['cam1']
    views = eng._centres_compared_at
    assert views and again._centres_compared_at == views
    assert not again._centres_due(2 * views - 1) and again._centres_due(2 * views)
    again.reset()                           # the views weighed are gone: weighed anew
    assert again._centres_due(1) and again._fitted_centres == {'cam1'}
    (tmp_path / 'lit_centres.json').write_text('{"fitted": ["cam1"]}')      # an older file
    older = _engine(prob, Clock(), min_samples=10, pool_light_shift=True)
    older.load(tmp_path)
    assert older._fitted_centres == {'cam1'} and older._centres_due(1)
    (tmp_path / 'lit_centres.json').write_text('{"fitted": 3}')
    with pytest.raises(ValueError, match='lit_centres.json'):
        _engine(prob, Clock()).load(tmp_path)
