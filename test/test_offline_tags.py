"""
An ArUco tag as a rigid four-corner target (``aruco_size`` > 0) on the link, end to end.

A 6 cm tag rides on a link at an unknown pose (``MOUNT``); one static camera with known
(factory) intrinsics sees it in 10 captures written as a capture folder, imported into a bag and
calibrated with ``estimate_marker_offset``: the mount comes back from hand-eye plus the
adjustment, the camera's pose to millimetres.  The tag's centre alone (``aruco_size`` 0) cannot
give the mount's rotation; its four corners do.
"""

import os

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from armcal_ros.core.camera import Camera
from armcal_ros.core.target import invert, pose_vector
from armcal_ros.frontend.detectors import ArucoDetector, tag_corner_points
from armcal_ros.io.calib_files import write_camera_info
from helpers.captures import import_and_calibrate

W, H = 800, 600
K = np.array([[700.0, 0, 399.5], [0, 705.0, 299.5], [0, 0, 1]])
SIZE = 0.06
TAG_ID = 3
MOUNT = np.eye(4)
MOUNT[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 1.1]).as_matrix()
MOUNT[:3, 3] = [0.02, -0.04, 0.11]
T_CAM_BASE = np.eye(4)
T_CAM_BASE[:3, :3] = Rotation.from_rotvec([2.0, 0.3, -0.2]).as_matrix()
T_CAM_BASE[:3, 3] = [0.1, -0.2, 1.4]


def render_tag(T_ct, seed):
    """Render the tag (white border of one module) at camera-from-tag pose ``T_ct``."""
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    px = 60                                  # pixels per module; 6 modules across the tag
    tag = cv2.aruco.generateImageMarker(d, TAG_ID, 6 * px)
    tex = np.full((8 * px, 8 * px), 255, np.uint8)
    tex[px:7 * px, px:7 * px] = tag
    s = SIZE / (6 * px)
    c = 4 * px - 0.5                         # the texture's centre pixel
    S = np.array([[s, 0, -c * s], [0, -s, c * s], [0, 0, 1]])
    Hm = K @ np.column_stack([T_ct[:3, 0], T_ct[:3, 1], T_ct[:3, 3]]) @ S
    img = cv2.warpPerspective(tex, Hm, (W, H), flags=cv2.INTER_LINEAR, borderValue=128)
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.7)
    img += np.random.default_rng(seed).normal(0, 1.5, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def camera_from_tag(rng):
    """Return a pose showing the tag's face 0.5-0.7 m in front of the camera, tilted < 0.5 rad."""
    R = np.diag([1.0, -1.0, -1.0]) @ Rotation.from_rotvec(rng.uniform(-0.5, 0.5, 3)).as_matrix()
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = [rng.uniform(-0.08, 0.08), rng.uniform(-0.06, 0.06), rng.uniform(0.5, 0.7)]
    return T


def write_folder(root, n=10, seed=0):
    rng = np.random.default_rng(seed)
    os.makedirs(os.path.join(root, 'images'))
    os.makedirs(os.path.join(root, 'camera_info'))
    rows = ['sample,x,y,z,qx,qy,qz,qw']
    for k in range(n):
        T_ct = camera_from_tag(rng)
        cv2.imwrite(os.path.join(root, 'images', f'{k}_cam.png'), render_tag(T_ct, k))
        link = invert(T_CAM_BASE) @ T_ct @ invert(MOUNT)
        rows.append(f'{k},' + ','.join(f'{v:.10f}' for v in pose_vector(link)))
    with open(os.path.join(root, 'poses.csv'), 'w') as f:
        f.write('\n'.join(rows) + '\n')
    write_camera_info(os.path.join(root, 'camera_info', 'cam.yaml'),
                      Camera('cam', W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2]))


def test_tag_corners_come_back_where_they_were_drawn():
    rng = np.random.default_rng(1)
    T_ct = camera_from_tag(rng)
    dets = ArucoDetector('DICT_4X4_50', marker_id=TAG_ID, corners=True).detect(
        render_tag(T_ct, 0))
    assert [d.id for d in dets] == [0, 1, 2, 3]
    X = tag_corner_points(SIZE) @ T_ct[:3, :3].T + T_ct[:3, 3]
    uv = (X @ K.T)[:, :2] / X[:, 2:]
    # Sub-pixel corners of a warped, blurred, noisy render: a few tenths of a pixel.
    assert np.max(np.linalg.norm(np.array([d.uv for d in dets]) - uv, axis=1)) < 0.5


def test_a_tag_of_given_size_is_a_rigid_target_with_its_mount_estimated(tmp_path):
    folder = tmp_path / 'captures'
    write_folder(str(folder))
    report = import_and_calibrate(folder, tmp_path, marker_type='aruco', aruco_id=TAG_ID,
                                  aruco_size=SIZE, estimate_marker_offset='true',
                                  noise_model='fixed', free_distortion=[], min_samples=5)
    assert report['n_samples'] == 10
    cam = report['cameras']['cam']
    assert cam['n_observations'] == 40 and cam['rms_px'] < 0.3
    assert np.linalg.norm(np.array(cam['translation']) - invert(T_CAM_BASE)[:3, 3]) < 3e-3
    T = report['target']['T_link_target']
    assert np.linalg.norm(np.array(T[:3]) - MOUNT[:3, 3]) < 2e-3
    dR = Rotation.from_quat(T[3:]).as_matrix().T @ MOUNT[:3, :3]
    assert np.degrees(Rotation.from_matrix(dR).magnitude()) < 0.5


def test_a_tag_of_unknown_side_from_a_guess_30_percent_off(tmp_path):
    # aruco_size is only a guess; the arm's poses set the scale, so the side is estimated
    # with the tag's pose on the link.
    folder = tmp_path / 'captures'
    write_folder(str(folder), n=12, seed=3)
    report = import_and_calibrate(folder, tmp_path, marker_type='aruco', aruco_id=TAG_ID,
                                  aruco_size=0.7 * SIZE, estimate_aruco_size='true',
                                  estimate_marker_offset='true', noise_model='fixed',
                                  free_distortion=[], min_samples=5)
    tgt = report['target']
    assert abs(tgt['aruco_size'] - SIZE) < 1e-3, tgt
    assert np.linalg.norm(np.array(tgt['T_link_target'][:3]) - MOUNT[:3, 3]) < 3e-3
    cam = report['cameras']['cam']
    assert np.linalg.norm(np.array(cam['translation']) - invert(T_CAM_BASE)[:3, 3]) < 3e-3
