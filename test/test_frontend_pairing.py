"""Tests for joint history, time pairing, stillness, dwell pooling and its views cap."""

import numpy as np
import pytest

from armcal_ros.frontend.detectors import Detection
from armcal_ros.frontend.pairing import (
    DEFAULT_MAX_MARKER_SPEED, DwellPooler, FramePairer, JointHistory, JointStatus,
    max_speed_for_smear, PairedFrame, PairStatus)

JOINTS = ('shoulder', 'elbow')
L1, L2 = 0.5, 0.4
MS = 1_000_000


def fk(q):
    """Stand-in for KinematicChain.fk: a planar two-link arm in the z = 0.3 plane."""
    q = np.asarray(q, dtype=float)
    a, b = q[:, 0], q[:, 0] + q[:, 1]
    return np.column_stack([L1 * np.cos(a) + L2 * np.cos(b), L1 * np.sin(a) + L2 * np.sin(b),
                            np.full(q.shape[0], 0.3)])


def trajectory(t):
    """Joint angles at times t (s): a smooth, non-linear motion."""
    t = np.asarray(t, dtype=float)
    return np.column_stack([0.3 + 0.5 * np.sin(0.7 * t), 1.0 + 0.3 * np.cos(1.3 * t)])


def filled_history(rate_hz=100, duration_s=2.0, **kw):
    hist = JointHistory(JOINTS, **kw)
    ts = np.arange(0, duration_s, 1.0 / rate_hz)
    q = trajectory(ts)
    for t, qi in zip(ts, q):
        assert hist.add(int(round(t * 1e9)), JOINTS, qi) is JointStatus.OK
    return hist, ts, q


def test_default_speed_follows_from_the_smear_budget():
    assert DEFAULT_MAX_MARKER_SPEED == pytest.approx(0.1 * 1.5 / 800 / 0.005)
    assert max_speed_for_smear(0.2, 400, 1.0, 0.01) == pytest.approx(0.05)
    with pytest.raises(ValueError, match='focal_px'):
        max_speed_for_smear(focal_px=0)


def test_interpolation_matches_linear_interpolation_between_samples():
    hist, ts, q = filled_history()
    rng = np.random.default_rng(0)
    query = rng.uniform(ts[0], ts[-1], 200)
    stamps = np.round(query * 1e9).astype(np.int64)
    statuses, out = hist.lookup(stamps)
    assert all(s is PairStatus.OK for s in statuses)
    t_ns = np.round(ts * 1e9)
    for j in range(2):
        np.testing.assert_allclose(out[:, j], np.interp(stamps, t_ns, q[:, j]), atol=1e-12)
    # Linear interpolation at 100 Hz of this motion is within 1e-4 rad of the truth.
    np.testing.assert_allclose(out, trajectory(stamps * 1e-9), atol=1e-4)
    status, q0 = hist.interpolate(0)
    assert status is PairStatus.OK
    np.testing.assert_allclose(q0, q[0])
    status, qn = hist.interpolate(int(round(ts[-1] * 1e9)))
    assert status is PairStatus.OK
    np.testing.assert_allclose(qn, q[-1])


def test_out_of_range_and_empty():
    assert JointHistory(JOINTS).interpolate(5)[0] is PairStatus.EMPTY
    hist, ts, _ = filled_history()
    assert hist.interpolate(-1) == (PairStatus.BEFORE_HISTORY, None)
    assert hist.interpolate(int(ts[-1] * 1e9) + 1)[0] is PairStatus.AFTER_HISTORY


def test_gap_larger_than_max_gap_is_refused():
    hist = JointHistory(JOINTS, max_gap_ns=50 * MS)
    hist.add(0, JOINTS, [0.0, 0.0])
    hist.add(40 * MS, JOINTS, [0.4, 0.0])
    hist.add(140 * MS, JOINTS, [1.4, 0.0])
    status, q = hist.interpolate(20 * MS)
    assert status is PairStatus.OK and q[0] == pytest.approx(0.2)
    assert hist.interpolate(90 * MS) == (PairStatus.GAP, None)


def test_joint_names_are_matched_by_name_and_extras_ignored():
    hist = JointHistory(JOINTS)
    names = ('gripper', 'elbow', 'wrist', 'shoulder')
    assert hist.add(0, names, [9.0, 0.2, 8.0, 0.1]) is JointStatus.OK
    assert hist.add(10 * MS, JOINTS, [0.3, 0.4]) is JointStatus.OK
    status, q = hist.interpolate(5 * MS)
    np.testing.assert_allclose(q, [0.2, 0.3])


