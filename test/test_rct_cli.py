"""armcal calibrate on a robot_cal_tools folder: rendered board images and poses, end to end."""

import argparse
import os

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from armcal_ros.core.target import invert, pose_vector
from armcal_ros.frontend.detectors import CharucoBoard
from armcal_ros.io.calib_files import read_camera_info
from armcal_ros.offline import CalibrateError, run

W, H = 800, 600
K = np.array([[700.0, 0, 399.5], [0, 705.0, 299.5], [0, 0, 1]])
BOARD = CharucoBoard(7, 5, 0.04, 0.02, 'DICT_6X6_250')
MOUNT = np.eye(4)
MOUNT[:3, :3] = Rotation.from_rotvec([0.2, -1.9, 0.3]).as_matrix()
MOUNT[:3, 3] = [0.03, 0.08, 0.15]
T_CAM_BASE = np.eye(4)
T_CAM_BASE[:3, :3] = Rotation.from_rotvec([2.0, 0.3, -0.2]).as_matrix()
T_CAM_BASE[:3, 3] = [0.1, -0.2, 1.4]


def render(T_ct, pps=50, margin=25):
    """Render the board at camera-from-target pose T_ct (pinhole K, light blur and noise)."""
    tex = BOARD.render(pps, margin)
    s = BOARD.square_size / pps
    S = np.array([[s, 0, -(margin - 0.5) * s], [0, s, -(margin - 0.5) * s], [0, 0, 1]])
    Hm = K @ np.column_stack([T_ct[:3, 0], T_ct[:3, 1], T_ct[:3, 3]]) @ S
    img = cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_LINEAR, borderValue=128)
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.7)
    img += np.random.default_rng(0).normal(0, 1.5, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def write_folder(root, n_views=8, seed=0):
    rng = np.random.default_rng(seed)
    os.makedirs(os.path.join(root, 'images'))
    os.makedirs(os.path.join(root, 'poses'))
    centre = np.array([2.5 * 0.04, 3.5 * 0.04, 0.0])
    entries = []
    for v in range(n_views):
        R = Rotation.from_rotvec(rng.uniform(-0.5, 0.5, 3)).as_matrix()
        T_ct = np.eye(4)
        T_ct[:3, :3] = R
        T_ct[:3, 3] = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04),
                                rng.uniform(0.65, 0.8)]) - R @ centre
        T_bl = invert(T_CAM_BASE) @ T_ct @ invert(MOUNT)
        cv2.imwrite(os.path.join(root, 'images', f'{v}.png'), render(T_ct))
        x, y, z, qx, qy, qz, qw = (float(a) for a in pose_vector(T_bl))
        with open(os.path.join(root, 'poses', f'{v}.yaml'), 'w') as f:
            yaml.safe_dump(dict(x=x, y=y, z=z, qx=qx, qy=qy, qz=qz, qw=qw), f)
        entries.append(dict(image=f'images/{v}.png', pose=f'poses/{v}.yaml'))
    with open(os.path.join(root, 'cal_data.yaml'), 'w') as f:
        yaml.safe_dump(entries, f)
    with open(os.path.join(root, 'target.yaml'), 'w') as f:
        yaml.safe_dump(dict(target_finder=dict(
            type='rct_ros_tools::CharucoGridTargetFinderPlugin', rows=7, cols=5,
            chessboard_dim=0.04, aruco_marker_dim=0.02, dictionary=10)), f)


def params(path, **extra):
    p = dict(camera_names=['cam'], image_topics=['/cam/image_raw'], marker_type='charuco',
             estimate_marker_offset=True, noise_model='fixed', free_distortion=[],
             min_samples=3)
    p.update(extra)
    with open(path, 'w') as f:
        yaml.safe_dump({'armcal': {'ros__parameters': p}}, f)
    return str(path)


@pytest.fixture(scope='module')
def folder(tmp_path_factory):
    root = str(tmp_path_factory.mktemp('rct') / 'set')
    write_folder(root)
    return root


def test_calibrate_a_folder_end_to_end(folder, tmp_path, capsys):
    out = str(tmp_path / 'out')
    args = argparse.Namespace(bag=folder, params=params(tmp_path / 'p.yaml'), output=out,
                              noise_model=None, quiet=True)
    assert run(args) == 0
    printed = capsys.readouterr().out
    assert 'T_tool0_target' in printed and '(estimated)' in printed
    for name in ('cam.yaml', 'extrinsics.yaml', 'calibration.json', 'target.yaml',
                 'report.json'):
        assert os.path.isfile(os.path.join(out, name)), name
    cam = read_camera_info(os.path.join(out, 'cam.yaml'))
    assert abs(cam.fx - K[0, 0]) < 3 and abs(cam.fy - K[1, 1]) < 3
    assert abs(cam.cx - K[0, 2]) < 3 and abs(cam.cy - K[1, 2]) < 3
    with open(os.path.join(out, 'target.yaml')) as f:
        tgt = yaml.safe_load(f)
    assert tgt['estimated'] is True
    assert np.linalg.norm(np.array(tgt['translation']) - MOUNT[:3, 3]) < 2e-3
    q = Rotation.from_quat(tgt['rotation_xyzw'])
    assert (q.inv() * Rotation.from_matrix(MOUNT[:3, :3])).magnitude() < np.radians(0.2)


def test_wrong_board_parameters_are_named(folder, tmp_path):
    args = argparse.Namespace(bag=folder, params=params(tmp_path / 'p.yaml', charuco_rows=6),
                              output=str(tmp_path / 'out'), noise_model=None, quiet=True)
    with pytest.raises(CalibrateError, match='charuco_rows'):
        run(args)


def test_unknown_mount_without_estimation_is_refused(folder, tmp_path):
    args = argparse.Namespace(
        bag=folder, params=params(tmp_path / 'p.yaml', estimate_marker_offset=False),
        output=str(tmp_path / 'out'), noise_model=None, quiet=True)
    with pytest.raises(CalibrateError, match='estimate_marker_offset or target_pose_guess'):
        run(args)
