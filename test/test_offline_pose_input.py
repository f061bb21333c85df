"""
``armcal calibrate`` with pose input for point targets: a measured link pose, not joint angles.

One 30 s simulated bag carries both the joint states and the marker link's pose (TransformStamped,
nominal forward kinematics at the joint readings, as a controller reports it).  Calibrating it
from the pose topic must match the simulator's truth with the tolerances of test_offline.py, and
agree closely with the same bag calibrated from joint states: the two inputs give the same
nominal points.
"""

import argparse

import numpy as np
import pytest

from armcal_ros.compare import compare
from armcal_ros.io.bag import bag_topics
from armcal_ros.io.calib_files import read_cameras
from armcal_ros.offline import calibrate_bag, CalibrateError, run
from armcal_ros.params import defaults
from armcal_ros.settings import settings_from_values
from armcal_ros.sim.cell import simulate_cell
from armcal_ros.sim.output import write_sim_bag
from helpers.params_files import PUMA_URDF

POSE_TOPIC = '/tool_pose'


@pytest.fixture(scope='module')
def sim_bag(tmp_path_factory):
    bag = tmp_path_factory.mktemp('posesim') / 'bag'
    write_sim_bag(simulate_cell('geometric', seed=3, duration=30.0), bag,
                  pose_topic=POSE_TOPIC, pose_type='transform_stamped')
    return bag


def _values(**kw):
    v = defaults()
    v.update(marker_link='marker', min_samples=12, noise_model='correlated',
             robot_description_file=PUMA_URDF)
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


@pytest.mark.parametrize('pose_input', [True, False])
def test_a_point_markers_place_is_estimated_from_a_guess_3_cm_off(sim_bag, tmp_path, pose_input):
    # The sphere sits at the origin of the URDF's `marker` link (plus the simulator's 0.2 mm
    # mount error); the guess is 3 cm off.  Estimated as a one-point target, its place comes
    # back to a millimetre, the cameras to the tolerances of the known-place calibration.
    guess = [0.02, -0.015, 0.015]
    kw = dict(pose_topic=POSE_TOPIC, robot_description_file='') if pose_input else {}
    res = calibrate_bag(sim_bag, _values(marker_offset=guess, estimate_marker_offset=True,
                                         noise_model='fixed', **kw), tmp_path / 'out')
    tgt = res.report['target']
    assert tgt['estimated'] and np.linalg.norm(guess) > 0.029
    assert np.linalg.norm(tgt['T_link_target'][:3]) < 1.5e-3, tgt
    assert max(tgt['std'][:3]) < 1e-3
    score = compare(_cameras(tmp_path / 'out'), sim_bag / 'ground_truth')
    for name in ('cam1', 'cam2', 'cam3'):
        assert score.per_camera[name]['focal_pct'] < 3.0, score.per_camera[name]
        assert score.per_camera[name]['centre_mm'] < 40.0, score.per_camera[name]
    assert score.shape_mm < 1.0, score


@pytest.mark.slow
@pytest.mark.parametrize('model', ['kinematic', 'hybrid'])
def test_a_kinematic_model_estimates_the_place_from_a_guess_3_cm_off(sim_bag, tmp_path, model):
    # Under a kinematic model the place is the marker mount's translation error, given a wide
    # prior about the guess; the arm's other errors are estimated beside it as usual.
    guess = [0.02, -0.015, 0.015]
    res = calibrate_bag(sim_bag, _values(marker_offset=guess, estimate_marker_offset=True,
                                         noise_model=model), tmp_path / 'out')
    assert res.report['accepted'] and res.report['chosen']['model'] == model
    tgt = res.report['target']
    assert tgt['estimated']
    # The truth is the link's origin plus the simulator's 0.2 mm mount error.  The place
    # shares its correction with the wrist joints' origin errors (0.5 mm prior each, the same
    # marker motion), so it is known to about half a millimetre; the reported std must cover
    # the error (three standard deviations).  The fixed stage found it first (the cameras
    # cannot start from points 3 cm off).
    err = np.abs(np.array(tgt['T_link_target'][:3]))
    assert np.linalg.norm(err) < 1.5e-3, tgt
    assert np.all(err < 3 * np.array(tgt['std'][:3])), tgt
    assert max(tgt['std'][:3]) < 1.5e-3
    assert 'fixed stage moved the guess by 29' in res.report['chosen']['place_stage']
    assert (tmp_path / 'out' / 'target.yaml').exists()
    score = compare(_cameras(tmp_path / 'out'), sim_bag / 'ground_truth')
    for name in ('cam1', 'cam2', 'cam3'):
        assert score.per_camera[name]['focal_pct'] < 3.0, score.per_camera[name]
        assert score.per_camera[name]['centre_mm'] < 40.0, score.per_camera[name]
    assert score.shape_mm < 1.0, score
