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


def test_given_intrinsics_from_camera_info_files(tmp_path):
    # As camera_calibration writes it, with its default name (a '/' in it).
    (tmp_path / 'left.yaml').write_text(
        'image_width: 640\nimage_height: 480\ncamera_name: narrow_stereo/left\n'
        'camera_matrix: {rows: 3, cols: 3, data: [612.0, 0, 318.0, 0, 611.0, 242.0, 0, 0, 1]}\n'
        'distortion_model: plumb_bob\n'
        'distortion_coefficients: {rows: 1, cols: 5, data: [0.01, -0.02, 0, 0, 0]}\n')
    p = tmp_path / 'p.yaml'
    p.write_text('armcal:\n  ros__parameters:\n'
                 f'    robot_description_file: {PUMA_URDF}\n'
                 '    camera_names: [l, r]\n    image_topics: [/l, /r]\n'
                 '    intrinsics_mode: [fixed, estimate]\n'
                 '    intrinsics_files: [left.yaml, ""]\n')
    s = load_settings(str(p))       # the relative file name is found beside p.yaml
    given = s.solver.intrinsics
    assert list(given) == ['l'] and given['l'].mode == 'fixed'
    assert tuple(given['l'].intrinsics) == (612.0, 611.0, 318.0, 242.0)
    assert (given['l'].width, given['l'].height) == (640, 480)
    prior = load_settings(str(p), {'intrinsics_mode': ['prior'], 'intrinsics_sigma_px': 3.0,
                                   'intrinsics_files': ['left.yaml', 'left.yaml']})
    assert prior.solver.intrinsics['r'].sigma == (3.0,) * 4
    assert prior.solver.intrinsics['r'].sigma_dist is None


@pytest.mark.parametrize('change, why', [
    ({'intrinsics_mode': ['fixed', 'fixed', 'fixed']}, 'empty, one mode, or one per camera'),
    ({'intrinsics_mode': ['fixed'], 'intrinsics_files': ['a.yaml']},
     'must be empty .* or have one entry per camera'),
    ({'intrinsics_mode': ['prior'], 'intrinsics_files': ['a.yaml', 'a.yaml']},
     'needs intrinsics_sigma_px > 0'),
    ({'intrinsics_mode': ['focus']}, 'unknown modes'),
    ({'intrinsics_mode': ['fixed'], 'intrinsics_files': ['/nope.yaml', '/nope.yaml']},
     'intrinsics_files: camera l'),
])
def test_given_intrinsics_are_refused_with_the_reason(change, why):
    with pytest.raises(ValueError, match=why):
        settings_from_values(_values(camera_names=['l', 'r'], image_topics=['/l', '/r'],
                                     **change))


def test_given_cameras_without_a_file_wait_for_their_camera_info_topic():
    s = settings_from_values(_values(camera_names=['l', 'r'],
                                     image_topics=['/l/image_raw', '/r/image_raw/compressed'],
                                     intrinsics_mode=['prior'], intrinsics_sigma_px=2.0))
    assert s.solver.intrinsics == {}
    assert s.intrinsics.topics == (('l', '/l/camera_info'), ('r', '/r/camera_info'))
    from armcal_ros.core.camera import Camera
    given = s.intrinsics.prior_from('r', Camera('r', 640, 480, 600.0, 601.0, 320.0, 240.0))
    assert given.mode == 'prior' and given.sigma == (2.0,) * 4 and given.width == 640
