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


def test_late_stamps_are_measured_per_camera(tmp_path):
    bag, out = tmp_path / 'bag', tmp_path / 'out'
    armcal('simulate', '--output', bag, '--duration', 60, '--stamp-latency', 'cam1:0.03',
           '--stamp-latency', 'cam2:0.07', '--no-zstd', '--quiet')
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
