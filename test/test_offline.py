"""
``armcal calibrate`` end to end on simulated rosbag2 bags, checked against the ground truth.

One 60 s simulated bag (about 35 dwells, three cameras) is made per session.  Tolerances are set
from what 35 points with 0.5 px detections and a ~1 mm robot bias can pin down (bench/solver.py:
about 1 % focal and 10-20 mm centre error at N = 100): focal within 3 %, camera centres within
40 mm, triangulation of the workspace within 3 mm absolute and 1 mm in shape.  They are loose
enough for every seed and tight enough that a wrong sign, a swapped camera, a mis-paired
timestamp (tens of mm at arm speed) or a wrong marker offset fails them.
"""
import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from rosbags.highlevel import AnyReader

from armcal_ros.compare import compare
from armcal_ros.io.bag import BagWriter, iter_raw, jazzy_typestore
from armcal_ros.io.calib_files import read_camera_info, read_cameras, write_camera_info
from armcal_ros.offline import calibrate_bag, CalibrateError
from armcal_ros.settings import load_settings
from armcal_ros.sim.cell import simulate_cell
from armcal_ros.sim.output import write_sim_bag

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope='module')
def sim_bag(tmp_path_factory):
    d = tmp_path_factory.mktemp('sim')
    bag = d / 'bag'
    write_sim_bag(simulate_cell('geometric', seed=3, duration=60.0), bag)
    params = d / 'params.yaml'
    params.write_text('armcal:\n  ros__parameters:\n'
                      f'    robot_description_file: {ROOT}/urdf/puma560.urdf\n'
                      '    marker_link: marker\n    min_samples: 15\n')
    return bag, params


def _copy_bag(src, dst, edit):
    """Copy a bag message by message; ``edit(raw) -> bytes or None`` (None drops it)."""
    with BagWriter(dst) as w:
        for raw in iter_raw(src):
            data = edit(raw)
            if data is not None:
                w.write_raw(raw.topic, raw.msgtype, raw.t_ns, data)


def _check_against_truth(out_dir, gt_dir, names=('cam1', 'cam2', 'cam3')):
    _, cams = read_cameras(out_dir)
    est = {c.name: c for c in cams}
    assert sorted(est) == sorted(names)
    score = compare(est, gt_dir)
    for name in names:
        assert score.per_camera[name]['focal_pct'] < 3.0, (name, score.per_camera[name])
        assert score.per_camera[name]['centre_mm'] < 40.0, (name, score.per_camera[name])
    assert score.absolute_mm < 3.0 and score.shape_mm < 1.0, score
    return score


@pytest.mark.slow
@pytest.mark.parametrize('model', ['fixed', 'independent', 'correlated', 'kinematic', 'hybrid',
                                   'auto'])
