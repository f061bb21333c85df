"""The composition root: settings in, the wired pipeline out, for each target and input."""

import numpy as np
import pytest

from armcal_ros.compose import build_board, build_pipeline, engine_settings
from armcal_ros.frontend.detectors import ArucoDetector, CharucoDetector, SphereDetector
from armcal_ros.params import defaults
from armcal_ros.settings import settings_from_values
from helpers.params_files import PUMA_URDF

BOARD = dict(marker_type='charuco', charuco_rows=7, charuco_cols=5, charuco_square_size=0.04,
             charuco_marker_size=0.02, noise_model='fixed')


def _settings(**kw):
    return settings_from_values({**defaults(), 'robot_description_file': PUMA_URDF,
                                 'marker_link': 'marker', **kw})


def test_sphere_with_joint_input_gets_a_chain_and_the_kinematic_jacobian():
    pipe = build_pipeline(_settings(camera_names=['l', 'r'], image_topics=['/l', '/r']))
    assert pipe.chain is not None and pipe.board is None
    assert sorted(pipe.collector.detectors) == ['l', 'r']
    assert all(isinstance(d, SphereDetector) for d in pipe.collector.detectors.values())
    assert pipe.collector.detectors['l'] is not pipe.collector.detectors['r']
    assert pipe.engine.kinematics_fn is not None
    assert list(pipe.engine.store.joint_names) == list(pipe.chain.joint_names)
    kin = pipe.engine.kinematics_fn(np.zeros((2, len(pipe.chain.joint_names))))
    assert kin.jacobian.shape == (2, 3, len(pipe.chain.error_names))


def test_pose_input_needs_no_robot_model():
    pipe = build_pipeline(_settings(pose_topic='/tool', robot_description_file='',
                                    marker_type='aruco', aruco_id=3, noise_model='correlated'))
    assert pipe.chain is None and pipe.collector.pose_input
    assert pipe.engine.kinematics_fn is None
    det = pipe.collector.detectors['cam1']
    assert isinstance(det, ArucoDetector) and det.marker_id == 3


def test_a_board_gets_its_target_and_a_folder_completes_it():
    pipe = build_pipeline(_settings(estimate_marker_offset=True, **BOARD))
    assert isinstance(pipe.collector.detectors['cam1'], CharucoDetector)
    target = pipe.engine.settings.board
    assert target is not None and target.estimate_mount and target.T_link_target is None
    assert len(target.points) == len(pipe.board.points()) == 24
    assert pipe.engine.kinematics_fn is None      # the board's mount, not the arm's errors
    # A data set's target.yaml fills unset sizes; its mount guess seeds the target.
    guess = np.eye(4)
    guess[:3, 3] = [0.01, 0.02, 0.03]
    s = _settings(marker_type='charuco', estimate_marker_offset=True, noise_model='fixed')
    board, target = build_board(s, (7, 5, 0.04, 0.02, 'DICT_6X6_250'), guess)
    assert (board.rows, board.cols) == (7, 5)
    np.testing.assert_array_equal(target.T_link_target, guess)


def test_an_unreadable_robot_model_names_its_parameters():
    with pytest.raises(ValueError, match='robot_description_file.*cannot read'):
        build_pipeline(_settings(robot_description_file='/nonexistent.urdf'))
    with pytest.raises(ValueError, match='robot model .*marker_link'):
        build_pipeline(_settings(marker_link='no_such_link'))


def test_engine_settings_follow_the_settings():
    s = _settings(min_samples=9, solve_period=3.0, noise_model='independent')
    e = engine_settings(s)
    assert (e.min_samples, e.solve_period_s, e.prior.model) == (9, 3.0, 'independent')
    assert e.camera_names == ['cam1', 'cam2', 'cam3'] and e.marker_link == 'marker'


def test_decoded_targets_need_one_frame_a_sphere_two():
    assert build_pipeline(_settings()).collector.pooler.min_frames == 2
    assert build_pipeline(_settings(marker_type='aruco')).collector.pooler.min_frames == 1
    pipe = build_pipeline(_settings(estimate_marker_offset=True, **BOARD))
    assert pipe.collector.pooler.min_frames == 1


def test_a_lit_marker_needs_its_radius_and_a_sphere():
    from armcal_ros.params import check_value
    lit = engine_settings(_settings(marker_lamp=[0.5, 0.0, 1.5], marker_radius=0.005,
                                    sphere_centre='centroid'))
    assert lit.marker_light == ((0.5, 0.0, 1.5), 0.25, 0.005)
    assert engine_settings(_settings()).marker_light is None
    with pytest.raises(ValueError, match='marker_radius'):
        engine_settings(_settings(marker_lamp=[0.5, 0.0, 1.5], sphere_centre='centroid'))
    # The default centre is a fitted one: a lamp given with it is refused, not ignored.
    with pytest.raises(ValueError, match='needs sphere_centre centroid'):
        engine_settings(_settings(marker_lamp=[0.5, 0.0, 1.5], marker_radius=0.005))
    with pytest.raises(ValueError, match='marker_lamp'):
        check_value('marker_lamp', [0.5, 0.0])
    with pytest.raises(ValueError, match='marker_ambient'):
        check_value('marker_ambient', 1.2)


def test_a_fitted_centre_is_not_lamp_corrected_and_pooling_is_switched_by_the_centre():
    with pytest.raises(ValueError, match='sphere_centre'):
        engine_settings(_settings(marker_lamp=[0.5, 0.0, 1.5], marker_radius=0.005,
                                  sphere_centre='shaded'))
    assert engine_settings(_settings(sphere_centre='shaded_pooled')).pool_light_shift
    assert not engine_settings(_settings(sphere_centre='shaded')).pool_light_shift
    assert not engine_settings(_settings(sphere_centre='centroid')).pool_light_shift
    assert engine_settings(_settings()).pool_light_shift       # the default
    from armcal_ros.compose import build_detectors
    det = build_detectors(_settings(sphere_centre='shaded_pooled'), ['cam1', 'cam2'])
    assert [d.centre for d in det.values()] == ['shaded', 'shaded']


def test_only_a_pooled_shaded_ball_is_fitted_in_a_few_frames_per_dwell():
    from armcal_ros.compose import FITS_PER_VIEW_POOLED
    fits = {c: build_pipeline(_settings(sphere_centre=c)).collector.pooler.max_fits
            for c in ('shaded_pooled', 'shaded', 'centroid')}
    # Unpooled, a view's own fit is its centre: every frame's fit counts.
    assert fits == {'shaded_pooled': FITS_PER_VIEW_POOLED, 'shaded': 0, 'centroid': 0}
    assert build_pipeline(_settings(estimate_marker_offset=True, **BOARD)
                          ).collector.pooler.max_fits == 0
