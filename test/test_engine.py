"""The online engine: when it solves, warm starts, refusing worse results, save and resume."""
import numpy as np
import pytest

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.priors import PriorSettings
from armcal_ros.core.uncertainty import pose_covariance
from armcal_ros.engine import CalibrationEngine, EngineSettings
from armcal_ros.io.results_files import load_calibration
from armcal_ros.frontend.samples import Observation, Sample
from armcal_ros.sim.synthetic import make_problem


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


def _samples(prob):
    names = [c.name for c in prob.cameras]
    out = []
    for i, X in enumerate(prob.measured):
        sel = prob.obs.point == i
        obs = {names[j]: Observation(uv[None], [0]) for j, uv in
               zip(prob.obs.camera[sel], prob.obs.uv[sel])}
        if obs:
            out.append(Sample(X, obs, stamp_ns=i))
    return out


def _engine(prob, clock, **kw):
    s = EngineSettings([c.name for c in prob.cameras], PriorSettings('independent'),
                       SolverSettings(pixel_sigma=0.3), **kw)
    eng = CalibrationEngine(s, clock=clock)
    for c in prob.cameras:
        eng.set_image_size(c.name, c.width, c.height)
    return eng


def test_solve_schedule_first_solve_and_warm_start():
    prob = make_problem(160, 3)
    clock = Clock()
    eng = _engine(prob, clock, min_samples=60, solve_period_s=5.0, min_new_samples=10)
    samples = _samples(prob)
    for s in samples[:59]:
        eng.add_sample(s)
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
    clock = Clock()
    eng = _engine(prob, clock, min_samples=10, solve_period_s=0.0, min_new_samples=1)
    samples = _samples(prob)
    for s in samples[:120]:
        eng.add_sample(s)
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


def test_save_and_resume_restores_samples_and_calibration(tmp_path):
    prob = make_problem(80, 6)
    eng = _engine(prob, Clock(), min_samples=10)
    for s in _samples(prob):
        eng.add_sample(s)
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


def test_pose_covariance_matches_monte_carlo():
    prob = make_problem(10, 1)
    cam = prob.cameras[0]
    rng = np.random.default_rng(0)
    A = rng.normal(0, 1e-3, (6, 6))
    cov = A @ A.T
    draws = rng.multivariate_normal(np.zeros(6), cov, 20000)
    out = []
    from scipy.spatial.transform import Rotation
    R_wc = cam.rotation.T
    for d in draws:
        c = cam.copy()
        c.apply_pose_increment(d[:3], d[3:])
        dr = Rotation.from_matrix(c.rotation.T @ R_wc.T).as_rotvec()
        out.append(np.concatenate([c.center - cam.center, dr]))
    emp = np.cov(np.array(out).T)
    ref = pose_covariance(cam, cov)
    assert np.allclose(emp, ref, atol=0.05 * np.max(np.abs(ref)))


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
    s = EngineSettings([c.name for c in prob.cameras], PriorSettings('kinematic'),
                       SolverSettings(pixel_sigma=0.3), min_samples=10)
    eng = CalibrationEngine(s)
    for c in prob.cameras:
        eng.set_image_size(c.name, c.width, c.height)
    for smp in _samples(prob):
        eng.add_sample(smp)
    out = eng.solve()
    assert not out.accepted and 'needs joint angles' in out.reason


def test_resume_does_not_solve_the_same_samples_again(tmp_path):
    prob = make_problem(60, 6)
    samples = _samples(prob)
    eng = _engine(prob, Clock(), min_samples=10, solve_period_s=0.0, min_new_samples=1)
    for s in samples[:40]:
        eng.add_sample(s)
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