def test_cli_calibrates_each_noise_model_close_to_truth(sim_bag, tmp_path, model):
    bag, params = sim_bag
    out = tmp_path / 'out'
    # The stamp-latency pass runs with auto (the default use); the other runs skip it.
    quiet = ['--quiet', '--no-latency'] if model != 'auto' else []
    proc = subprocess.run([sys.executable, '-m', 'armcal_ros.cli', 'calibrate', str(bag),
                           '--params', str(params), '--output', str(out), '--noise-model',
                           model] + quiet, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    if quiet:
        assert proc.stdout == '' and proc.stderr == '', 'quiet means quiet'
    else:
        assert f'noise model {model}' in proc.stdout and 'cam3' in proc.stdout
        # auto's choice is said once, and a log that is not a terminal gets no '\r' updates.
        assert proc.stdout.count('chose ') == 1, proc.stdout
        assert '\r' not in proc.stderr
    report = json.loads((out / 'report.json').read_text())
    assert report['noise_model'] == model and report['accepted']
    if quiet:
        assert 'stamp_latency' not in report and 'latency_s' not in report['timings']
    else:
        # The simulator stamps on time (2 ms of jitter): each camera timed near zero.
        assert 'stamp latency' in proc.stdout
        for name, e in report['stamp_latency'].items():
            assert e['status'] == 'ok' and abs(e['latency_ms']) < 3.0, (name, e)
    for c in report['cameras'].values():
        assert c['rms_px'] < 1.0 and c['n_inliers'] >= 0.9 * c['n_observations']
        assert c['std']['fx'] > 0
    _check_against_truth(out, bag / 'ground_truth')


def test_missing_camera_topic_is_reported_and_others_calibrate(sim_bag, tmp_path):
    bag, params = sim_bag
    cut = tmp_path / 'no_cam3'
    _copy_bag(bag, cut, lambda r: None if r.topic == '/cam3/image_raw' else r.rawdata)
    logs = []
    # An earlier run of three cameras wrote into the same directory: its cam3.yaml must not
    # stay beside an extrinsics.yaml that no longer lists cam3.
    shutil.copytree(bag / 'ground_truth', tmp_path / 'out')
    (tmp_path / 'out' / 'calibration.json').write_text(
        json.dumps({'cameras': {c: {} for c in ('cam1', 'cam2', 'cam3')}}))
    res = calibrate_bag(cut, load_settings(params), tmp_path / 'out', log=logs.append)
    assert not (tmp_path / 'out' / 'cam3.yaml').exists()
    assert any('cam3' in w and 'no messages' in w for w in res.warnings)
    assert any('cam3' in m for m in logs)
    assert res.report['cameras']['cam3']['status'] == 'not calibrated'
    _check_against_truth(tmp_path / 'out', bag / 'ground_truth', names=('cam1', 'cam2'))


def test_corrupt_messages_are_counted_and_skipped(sim_bag, tmp_path):
    bag, params = sim_bag
    bad = tmp_path / 'corrupt'
    n = {'i': 0}

    def edit(raw):
        n['i'] += 1
        if n['i'] % 97 == 0:
            return raw.rawdata[:len(raw.rawdata) // 3]      # truncated CDR
        return raw.rawdata
    _copy_bag(bag, bad, edit)
    res = calibrate_bag(bad, load_settings(params), tmp_path / 'out')
    assert res.report['front_end']['corrupt_message'] >= 50
    _check_against_truth(tmp_path / 'out', bag / 'ground_truth')


def test_unknown_joint_names_are_counted_and_the_rest_used(sim_bag, tmp_path):
    bag, params = sim_bag
    ts = jazzy_typestore()
    bad = tmp_path / 'renamed'
    n = {'i': 0}

    def edit(raw):
        if raw.msgtype != 'sensor_msgs/msg/JointState':
            return raw.rawdata
        n['i'] += 1
        if n['i'] % 10:
            return raw.rawdata
        msg = ts.deserialize_cdr(raw.rawdata, raw.msgtype)
        msg.name = ['elbow_typo' if x == 'joint_3' else x for x in msg.name]
        return bytes(ts.serialize_cdr(msg, raw.msgtype))
    _copy_bag(bag, bad, edit)
    res = calibrate_bag(bad, load_settings(params), tmp_path / 'out')
    rejected = sum(v for k, v in res.report['front_end'].items() if k.startswith('joint_state_'))
    assert rejected >= 0.09 * n['i']
    _check_against_truth(tmp_path / 'out', bag / 'ground_truth')


def test_clear_errors_for_unusable_input(sim_bag, tmp_path):
    bag, params = sim_bag
    settings = load_settings(params, {'joint_states_topic': '/arm/joint_states'})
    with pytest.raises(CalibrateError, match='/arm/joint_states'):
        calibrate_bag(bag, settings, tmp_path / 'out')
    with pytest.raises(CalibrateError, match='cannot open bag'):
        calibrate_bag(tmp_path / 'nothing', load_settings(params), tmp_path / 'out')
    proc = subprocess.run([sys.executable, '-m', 'armcal_ros.cli', 'calibrate', str(bag),
                           '--params', str(params), '--output', str(tmp_path / 'o'),
                           '--noise-model', 'magic'], capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode != 0 and 'noise_model' in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_the_output_directory_is_checked_before_the_bag_is_read(sim_bag, tmp_path, monkeypatch):
    import armcal_ros.offline as offline
    bag, params = sim_bag
    monkeypatch.setattr(offline, 'collect_samples', lambda *a, **k: pytest.fail('read first'))
    (tmp_path / 'file').write_text('x')
    with pytest.raises(CalibrateError, match='not a directory'):
        calibrate_bag(bag, load_settings(params), tmp_path / 'file')
    with pytest.raises(CalibrateError, match='cannot be created'):
        calibrate_bag(bag, load_settings(params), tmp_path / 'file' / 'out')


def test_the_wrong_robots_urdf_is_named_with_the_joints(sim_bag, tmp_path):
    bag, _ = sim_bag
    params = tmp_path / 'ur5.yaml'
    params.write_text('armcal:\n  ros__parameters:\n'
                      f'    robot_description_file: {ROOT}/urdf/ur5.urdf\n'
                      '    marker_link: tool0\n    min_samples: 15\n')
    with pytest.raises(CalibrateError) as err:
        calibrate_bag(bag, load_settings(params), tmp_path / 'out')
    text = str(err.value)
    assert 'shoulder_pan_joint' in text and 'joint_1' in text and "robot's URDF" in text, text


def test_ctrl_c_ends_calibrate_with_one_line_and_status_130(sim_bag, tmp_path):
    import signal
    import time
    bag, params = sim_bag
    out = tmp_path / 'out'
    out.mkdir()
    (out / 'cam1.yaml').write_text('an earlier result')
    # A suite started in the background inherits SIGINT ignored; the user's shell does not.
    proc = subprocess.Popen([sys.executable, '-m', 'armcal_ros.cli', 'calibrate', str(bag),
                             '--params', str(params), '--output', str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    # The staging area appears once the directory is locked, before the bag is read (the
    # whole run takes ~3 s): interrupt then, mid-run.
    deadline = time.monotonic() + 60
    while not any(p.name.startswith('.armcal-staging') for p in out.iterdir()):
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130, stderr
    assert 'Traceback' not in stderr
    assert stderr.strip().splitlines()[-1] == 'armcal calibrate: interrupted'
    assert (out / 'cam1.yaml').read_text() == 'an earlier result'
    assert sorted(p.name for p in out.iterdir()) == ['.armcal.lock', 'cam1.yaml']


def test_bag_is_real_rosbag2(sim_bag):
    bag, _ = sim_bag
    with AnyReader([bag], default_typestore=jazzy_typestore()) as reader:
        topics = {c.topic for c in reader.connections}
    assert {'/joint_states', '/cam1/image_raw'} <= topics
    assert np.load(bag / 'ground_truth' / 'markers.npz')['dwell_true'].shape[0] >= 20


def test_given_intrinsics_are_kept_and_only_poses_estimated(sim_bag, tmp_path):
    # The simulator's true camera_info files stand for a driver's factory calibration: with
    # intrinsics_mode fixed they come back unchanged, the poses are estimated; with a prior of
    # 2 px around values 3 px off, the estimate moves back towards the truth.
    bag, params = sim_bag
    gt = bag / 'ground_truth'
    files = [str(gt / f'{c}.yaml') for c in ('cam1', 'cam2', 'cam3')]
    fixed = calibrate_bag(bag, load_settings(params, {'intrinsics_mode': ['fixed'],
                                                      'intrinsics_files': files,
                                                      'noise_model': 'correlated'}),
                          tmp_path / 'fixed')
    _, truth = read_cameras(str(gt))
    for t in truth:
        c = fixed.report['cameras'][t.name]
        np.testing.assert_allclose([c['fx'], c['fy'], c['cx'], c['cy']], t.intrinsics(),
                                   atol=1e-3)
        np.testing.assert_allclose(c['dist'], t.dist, atol=1e-8)
        assert c['std']['fx'] < 1e-3
    score = _check_against_truth(tmp_path / 'fixed', gt)
    for name in ('cam1', 'cam2', 'cam3'):
        assert score.per_camera[name]['centre_mm'] < 10.0, score.per_camera[name]
    # A prior of 2 px around intrinsics 3 px off: the estimates come back closer to the
    # truth than the given values are, on the whole (the images, weighted by their estimated
    # noise, inform them), each within two of its reported standard deviations of the 3 px
    # (one may drift a little further on the images' noise: with the shaded fit's cold-start
    # changes cam3's fy came back 3.15 px off, the same with or without each camera's choice
    # of centre), and no reported standard deviation exceeds the prior's (the posterior is
    # never wider than the prior).
    off = tmp_path / 'off'
    off.mkdir()
    for t in truth:
        cam = read_camera_info(str(gt / f'{t.name}.yaml'))
        cam.set_intrinsics(cam.intrinsics() + 3.0)
        write_camera_info(str(off / f'{t.name}.yaml'), cam)
    prior = calibrate_bag(bag, load_settings(params, {
        'intrinsics_mode': ['prior'], 'intrinsics_sigma_px': 2.0, 'noise_model': 'correlated',
        'intrinsics_files': [str(off / f'{c}.yaml') for c in ('cam1', 'cam2', 'cam3')]}),
        tmp_path / 'prior')
    errors = []
    for t in truth:
        c = prior.report['cameras'][t.name]
        est = np.array([c['fx'], c['fy'], c['cx'], c['cy']])
        std = np.array([c['std'][k] for k in ('fx', 'fy', 'cx', 'cy')])
        errors.append(est - t.intrinsics())
        assert np.all(np.abs(errors[-1]) < 3.0 + 2.0 * std), (t.name, errors[-1], std)
        assert max(c['std'][k] for k in ('fx', 'fy', 'cx', 'cy')) <= 2.0, c['std']
        assert c['dist'] == pytest.approx(list(t.dist), abs=1e-8)   # sigma_dist 0: held
    assert np.sqrt(np.mean(np.square(errors))) < 3.0, errors