def test_refused_joint_states():
    hist = JointHistory(JOINTS)
    assert hist.add(0, ('shoulder', 'elbwo'), [0.1, 0.2]) is JointStatus.MISSING_JOINT
    assert hist.missing == ('elbow',)
    assert hist.add(0, JOINTS, [np.nan, 0.2]) is JointStatus.NON_FINITE
    assert hist.add(0, JOINTS, [np.inf, 0.2]) is JointStatus.NON_FINITE
    assert hist.add(0, ('x',) + JOINTS, [np.nan, 0.1, 0.2]) is JointStatus.OK   # NaN elsewhere
    assert hist.add(0, JOINTS, [0.1]) is JointStatus.MALFORMED
    assert hist.add(0, JOINTS + ('elbow',), [0.1, 0.2, 0.3]) is JointStatus.MALFORMED
    assert hist.missing == ('elbow',)
    assert hist.add(0, JOINTS, [0.1, 0.2]) is JointStatus.DUPLICATE
    assert hist.add(100 * MS, JOINTS, [0.1, 0.2]) is JointStatus.OK
    assert hist.add(50 * MS, JOINTS, [0.1, 0.2]) is JointStatus.OUT_OF_ORDER
    assert len(hist) == 2
    with pytest.raises(ValueError, match='joint_names'):
        JointHistory(('a', 'a'))


def test_backwards_clock_jump_resets_the_history():
    hist, ts, _ = filled_history(duration_s=2.0, jump_threshold_ns=500 * MS)
    assert hist.add(10 * MS, JOINTS, [0.5, 0.5]) is JointStatus.TIME_JUMP
    assert len(hist) == 1 and hist.first_stamp == 10 * MS
    assert hist.interpolate(1_500 * MS)[0] is PairStatus.AFTER_HISTORY   # old times gone
    assert hist.add(20 * MS, JOINTS, [0.6, 0.5]) is JointStatus.OK
    assert hist.interpolate(15 * MS)[1][0] == pytest.approx(0.55)


def test_continuous_joint_wrap_is_interpolated_the_short_way():
    hist = JointHistory(JOINTS)
    hist.add(0, JOINTS, [3.1, 0.0])
    hist.add(10 * MS, JOINTS, [-3.1, 0.0])
    q = hist.interpolate(5 * MS)[1]
    assert abs(abs(q[0]) - np.pi) < 1e-9


def test_ring_keeps_the_newest_capacity_samples():
    hist = JointHistory(JOINTS, capacity=50)
    for k in range(175):
        hist.add(k * 10 * MS, JOINTS, [k * 0.01, 0.0])
    assert len(hist) == 50
    assert hist.first_stamp == 125 * 10 * MS and hist.last_stamp == 174 * 10 * MS
    np.testing.assert_allclose(hist.positions[:, 0], np.arange(125, 175) * 0.01)
    assert hist.interpolate(1500 * MS + 5 * MS)[1][0] == pytest.approx(1.505)
    assert hist.interpolate(1000 * MS)[0] is PairStatus.BEFORE_HISTORY


# -- FramePairer ---------------------------------------------------------------------------


