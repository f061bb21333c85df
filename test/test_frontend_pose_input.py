"""Pose input: the link pose history, stillness of an extended target, the mean of poses."""

import numpy as np
from scipy.spatial.transform import Rotation

from armcal_ros.frontend.pairing import FramePairer, JointStatus, PairStatus
from armcal_ros.frontend.pose_input import mean_pose_vector, pose_points, PoseHistory


def _pose_pairer(ref, **kw):
    return FramePairer((), lambda C: pose_points(C, ref), history=PoseHistory(), **kw)


def test_pose_stillness_counts_a_turn_of_an_extended_target():
    """A board turning about the link origin is moving even though the link origin is still."""
    board_ref = np.array([[0.2, 0, 0], [0, 0.2, 0], [-0.2, 0, 0], [0, -0.2, 0]])
    results = {}
    for name, ref in (('point', np.zeros((1, 3))), ('board', board_ref)):
        pairer = _pose_pairer(ref)
        for k in range(100):                          # 10 ms poses, 0.5 rad/s about z
            q = Rotation.from_rotvec([0, 0, 0.005 * k]).as_quat()
            assert pairer.add_pose(k * 10_000_000, [0.5, 0, 0.2], q)[0] is JointStatus.OK
        (frame,) = pairer.add_frame('cam', 500_000_000) + pairer.flush()
        results[name] = frame
    assert results['point'].status is PairStatus.STILL
    assert results['board'].status is PairStatus.MOVING
    assert np.isclose(results['board'].speed, 0.5 * 0.2, rtol=1e-3)
    assert results['board'].point.shape == (4, 3)


def test_pose_history_interpolates_and_handles_gaps_and_time_jumps():
    h = PoseHistory(capacity=8, max_gap_ns=100_000_000, jump_threshold_ns=500_000_000)
    q1 = Rotation.from_rotvec([0, 0.1, 0]).as_quat()
    assert h.add(0, [0, 0, 0], [0, 0, 0, 1]) is JointStatus.OK
    assert h.add(50_000_000, [0.01, 0, 0], q1) is JointStatus.OK
    assert h.add(400_000_000, [0.01, 0, 0], q1) is JointStatus.OK
    assert h.add(400_000_000, [0.01, 0, 0], q1) is JointStatus.DUPLICATE
    assert h.add(300_000_000, [0.01, 0, 0], q1) is JointStatus.OUT_OF_ORDER
    assert h.add(1, [0, 0, 0], [0, 0, 0, 2]) is JointStatus.NON_FINITE
    st, c = h.lookup([25_000_000, 200_000_000, -1, 500_000_000])
    assert list(st) == [PairStatus.OK, PairStatus.GAP, PairStatus.BEFORE_HISTORY,
                        PairStatus.AFTER_HISTORY]
    np.testing.assert_allclose(c[0, :3], [0.005, 0, 0])
    assert np.isclose(Rotation.from_quat(c[0, 3:]).magnitude(), 0.05)
    assert np.all(np.isnan(c[1:]))
    for k in range(20):                                # bounded: keeps the newest 8
        h.add(500_000_000 + k * 10_000_000, [0, 0, 0], [0, 0, 0, 1])
    assert len(h) == 8 and h.first_stamp == 500_000_000 + 12 * 10_000_000
    assert h.add(0, [0, 0, 0], [0, 0, 0, 1]) is JointStatus.TIME_JUMP and len(h) == 1


def test_mean_pose_vector_is_rotation_aware():
    r = Rotation.from_rotvec([[0, 0, np.pi - 0.01], [0, 0, -np.pi + 0.01]])
    C = np.column_stack([[[0, 0, 0], [0.002, 0, 0]], r.as_quat()])
    m = mean_pose_vector(C)
    np.testing.assert_allclose(m[:3], [0.001, 0, 0])
    # The naive mean of the two rotation vectors would be no rotation at all.
    assert np.isclose(Rotation.from_quat(m[3:]).magnitude(), np.pi, atol=1e-6)
