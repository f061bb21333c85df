"""The simulator's arm and clock effects: backlash, repeatability, settling, clocks."""

import numpy as np
import pytest

from armcal_ros.sim.arm_effects import arm_effects
from armcal_ros.sim.cell import SimSettings, simulate_cell
from armcal_ros.sim.trajectory import Trajectory

DURATION = 30.0


@pytest.fixture(scope='module')
def plain():
    return simulate_cell('geometric', 5, DURATION, SimSettings(duration=DURATION))


def _with(**kw):
    return simulate_cell('geometric', 5, DURATION, SimSettings(duration=DURATION, **kw))


def test_every_effect_is_off_by_default_and_draws_from_its_own_stream(plain):
    assert arm_effects(plain.trajectory) is None
    on = _with(repeatability_mm=0.05, joint_drop=0.1)
    # The cameras, the trajectory and the frame clocks are the same draws with the effects on.
    for a, b in zip(plain.cameras, on.cameras):
        assert np.array_equal(a.rotation, b.rotation)
        assert np.array_equal(a.translation, b.translation)
    assert np.array_equal(plain.frames.stamp_ns, on.frames.stamp_ns)


def test_late_stamps_shift_each_camera_by_its_latency(plain):
    late = _with(stamp_latency=(0.03, 0.0, 0.08))
    for j, lat in enumerate((0.03, 0.0, 0.08)):
        m = plain.frames.camera == j
        d = (late.frames.stamp_ns[m] - plain.frames.stamp_ns[m]) * 1e-9
        assert np.allclose(d, lat, atol=1e-9)
        # The exposure (the truth) does not move.
        assert np.array_equal(late.frames.exposure_ns[m], plain.frames.exposure_ns[m])


def test_joint_states_lose_the_stated_fraction_and_jitter_by_the_stated_std(plain):
    # Jitter well inside the 5 ms control period, so each stamp's tick is the nearest one.
    rough = _with(joint_jitter=0.0005, joint_drop=0.2)
    kept = len(rough.joint_stamps_ns) / len(plain.joint_stamps_ns)
    assert kept == pytest.approx(0.8, abs=0.02)
    assert np.all(np.diff(rough.joint_stamps_ns) >= 0)          # published in stamp order
    # Each kept state is its control-clock reading: stamp minus its clock tick is the jitter.
    period = 1e9 / SimSettings().joint_rate
    tick = np.round((rough.joint_stamps_ns - plain.joint_stamps_ns[0]) / period) * period
    jitter = (rough.joint_stamps_ns - plain.joint_stamps_ns[0] - tick) * 1e-9
    assert np.std(jitter) == pytest.approx(0.0005, rel=0.1)


def test_backlash_lags_the_links_behind_the_last_move():
    # Joint 0 goes up then stays; joint 1 goes down, dwells, then up.
    knots = np.array([[0.0, 1.0], [0.5, 0.5], [0.5, 0.5], [0.5, 0.9], [0.5, 0.9]])
    traj = Trajectory(np.array([0.0, 1.0, 2.0, 3.0, 4.0]), knots,
                      np.array([True, False, True, False]))
    eff = arm_effects(traj, backlash_deg=0.02)
    half = np.radians(0.01)
    q = np.array([[0.5, 0.5], [0.5, 0.9]])
    got = eff.link_joints(q, np.array([1.5, 3.5]))
    assert np.allclose(got[0], [0.5 - half, 0.5 + half])       # after up / after down
    assert np.allclose(got[1], [0.5 - half, 0.9 - half])       # joint 0 keeps its last sign


def test_repeatability_moves_each_stop_by_the_stated_std(plain):
    rep = _with(repeatability_mm=0.05)
    d = 1e3 * (rep.dwells.true_marker - plain.dwells.true_marker)
    assert len(d) > 10
    assert np.std(d) == pytest.approx(0.05, rel=0.35)
    # Within a dwell the offset is constant: frames of one stop share it.
    f = rep.frames
    mid = rep.dwells.stamp_ns[len(rep.dwells) // 2]
    m = np.abs(f.exposure_ns - mid) < 0.1e9
    off = f.marker[m] - plain.frames.marker[m]
    assert np.ptp(off, axis=0).max() < 1e-9


def test_settling_rings_down_after_each_stop(plain):
    ring = _with(settle_mm=0.1, settle_hz=10.0, settle_tau=0.1)
    f = ring.frames
    d = 1e3 * np.linalg.norm(f.marker - plain.frames.marker, axis=1)
    since = []
    for start, end in zip(ring.dwells.start_ns, ring.dwells.end_ns):
        m = (f.exposure_ns >= start) & (f.exposure_ns < end)
        since.append(np.column_stack([(f.exposure_ns[m] - start) * 1e-9, d[m]]))
    s = np.concatenate(since)
    early, late = s[s[:, 0] < 0.1, 1], s[s[:, 0] > 0.5, 1]
    assert early.max() > 0.03 and early.max() <= 0.1 + 1e-9
    assert late.max() < 0.1 * np.exp(-5.0) + 1e-9            # e^-(0.5 / 0.1) of the amplitude


def test_bad_settings_are_refused_with_their_name():
    with pytest.raises(ValueError, match='stamp_latency'):
        SimSettings(stamp_latency=(0.1, 0.1, 0.1, 0.1))
    with pytest.raises(ValueError, match='joint_drop'):
        SimSettings(joint_drop=1.0)
    with pytest.raises(ValueError, match='settle_mm'):
        arm_effects(Trajectory(np.array([0.0, 1.0]), np.zeros((2, 1)), np.array([False])),
                    settle_mm=-1.0)


def test_armcal_simulate_writes_the_effects_into_the_bag_and_its_ground_truth(tmp_path):
    import subprocess
    import sys

    from armcal_ros.io.bag import iter_messages
    from armcal_ros.sim.output import read_ground_truth
    from helpers.cli import armcal

    bag = tmp_path / 'rough'
    armcal('simulate', '--output', bag, '--duration', 8, '--stamp-latency', 'cam2:0.05',
           '--joint-drop', 0.5, '--backlash', 0.01, '--repeatability', 0.05, '--settle', 0.1,
           10, 0.1, '--quiet')
    gt = read_ground_truth(bag / 'ground_truth')
    s = gt['scenario']['settings']
    assert s['stamp_latency'] == [0.0, 0.05, 0.0] and s['joint_drop'] == 0.5
    assert s['backlash_deg'] == 0.01 and s['settle_mm'] == 0.1
    states = sum(1 for _ in iter_messages(str(bag), ['/joint_states']))
    assert states == pytest.approx(8.0 * SimSettings().joint_rate * 0.5, rel=0.1)
    bad = subprocess.run([sys.executable, '-m', 'armcal_ros.cli', 'simulate', '--output',
                          tmp_path / 'x', '--stamp-latency', 'camX:0.1'],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and 'unknown camera' in bad.stderr