def dwell_then_move(pairer, t0_ms=0, t1_ms=1000, speed_rad_s=0.2, rate_hz=200):
    """Joint states: still at q0 until t1_ms, then the shoulder turns at speed_rad_s."""
    frames = []
    for k in range(int((t1_ms - t0_ms) * 2 * rate_hz / 1000)):
        t = t0_ms * MS + k * (1000 // rate_hz) * MS
        dt = max(0.0, (t - t1_ms * MS) * 1e-9)
        status, ready = pairer.add_joint_state(t, JOINTS, [0.2 + speed_rad_s * dt, 0.9])
        assert status is JointStatus.OK
        frames += ready
    return frames


def test_frames_wait_for_joint_states_then_get_still_or_moving():
    pairer = FramePairer(JOINTS, fk, speed_window_ns=20 * MS)
    out = []
    out += pairer.add_frame('cam1', 500 * MS, payload='a')       # before any joint state
    assert out == [] and pairer.n_pending == 1
    out += dwell_then_move(pairer)
    out += pairer.add_frame('cam2', 1500 * MS, payload='b')      # moving
    out += pairer.add_frame('cam1', 900 * MS, payload='c')       # still
    out += pairer.add_frame('cam1', 5000 * MS, payload='d')      # in the future: waits
    by_payload = {f.payload: f for f in out}
    assert set(by_payload) == {'a', 'b', 'c'} and pairer.n_pending == 1
    a = by_payload['a']
    assert a.status is PairStatus.STILL and a.camera == 'cam1' and a.speed < 1e-9
    np.testing.assert_allclose(a.q, [0.2, 0.9])
    np.testing.assert_allclose(a.point, fk(np.array([[0.2, 0.9]]))[0])
    b = by_payload['b']
    # Tip speed of a shoulder rotation = omega * |p_xy|.
    expected = 0.2 * np.linalg.norm(b.point[:2])
    assert b.status is PairStatus.MOVING and b.speed == pytest.approx(expected, rel=1e-3)
    tail = pairer.flush()
    assert [f.status for f in tail] == [PairStatus.AFTER_HISTORY]


def test_speed_threshold_is_applied():
    slow = FramePairer(JOINTS, fk, max_marker_speed=0.5)
    dwell_then_move(slow)
    assert slow.add_frame('c', 1500 * MS)[0].status is PairStatus.STILL   # 0.2 rad/s ~ 0.15 m/s


def test_a_still_guard_needs_stillness_before_the_stamp_too():
    """A frame stamped 50 ms after the arm stopped: still at its stamp, not 100 ms before."""
    def move_then_still(pairer):
        out = []
        for k in range(400):                                   # 2 s at 200 Hz
            t = k * 5 * MS
            q0 = 0.2 + 0.2 * min(t, 1000 * MS) * 1e-9         # turns until 1 s, then stops
            out += pairer.add_joint_state(t, JOINTS, [q0, 0.9])[1]
        return out

    def status(guard_ms, stamp_ms):
        pairer = FramePairer(JOINTS, fk, still_guard_ns=guard_ms * MS)
        pairer.add_frame('c', stamp_ms * MS)
        return [f.status for f in move_then_still(pairer) + pairer.flush()][0]
    assert status(0, 1050) is PairStatus.STILL
    assert status(100, 1050) is PairStatus.MOVING
    assert status(100, 1200) is PairStatus.STILL
    with pytest.raises(ValueError, match='still_guard_ns'):
        FramePairer(JOINTS, fk, still_guard_ns=-1)


def test_frames_before_history_and_stale():
    pairer = FramePairer(JOINTS, fk, max_pending=3)
    dwell_then_move(pairer, t0_ms=1000, t1_ms=2000)
    assert pairer.add_frame('c', 100 * MS)[0].status is PairStatus.BEFORE_HISTORY
    assert pairer.add_frame('c', 1005 * MS)[0].status is PairStatus.BEFORE_HISTORY  # t - W
    stale = []
    for k in range(5):
        stale += pairer.add_frame('c', (9000 + k) * MS)
    assert [f.status for f in stale] == [PairStatus.STALE] * 2 and pairer.n_pending == 3


def test_time_jump_drops_frames_of_the_old_timeline():
    pairer = FramePairer(JOINTS, fk, batch_ns=0)
    dwell_then_move(pairer, t0_ms=10_000, t1_ms=11_000)
    assert pairer.add_frame('c', 12_500 * MS) == []           # waits for t + W
    status, ready = pairer.add_joint_state(0, JOINTS, [0.2, 0.9])
    assert status is JointStatus.TIME_JUMP
    assert [f.status for f in ready] == [PairStatus.TIME_JUMP]
    assert pairer.add_frame('c', 30 * MS) == []
    out = []
    for k in range(1, 20):
        out += pairer.add_joint_state(k * 5 * MS, JOINTS, [0.2, 0.9])[1]
    assert [f.status for f in out] == [PairStatus.STILL]


def test_gap_in_joint_states_refuses_the_frame():
    pairer = FramePairer(JOINTS, fk, max_gap_ns=50 * MS, batch_ns=0)
    pairer.add_joint_state(0, JOINTS, [0.2, 0.9])
    pairer.add_joint_state(10 * MS, JOINTS, [0.2, 0.9])
    pairer.add_joint_state(200 * MS, JOINTS, [0.2, 0.9])
    assert pairer.add_frame('c', 100 * MS)[0].status is PairStatus.GAP


# -- DwellPooler ---------------------------------------------------------------------------


def _still(camera, t_ms, q, status=PairStatus.STILL):
    from armcal_ros.frontend.pairing import PairedFrame
    q = np.asarray(q, dtype=float)
    return PairedFrame(camera, t_ms * MS, None, status, q=q, point=fk(q[None])[0], speed=0.0)


def _det(uv, tid=0):
    return [Detection(uv=np.asarray(uv, dtype=float), id=tid, quality=1.0, radius_px=5.0)]


def test_pooling_a_dwell_into_one_sample():
    rng = np.random.default_rng(1)
    pooler = DwellPooler(fk, min_frames=3, outlier_px=2.0)
    out = []
    uv1, uv2 = np.array([100.0, 200.0]), np.array([300.0, 50.0])
    qs = []
    for k in range(20):
        q = [0.2 + 1e-6 * rng.normal(), 0.9]
        qs += [q, q]                                           # one per frame, both cameras
        out += pooler.add(_still('cam1', 33 * k, q), _det(uv1 + rng.normal(0, 0.05, 2)))
        dets = _det(uv2 + rng.normal(0, 0.05, 2)) if k % 2 else []
        out += pooler.add(_still('cam2', 33 * k + 10, q), dets)
    out += pooler.add(_still('cam1', 700, qs[-1]), _det(uv1 + (9.0, 0.0)))   # spurious frame
    out += pooler.add(_still('cam3', 710, qs[-1]), _det((5.0, 5.0)))         # only one frame
    assert out == [] and pooler.open
    moving = _still('cam1', 750, [0.3, 0.9], status=PairStatus.MOVING)
    out += pooler.add(moving, _det((1.0, 1.0)))
    assert len(out) == 1 and not pooler.open
    s = out[0]
    assert set(s.observations) == {'cam1', 'cam2'}             # cam3 below min_frames
    o1, o2 = s.observations['cam1'], s.observations['cam2']
    assert o1.n_frames == 20 and o2.n_frames == 10             # the outlier frame was dropped
    np.testing.assert_allclose(o1.uv[0], uv1, atol=0.05)
    np.testing.assert_allclose(o2.uv[0], uv2, atol=0.06)
    assert 0.02 < o1.spread_px < 0.12
    np.testing.assert_allclose(s.q, np.mean(qs + [qs[-1], qs[-1]], axis=0), rtol=0, atol=1e-15)
    np.testing.assert_allclose(s.point_nominal, fk(s.q[None])[0])
    assert 0 <= s.stamp_ns <= 710 * MS


def test_dwell_closes_on_position_change_gap_jump_and_timeout():
    pooler = DwellPooler(fk, min_frames=1, dwell_radius=0.001, max_gap_ns=300 * MS,
                         max_dwell_ns=2000 * MS)
    out = []
    out += pooler.add(_still('c', 0, [0.2, 0.9]), _det((1, 1)))
    out += pooler.add(_still('c', 30, [0.21, 0.9]), _det((2, 2)))  # 9 mm away: new dwell
    assert len(out) == 1
    out += pooler.add(_still('c', 900, [0.21, 0.9]), _det((2, 2)))  # gap: new dwell
    assert len(out) == 2
    out += pooler.add(_still('c', 3000, [0.21, 0.9]), _det((2, 2)))  # gap again
    for t in range(3030, 5200, 30):
        out += pooler.add(_still('c', t, [0.21, 0.9]), _det((2, 2)))
    assert len(out) == 4                                            # one max_dwell timeout
    frame = _still('c', 0, [0.2, 0.9], status=PairStatus.TIME_JUMP)
    out += pooler.add(frame)
    assert len(out) == 5 and not pooler.open
    out += pooler.add(_still('c', 10, [0.2, 0.9]), _det((1, 1)))
    assert pooler.poll(100 * MS) == [] and len(pooler.poll(400 * MS)) == 1


def test_dwell_without_detections_gives_no_sample():
    pooler = DwellPooler(fk)
    for t in range(0, 300, 30):
        pooler.add(_still('c', t, [0.2, 0.9]), [])
    assert pooler.flush() == []


def test_board_ids_are_pooled_separately():
    pooler = DwellPooler(fk, min_frames=2)
    for t in range(0, 90, 30):
        dets = _det((10.0, 10.0), 4) + _det((50.0, 60.0), 1)
        pooler.add(_still('c', t, [0.2, 0.9]), dets)
    obs = pooler.flush()[0].observations['c']
    np.testing.assert_array_equal(obs.ids, [1, 4])
    np.testing.assert_allclose(obs.uv, [[50, 60], [10, 10]])
    assert obs.n_frames == 3 and obs.spread_px == 0.0


def test_pairer_and_pooler_end_to_end():
    """200 Hz joints, two 30 Hz cameras, two dwells separated by a move."""
    pairer = FramePairer(JOINTS, fk)
    pooler = DwellPooler(fk, min_frames=5)
    q_of_t = (lambda t: [0.2, 0.9] if t < 1.0 else
              ([0.2 + 0.5 * (t - 1.0), 0.9] if t < 1.4 else [0.4, 0.9]))
    samples = []

    def feed(frames):
        for f in frames:
            dets = _det(f.point[:2] * 1000.0) if f.status is PairStatus.STILL else []
            samples.extend(pooler.add(f, dets))

    events = [(k * 5 * MS, 'j', None) for k in range(600)]
    events += [(int(k * 33.3 * MS) + 3 * MS, 'img', 'cam1') for k in range(88)]
    events += [(int(k * 33.3 * MS) + 17 * MS, 'img', 'cam2') for k in range(88)]
    for t, kind, cam in sorted(events):
        if kind == 'j':
            feed(pairer.add_joint_state(t, JOINTS, q_of_t(t * 1e-9))[1])
        else:
            feed(pairer.add_frame(cam, t, payload=cam))
    feed(pairer.flush())
    samples += pooler.flush()
    assert len(samples) == 2
    for s, q in zip(samples, ([0.2, 0.9], [0.4, 0.9])):
        np.testing.assert_allclose(s.q, q, atol=1e-12)
        assert set(s.observations) == {'cam1', 'cam2'}
        assert min(o.n_frames for o in s.observations.values()) >= 15
        np.testing.assert_allclose(s.observations['cam1'].uv[0], s.point_nominal[:2] * 1000)


def test_with_the_robot_model():
    """The real KinematicChain plugs in through a closure: fk(Q) = chain.fk(Q, point=offset)."""
    import os
    from armcal_ros.robot.kinematics import KinematicChain
    urdf = os.path.join(os.path.dirname(__file__), '..', 'urdf', 'puma560.urdf')
    chain = KinematicChain.from_file(urdf, tip_link='tool0')
    offset = np.array([0.0, 0.0, 0.05])
    pairer = FramePairer(chain.joint_names, lambda Q: chain.fk(Q, point=offset), batch_ns=0)
    q0 = np.linspace(0.1, 0.6, chain.n_joints)
    names = list(reversed(chain.joint_names))
    for k in range(20):
        pairer.add_joint_state(k * 5 * MS, names, q0[::-1])
    (frame,) = pairer.add_frame('cam1', 50 * MS)
    assert frame.status is PairStatus.STILL
    np.testing.assert_allclose(frame.q, q0)
    np.testing.assert_allclose(frame.point, chain.fk(q0[None], point=offset)[0])


def test_frames_are_decided_in_batches():
    """With batch_ns, frames wait until the oldest is batch_ns past its window, then go at once."""
    pairer = FramePairer(JOINTS, fk, batch_ns=100 * MS)
    for k in range(20):
        pairer.add_joint_state(k * 5 * MS, JOINTS, [0.2, 0.9])
    assert pairer.add_frame('a', 30 * MS) == [] and pairer.add_frame('b', 40 * MS) == []
    out = []
    for k in range(20, 60):
        out += pairer.add_joint_state(k * 5 * MS, JOINTS, [0.2, 0.9])[1]
        if out:
            break
    assert k * 5 == 150, 'decided once the history reaches 30 + 20 + 100 ms'
    assert [f.camera for f in out] == ['a', 'b']
    assert all(f.status is PairStatus.STILL for f in out)


# -- the views cap of a board: at most max_views detections per camera and dwell --------

def _frame(camera, stamp_ms, point=(0.0, 0.0, 0.0)):
    return PairedFrame(camera, stamp_ms * MS, None, PairStatus.STILL, q=np.array(point, float),
                       point=np.array(point, float), speed=0.0)


def _dets(rng, n_ids=3):
    return [Detection(uv=np.array([100.0 + 50 * i, 200.0]) + rng.normal(0, 0.3, 2), id=i,
                      quality=1.0, radius_px=10.0) for i in range(n_ids)]


def _identity_fk(Q):
    return np.asarray(Q, float)


def test_pooler_cap_counts_views_per_camera_and_pools_the_first_ones():
    rng = np.random.default_rng(0)
    capped = DwellPooler(_identity_fk, min_frames=1, max_views=3)
    reference = DwellPooler(_identity_fk, min_frames=1)
    needed = {'a': 0, 'b': 0}
    for k in range(12):
        cam = 'ab'[k % 2]
        f = _frame(cam, 10 * k)
        dets = _dets(rng) if k != 2 else []      # camera a's second frame shows nothing
        wants = capped.needs_detection(f)
        needed[cam] += wants
        assert capped.add(f, dets if wants else ()) == []
        # The reference sees every frame, with detections only where the capped one looked.
        reference.add(f, dets if wants else ())
    # Camera a needed 4 searches (one found nothing), b 3; the rest were skipped.
    assert needed == {'a': 4, 'b': 3}
    [s] = capped.flush()
    [r] = reference.flush()
    for cam in 'ab':
        assert s.observations[cam].n_frames == 3
        np.testing.assert_array_equal(s.observations[cam].uv, r.observations[cam].uv)
        assert s.observations[cam].spread_px == r.observations[cam].spread_px
        assert s.observations[cam].stamp_ns == r.observations[cam].stamp_ns
    np.testing.assert_array_equal(s.q, r.q)
    assert s.stamp_ns == r.stamp_ns


def test_pooler_cap_ignores_late_detections_and_restarts_with_a_new_dwell():
    rng = np.random.default_rng(1)
    pooler = DwellPooler(_identity_fk, min_frames=1, max_views=2)
    first = [_dets(rng) for _ in range(4)]
    for k, d in enumerate(first):
        pooler.add(_frame('a', 10 * k), d)           # a caller that detects anyway
    far = _frame('a', 50, point=(0.01, 0.0, 0.0))
    assert pooler.needs_detection(far)                # a new dwell: search again
    assert not pooler.needs_detection(_frame('a', 50))
    assert pooler.needs_detection(_frame('a', 50_000))    # after a gap: a new dwell
    assert pooler.needs_detection(_frame('b', 50))         # another camera
    moving = PairedFrame('a', 50 * MS, None, PairStatus.MOVING, q=np.zeros(3),
                         point=np.zeros(3), speed=1.0)
    assert pooler.needs_detection(moving)
    [s] = pooler.add(far, _dets(rng))
    expected = np.mean([[d.uv for d in dets] for dets in first[:2]], axis=0)
    np.testing.assert_allclose(s.observations['a'].uv, expected, atol=1e-12)
    assert s.observations['a'].n_frames == 2
    assert len(pooler.flush()[0].observations['a'].ids) == 3


def test_pooler_cap_validation():
    assert DwellPooler(_identity_fk).max_views == 0
    for bad in (-1, 1.5, True, '3'):
        with pytest.raises(ValueError, match='max_views'):
            DwellPooler(_identity_fk, max_views=bad)
    with pytest.raises(ValueError, match=r'max_views .* >= min_frames \(2\)'):
        DwellPooler(_identity_fk, min_frames=2, max_views=1)


def test_fitted_centres_carry_their_centroids_through_the_dwell():
    pooler = DwellPooler(fk, min_frames=2, outlier_px=2.0)
    q = [0.2, 0.9]
    out = []
    for k in range(6):
        fitted, centroid = np.array([100.0 + 0.01 * k, 50.0]), np.array([100.4, 50.0 + 0.02 * k])
        out += pooler.add(_still('cam1', 33 * k, q), [Detection(
            uv=fitted, id=0, quality=1.0, radius_px=5.0, centroid=centroid)])
        out += pooler.add(_still('cam2', 33 * k + 5, q), _det((10.0, 10.0)))
    out += pooler.flush()
    o1, o2 = out[0].observations['cam1'], out[0].observations['cam2']
    np.testing.assert_allclose(o1.uv, [[100.025, 50.0]])
    np.testing.assert_allclose(o1.centroid_uv, [[100.4, 50.05]])
    assert o1.centroid_spread_px == pytest.approx(np.std(0.02 * np.arange(6)))
    assert o2.centroid_uv is None and o2.centroid_spread_px == 0.0


def _lit_dwell(pooler, rng, n=20, shift=(-0.4, 0.1), sigma_c=0.02, sigma_f=0.08,
               bad_fit=None):
    """Feed one camera's dwell of a still lit ball, fitting only where the pooler asks."""
    centre = np.array([200.0, 120.0])
    fitted_frames = 0
    for k in range(n):
        f = _frame('a', 10 * k)
        c = centre - np.asarray(shift) + rng.normal(0, sigma_c, 2)
        if pooler.needs_fit(f):
            uv = centre + rng.normal(0, sigma_f, 2)
            if bad_fit is not None and fitted_frames == bad_fit:
                uv = uv + 3.0
            fitted_frames += 1
        else:
            uv = np.full(2, np.nan)
        pooler.add(f, [Detection(uv=uv, id=0, quality=1.0, radius_px=6.0, centroid=c)])
    return fitted_frames


def test_fit_cap_pools_all_centroids_and_the_fitted_frames_shift():
    rng = np.random.default_rng(3)
    pooler = DwellPooler(_identity_fk, min_frames=2, max_fits=3)
    assert _lit_dwell(pooler, rng) == 3
    assert not pooler.needs_fit(_frame('a', 300)) and pooler.needs_fit(_frame('b', 300))
    [s] = pooler.flush()
    o = s.observations['a']
    assert o.n_frames == 20
    # The centroid's light bias (0.41 px) is gone: the centre within the noise of 3 fits.
    np.testing.assert_allclose(o.uv[0], [200.0, 120.0], atol=0.15)
    np.testing.assert_allclose(o.centroid_uv[0], [200.4, 119.9], atol=0.03)
    assert 0.005 < o.centroid_spread_px < 0.05


def test_fit_cap_stated_spread_bounds_the_pooled_centres_scatter():
    rng = np.random.default_rng(4)
    errors, stated = [], []
    for _ in range(400):
        pooler = DwellPooler(_identity_fk, min_frames=2, max_fits=4)
        _lit_dwell(pooler, rng, n=24)
        [s] = pooler.flush()
        o = s.observations['a']
        errors.append(o.uv[0] - [200.0, 120.0])
        stated.append(o.spread_px ** 2 / (2.0 * (o.n_frames - 1)))   # per-axis variance
    true_var = np.mean(np.square(errors))            # per axis, both axes pooled
    # Truth: s_c^2 (1/K - 1/n) + s_f^2 / K; stated on average s_c^2 / n + (s_f^2 + s_c^2) / K,
    # an upper bound that the fit's noise dominates here (2 % above the truth).
    expected = 0.02 ** 2 * (1 / 4 - 1 / 24) + 0.08 ** 2 / 4
    assert true_var == pytest.approx(expected, rel=0.15)
    assert np.mean(stated) == pytest.approx(true_var, rel=0.15)


def test_fit_cap_drops_a_bad_fit_and_needs_min_frames_fits():
    rng = np.random.default_rng(5)
    pooler = DwellPooler(_identity_fk, min_frames=2, max_fits=3)
    _lit_dwell(pooler, rng, bad_fit=1)
    [s] = pooler.flush()
    np.testing.assert_allclose(s.observations['a'].uv[0], [200.0, 120.0], atol=0.2)
    # One fitted frame and many centroids: a centroid alone would carry the light's bias.
    pooler = DwellPooler(_identity_fk, min_frames=2, max_fits=2)
    c = np.array([200.4, 119.9])
    pooler.add(_frame('a', 0), [Detection(uv=np.array([200.0, 120.0]), id=0, quality=1.0,
                                          radius_px=6.0, centroid=c)])
    for k in range(1, 8):
        pooler.add(_frame('a', 10 * k), [Detection(uv=np.full(2, np.nan), id=0, quality=1.0,
                                                   radius_px=6.0, centroid=c)])
    assert pooler.flush() == []
    for bad in (-1, 1, True, 2.0):
        with pytest.raises(ValueError, match='max_fits'):
            DwellPooler(_identity_fk, min_frames=2, max_fits=bad)
