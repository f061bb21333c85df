"""
Pose input for point targets: a measured link pose instead of joint angles.

One 30 s simulated bag carries both the joint states and the marker link's pose (TransformStamped,
nominal forward kinematics at the joint readings, as a controller reports it).  Calibrating it
from the pose topic must match the simulator's truth with the tolerances of test_offline.py, and
agree closely with the same bag calibrated from joint states: the two inputs give the same
nominal points.
"""

import argparse
import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.compare import compare
from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.priors import PriorSettings
from armcal_ros.engine import EngineSettings
from armcal_ros.frontend.pairing import FramePairer, JointStatus, PairStatus
from armcal_ros.frontend.pose_input import mean_pose_vector, pose_points, PoseHistory
from armcal_ros.frontend.samples import BoardTarget
from armcal_ros.io.bag import bag_topics
from armcal_ros.io.calib_files import read_cameras
from armcal_ros.offline import calibrate_bag, CalibrateError, run
from armcal_ros.params import defaults
from armcal_ros.frontend.collector import SampleCollector
from armcal_ros.settings import settings_from_values
from armcal_ros.sim.cell import simulate_cell
from armcal_ros.sim.output import write_sim_bag

POSE_TOPIC = '/tool_pose'
URDF = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'urdf',
                    'puma560.urdf')


@pytest.fixture(scope='module')
def sim_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp('posesim') / 'bag'
    write_sim_bag(simulate_cell('geometric', seed=3, duration=30.0), bag,
                  pose_topic=POSE_TOPIC, pose_type='transform_stamped')
    return bag


def _values(**kw):
    v = defaults()
    v.update(marker_link='marker', min_samples=12, noise_model='correlated',
             robot_description_file=URDF)
    v.update(kw)
    return settings_from_values(v)


def _cameras(out):
    _, cams = read_cameras(out)
    return {c.name: c for c in cams}


def test_simulator_writes_the_link_pose_topic(sim_bag):
    topics = bag_topics(sim_bag)
    assert topics[POSE_TOPIC][0] == 'geometry_msgs/msg/TransformStamped'
    assert topics[POSE_TOPIC][1] == topics['/joint_states'][1]


@pytest.mark.slow
def test_pose_input_sphere_bag_matches_truth_and_joint_input(sim_bag, tmp_path):
    pose = calibrate_bag(sim_bag, _values(pose_topic=POSE_TOPIC, robot_description_file=''),
                         tmp_path / 'pose')
    rep = pose.report
    assert rep['accepted'] and rep['n_samples'] >= 12
    assert rep['front_end']['poses'] > 0 and 'joint_states' not in rep['front_end']
    assert rep['input']['arm'] == f'pose_topic {POSE_TOPIC}'
    est = _cameras(tmp_path / 'pose')
    score = compare(est, sim_bag / 'ground_truth')
    for name in ('cam1', 'cam2', 'cam3'):
        assert score.per_camera[name]['focal_pct'] < 3.0, score.per_camera[name]
        assert score.per_camera[name]['centre_mm'] < 40.0, score.per_camera[name]
    assert score.absolute_mm < 3.0 and score.shape_mm < 1.0, score
    # The same bag from joint states: the same nominal points, so nearly the same cameras.
    joint = calibrate_bag(sim_bag, _values(), tmp_path / 'joint')
    assert abs(joint.report['n_samples'] - rep['n_samples']) <= 1
    ref = _cameras(tmp_path / 'joint')
    for name, c in est.items():
        assert abs(c.fx - ref[name].fx) < 0.002 * ref[name].fx
        assert np.linalg.norm(c.center - ref[name].center) < 0.005


@pytest.mark.slow
def test_pose_input_auto_chooses_among_the_point_models(sim_bag, tmp_path):
    res = calibrate_bag(sim_bag, _values(pose_topic=POSE_TOPIC, robot_description_file='',
                                         noise_model='auto'), tmp_path / 'auto')
    assert res.report['accepted']
    assert res.report['chosen']['model'] in ('fixed', 'independent', 'correlated')


def test_pose_input_refuses_models_that_need_joint_angles(sim_bag, tmp_path):
    with pytest.raises(ValueError, match='noise_model kinematic.*pose_topic|pose_topic.*'
                       'noise_model kinematic'):
        _values(pose_topic=POSE_TOPIC, noise_model='kinematic')
    with pytest.raises(ValueError, match='noise_model and pose_topic: noise_model hybrid'):
        _values(pose_topic=POSE_TOPIC, noise_model='hybrid')
    params = tmp_path / 'p.yaml'
    params.write_text('armcal:\n  ros__parameters:\n    marker_link: marker\n'
                      f'    pose_topic: {POSE_TOPIC}\n')
    with pytest.raises(CalibrateError, match='noise_model and pose_topic'):
        run(argparse.Namespace(bag=str(sim_bag), params=str(params),
                               output=str(tmp_path / 'o'), noise_model='kinematic', quiet=True))
    # auto is allowed: without joint angles it chooses among fixed, independent, correlated.
    _values(pose_topic=POSE_TOPIC, noise_model='auto')


def test_pose_input_with_a_joint_state_topic_only_says_what_is_missing(sim_bag, tmp_path):
    with pytest.raises(CalibrateError, match='pose_topic /nope'):
        calibrate_bag(sim_bag, _values(pose_topic='/nope'), tmp_path / 'o')
    with pytest.raises(CalibrateError, match='pose_topic /joint_states carries '
                       'sensor_msgs/msg/JointState'):
        calibrate_bag(sim_bag, _values(pose_topic='/joint_states'), tmp_path / 'o')


def test_board_refuses_models_that_need_joint_angles():
    with pytest.raises(ValueError, match='noise_model and marker_type'):
        _values(marker_type='charuco', noise_model='kinematic')
    board = BoardTarget(np.random.default_rng(0).uniform(size=(6, 3)), estimate_mount=True)
    with pytest.raises(ValueError, match='noise_model hybrid is not available with a board'):
        EngineSettings(['cam'], PriorSettings('hybrid'), SolverSettings(),
                       board=board).validate()
    with pytest.raises(ValueError, match='estimate_marker_offset or target_pose_guess'):
        BoardTarget(np.zeros((4, 3)) + np.arange(4)[:, None], estimate_mount=False)


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


def test_collector_without_a_robot_model_takes_poses_not_joint_states():
    col = SampleCollector(None, [0, 0, 0.1], ['cam'], {'cam': object()})
    assert col.pose_input
    assert col.add_joint_state(0, ['j1'], [0.0]) == []
    assert col.counts['joint_state_unused'] == 1
    assert col.add_pose(0, [0, 0, 0], [0, 0, 0, 1]) == []
    assert col.add_pose(1, [0, 0, 0], [0, 0, 0, 5]) == []
    assert col.counts['poses'] == 2 and col.counts['pose_invalid'] == 1
