"""
Settings: parameter values checked once and split by stage; refusals name the parameters.

A board refuses the noise models that need joint angles, in the settings and again in the
engine's settings; a board target needs its mount estimated or given.
"""
import numpy as np
import pytest

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.priors import PriorSettings
from armcal_ros.engine import EngineSettings
from armcal_ros.frontend.samples import BoardTarget
from armcal_ros.params import defaults
from armcal_ros.settings import (BoardSettings, load_settings, settings_from_values,
                                 with_noise_model)
from helpers.params_files import PUMA_URDF


def test_board_refuses_models_that_need_joint_angles():
    with pytest.raises(ValueError, match='noise_model and marker_type'):
        settings_from_values(dict(defaults(), marker_link='marker', min_samples=12,
                                  robot_description_file=PUMA_URDF, marker_type='charuco',
                                  noise_model='kinematic'))
    board = BoardTarget(np.random.default_rng(0).uniform(size=(6, 3)), estimate_mount=True)
    with pytest.raises(ValueError, match='noise_model hybrid is not available with a board'):
        EngineSettings(['cam'], PriorSettings('hybrid'), SolverSettings(),
                       board=board).validate()
    with pytest.raises(ValueError, match='estimate_marker_offset or target_pose_guess'):
        BoardTarget(np.zeros((4, 3)) + np.arange(4)[:, None], estimate_mount=False)


def _values(**kw):
    return {**defaults(), 'robot_description_file': PUMA_URDF, **kw}


def test_each_stage_gets_its_part():
    s = settings_from_values(_values(camera_names=['a', 'b'],
                                     image_topics=['/a', '/b/compressed'], aruco_id=-1,
                                     max_views_per_dwell=2, dwell_radius=0.002,
                                     max_samples=50, pixel_sigma=0.3, kernel='matern32',
                                     min_samples=7, publish_tf=False, output_dir='/tmp/x'))
    assert s.inputs.camera_names == ('a', 'b') and not s.inputs.pose_input
    assert s.inputs.arm_topic == '/joint_states'
    assert s.robot.urdf_text().startswith('<') and s.robot.marker_link == 'tool0'
    assert s.detector.aruco_id is None and s.detector.max_views_per_dwell == 2
    assert s.front_end.dwell_radius == 0.002 and s.store.max_samples == 50
    assert s.solver.pixel_sigma == 0.3 and s.prior.kernel == 'matern32'
    assert s.schedule.min_samples == 7
    assert s.outputs.output_dir == '/tmp/x' and s.outputs.publish_tf is False
    pose = settings_from_values(_values(pose_topic='/tool', robot_description_file=''))
    assert pose.inputs.pose_input and pose.inputs.arm_topic == '/tool'


def test_default_output_dir_follows_ros_home(monkeypatch):
    monkeypatch.setenv('ROS_HOME', '/srv/ros')
    assert settings_from_values(_values()).outputs.output_dir == '/srv/ros/armcal'


@pytest.mark.parametrize('name, value', [('pixel_sigma', -1.0), ('camera_names', []),
                                         ('noise_model', 'gp'), ('free_distortion', ['k9'])])
def test_a_bad_value_is_refused_naming_the_parameter(name, value):
    with pytest.raises(ValueError, match=f'parameter.* {name}'):
        settings_from_values(_values(**{name: value}))


def test_with_noise_model_checks_the_name():
    s = settings_from_values(_values())
    assert with_noise_model(s, 'kinematic').prior.model == 'kinematic'
    assert s.prior.model == 'auto'
    with pytest.raises(ValueError, match='noise_model'):
        with_noise_model(s, 'gaussian')


def test_board_settings_are_completed_from_a_data_set_and_checked():
    b = BoardSettings(rows=7)
    done = b.completed((7, 5, 0.04, 0.02, 10))
    assert (done.rows, done.cols, done.square_size, done.marker_size, done.dictionary) == \
        (7, 5, 0.04, 0.02, 10)
    with pytest.raises(ValueError, match='parameter charuco_rows: 6 disagrees'):
        BoardSettings(rows=6).completed((7, 5, 0.04, 0.02, 10))
    with pytest.raises(ValueError, match='charuco_cols, charuco_square_size'):
        b.completed()


def test_load_settings_applies_overrides_before_the_checks(tmp_path):
    p = tmp_path / 'p.yaml'
    p.write_text('armcal:\n  ros__parameters:\n    robot_description_file: '
                 f'{PUMA_URDF}\n    noise_model: fixed\n')
    assert load_settings(str(p)).prior.model == 'fixed'
    assert load_settings(str(p), {'noise_model': 'hybrid'}).prior.model == 'hybrid'
    with pytest.raises(ValueError, match='noise_model'):
        load_settings(str(p), {'noise_model': 'nope'})
