"""
Each camera's stamp latency measured by ``armcal calibrate`` against the simulator's truth.

The simulator stamps two cameras late (30 and 70 ms) and the third on time; the calibration
comes from frames at rest, and the frames in motion time each camera.  The issue's target is
5 ms; the estimate's own deviation is ~0.1 ms, so 5 ms leaves room for the simulator's 2 ms
stamp jitter and the detection of a moving ball.
"""
import json

import numpy as np
import pytest

from helpers.cli import armcal

pytestmark = pytest.mark.slow


@pytest.fixture(scope='module')
def late_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp('late') / 'bag'
    armcal('simulate', '--output', bag, '--duration', 60, '--stamp-latency', 'cam1:0.03',
           '--stamp-latency', 'cam2:0.07', '--no-zstd', '--quiet')
    return bag


def test_late_stamps_are_measured_per_camera(late_bag, tmp_path):
    bag, out = late_bag, tmp_path / 'out'
    armcal('calibrate', bag, '--params', bag / 'ground_truth' / 'params.yaml', '--output', out,
           '--quiet')
    report = json.loads((out / 'report.json').read_text())
    truth = np.load(bag / 'ground_truth' / 'markers.npz')
    for j, name in enumerate(truth['camera_names']):
        m = truth['frame_camera'] == j
        expected_ms = np.median(truth['frame_stamp_ns'][m] - truth['frame_exposure_ns'][m]) / 1e6
        got = report['stamp_latency'][str(name)]
        assert got['status'] == 'ok', got
        assert abs(got['latency_ms'] - expected_ms) < 5.0, (name, got, expected_ms)
        assert got['frames'] >= 50
        # The late cameras' frames were paired again at their measured latency; the third's
        # (on time, within 2 ms) as stamped.
        assert got['applied_ms'] == pytest.approx(got['latency_ms'] if expected_ms > 10 else 0,
                                                  abs=1e-6), got


def test_a_change_the_late_stamps_made_does_not_end_the_job(late_bag, tmp_path, monkeypatch):
    """
    The first pass pairs frames at their (late) stamps; a change it declares can be theirs.

    Here the first pass's change following is made to retire all but the last 5 samples' views,
    as a false arm change late in the recording did on a lamp-lit UR5 cell (11 samples left,
    min_samples 20: the job ended).  The latency is then measured on every sample, changes not
    followed, and the second pass - frames paired at their exposure - calibrates as usual.
    """
    from armcal_ros import offline
    from armcal_ros.settings import load_settings
    collect = offline.collect_samples
    calls = []

    def first_pass_retires(source, settings, *args, **kwargs):
        front = collect(source, settings, *args, **kwargs)
        if not calls:
            stamps = sorted(s.stamp_ns for s in front.store)
            front.store.retire(stamps[-5], epoch=1)
        calls.append(len(front.store))
        return front
    monkeypatch.setattr(offline, 'collect_samples', first_pass_retires)
    settings = load_settings(str(late_bag / 'ground_truth' / 'params.yaml'))
    # Where the latency then needs no second pass, the first pass's own failure stands.
    with monkeypatch.context() as m:
        m.setattr(offline, '_latencies_to_apply', lambda estimates, settings: {})
        with pytest.raises(offline.CalibrateError, match='only 5 samples'):
            offline.calibrate_bag(str(late_bag), settings, str(tmp_path / 'refused'))
    calls.clear()
    logged = []
    result = offline.calibrate_bag(str(late_bag), settings, str(tmp_path / 'out'),
                                   log=logged.append)
    assert len(calls) == 2 and calls[0] < settings.schedule.min_samples <= calls[1], calls
    assert result.outcome.accepted and len(result.outcome.calibration.cameras) == 3
    assert any('changes not followed' in m for m in logged), logged
    report = json.loads((tmp_path / 'out' / 'report.json').read_text())
    assert report['stamp_latency']['cam2']['applied_ms'] == pytest.approx(70.0, abs=5.0)
