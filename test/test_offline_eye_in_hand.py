"""
Cameras on the arm (``eye_in_hand``): a static board, the camera riding on the link.

The board scene of helpers/board_scene.py with the roles swapped: the board stands in the base
frame at ``T_BASE_BOARD``, the camera rides on the link at ``T_LINK_CAM``, and each capture's
link pose is the one that shows the board as the static scene's views do.  Calibrated from the
capture folder with the board's place estimated (hand-eye seed), the camera's pose on the link
and the board's in the base come back to millimetres.
"""

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from armcal_ros.core.target import invert
from armcal_ros.params import defaults
from armcal_ros.settings import settings_from_values
from helpers.board_scene import BOARD_SIZE, transform, write_capture_folder
from helpers.captures import import_and_calibrate

T_LINK_CAM = transform([0.1, -0.3, 1.4], [0.03, -0.08, 0.05])
T_BASE_BOARD = transform([3.0, 0.2, 0.1], [0.6, 0.1, 0.02])


def link_of(T_cb):
    """Return the link pose whose camera sees the static board at camera-from-board ``T_cb``."""
    return T_BASE_BOARD @ invert(T_cb) @ invert(T_LINK_CAM)


def _angle_deg(Ra, Rb):
    return np.degrees(Rotation.from_matrix(Ra.T @ Rb).magnitude())


def test_a_camera_on_the_link_and_a_static_board(tmp_path):
    folder = tmp_path / 'captures'
    write_capture_folder(str(folder), n=10, link_of=link_of)
    report = import_and_calibrate(folder, tmp_path, marker_type='charuco',
                                  estimate_marker_offset='true', eye_in_hand='true',
                                  noise_model='fixed', free_distortion=[], min_samples=3,
                                  **BOARD_SIZE)
    assert report['n_samples'] == 10
    with open(tmp_path / 'out' / 'extrinsics.yaml') as f:
        ext = yaml.safe_load(f)
    assert ext['base_frame'] == 'tool0'            # the camera's pose is on the link
    cam = ext['cameras']['cam']
    assert np.linalg.norm(np.array(cam['translation']) - T_LINK_CAM[:3, 3]) < 3e-3
    R = Rotation.from_quat(cam['rotation']).as_matrix()
    assert _angle_deg(R, T_LINK_CAM[:3, :3]) < 0.3
    T = report['target']['T_link_target']          # the board's pose in the base frame
    assert np.linalg.norm(np.array(T[:3]) - T_BASE_BOARD[:3, 3]) < 3e-3
    assert _angle_deg(Rotation.from_quat(T[3:]).as_matrix(), T_BASE_BOARD[:3, :3]) < 0.3


def test_eye_in_hand_needs_the_targets_place_estimated_and_no_kinematic_model():
    base = dict(defaults(), robot_description='<robot name="x"/>', eye_in_hand=True)
    with pytest.raises(ValueError, match='eye_in_hand and estimate_marker_offset'):
        settings_from_values(base)
    with pytest.raises(ValueError, match='noise_model and eye_in_hand'):
        settings_from_values(dict(base, estimate_marker_offset=True, noise_model='hybrid'))
