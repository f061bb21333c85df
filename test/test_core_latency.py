"""
Stamp latency from motion (core/latency.py): known delays recovered, and refusals.

A marker on a smooth path seen by a camera whose stamps are late by d: the estimate must find
d within a few tenths of a millisecond from 0.3 px detection noise (its standard deviation is
s / sqrt(sum |v|^2), ~0.05 ms here), state an honest standard deviation, ignore a constant
image offset and stray detections, and refuse when the marker barely moves.
"""
import numpy as np
import pytest

from armcal_ros.core import latency
from armcal_ros.core.latency import estimate_latency


def _path(t):
    """Return points of an image path (px) with speeds of 100-300 px/s."""
    return np.column_stack([320 + 150 * np.sin(1.3 * t), 240 + 100 * np.sin(0.9 * t + 1.0)])


@pytest.mark.parametrize('delay', [-0.02, 0.0, 0.03, 0.08])
def test_a_known_delay_is_recovered_with_an_honest_deviation(delay):
    rng = np.random.default_rng(7)
    errors, stds = [], []
    for _ in range(20):
        t = np.sort(rng.uniform(0, 20, 200))
        uv = _path(t - delay) + rng.normal(0, 0.3, (200, 2)) + [0.5, -0.4]    # a fixed offset
        e = estimate_latency(t, uv, _path)
        assert e.ok, e
        errors.append(e.latency_s - delay)
        stds.append(e.std_s)
    errors = np.array(errors)
    assert np.max(np.abs(errors)) < 5e-4
    # The stated deviation is the scatter's (within the sampling error of 20 runs).
    assert 0.6 < np.std(errors) / np.mean(stds) < 1.5


def _uneven_path(t):
    """Return the points of ``_path`` run at 0.1-1.9 x its speed (10-570 px/s)."""
    return _path(t + 0.9 / 0.4 * np.sin(0.4 * t))


def test_stamp_jitter_is_in_the_stated_deviation(monkeypatch):
    """
    A stamp's jitter moves its frame's residual along the motion, more for faster frames.

    The stated deviation (module doc, (2)) must be the scatter's with the block jackknife
    out of the way; s / sqrt(sum |v|^2) said about half of it here.
    """
    monkeypatch.setattr(latency, '_block_jackknife', lambda *args: 0.0)
    rng = np.random.default_rng(3)
    errors, stds = [], []
    for _ in range(40):
        t = np.sort(rng.uniform(0, 20, 200))
        uv = _uneven_path(t - 0.03 - rng.normal(0, 0.002, t.size)) + rng.normal(0, 0.05, (200, 2))
        e = estimate_latency(t, uv, _uneven_path)
        assert e.ok, e
        errors.append(e.latency_s - 0.03)
        stds.append(e.std_s)
    ratio = np.std(errors) / np.mean(stds)
    assert 0.75 < ratio < 1.33, (np.std(errors), np.mean(stds))


def test_stray_detections_are_left_out():
    rng = np.random.default_rng(1)
    t = np.sort(rng.uniform(0, 20, 200))
    uv = _path(t - 0.04) + rng.normal(0, 0.3, (200, 2))
    uv[::17] += rng.uniform(20, 60, (len(uv[::17]), 2))
    e = estimate_latency(t, uv, _path)
    assert e.ok and abs(e.latency_s - 0.04) < 5e-4, e
    assert e.frames <= 200 - len(uv[::17])


def test_a_marker_that_barely_moves_is_not_timed():
    rng = np.random.default_rng(2)
    t = np.sort(rng.uniform(0, 20, 100))

    def still(tq):
        return _path(1e-3 * tq)
    e = estimate_latency(t, still(t) + rng.normal(0, 0.3, (100, 2)), still)
    assert e.status == 'too_little_motion' and 'too little motion' in e.message


def test_refusals_name_their_argument():
    t = np.linspace(0, 1, 20)
    with pytest.raises(ValueError, match='uv'):
        estimate_latency(t, np.zeros((19, 2)), _path)
    with pytest.raises(ValueError, match='bounds'):
        estimate_latency(t, _path(t), _path, bounds=(0.1, 0.0))
    e = estimate_latency(t[:5], _path(t[:5]), _path)
    assert e.status == 'too_few_frames' and not e.ok


def test_a_delay_outside_the_range_searched_is_flagged():
    t = np.linspace(0, 20, 200)
    e = estimate_latency(t, _path(t - 0.26), _path, bounds=(-0.1, 0.25))
    assert e.status == 'at_bound' and not e.ok, e
    e = estimate_latency(t, _path(t - 0.6), _path, bounds=(-0.1, 0.25))
    assert e.status == 'no_fit' and 'no delay' in e.message, e
