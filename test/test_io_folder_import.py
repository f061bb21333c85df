"""
Folders of captures into bags (``armcal import-folder``), then through ``armcal calibrate``.

The board scene of helpers/board_scene.py written as a capture folder (poses.csv, one PNG per
capture, the camera's factory intrinsics as camera_info/cam.yaml) must come back from the bag as
the same calibration problem: with the intrinsics fixed, the camera's intrinsics exactly and its
pose and the board's mount close to the truth.  The facebookresearch/fairo layout
(ee_poses.csv, intrinsics.json by RealSense serial) is read from the real data when present.
"""

import json
import os

import cv2
import numpy as np
import pytest

from armcal_ros.cli import main
from armcal_ros.core.target import invert
from armcal_ros.io.bag import bag_topics
from armcal_ros.io.folder_import import (FolderFormatError, read_capture_folder,
                                         write_capture_bag)
from helpers.board_scene import BOARD_SIZE, check_mount, K, T_CAM_BASE, write_capture_folder
from helpers.captures import (FRANKA, import_and_calibrate, write_group_params,
                              write_mixed_cell_folder)

REAL = os.path.join(FRANKA, 'caldata_world_cam')


def test_capture_folder_to_bag_to_calibration(tmp_path, capsys):
    folder = tmp_path / 'captures'
    write_capture_folder(str(folder))
    bag = tmp_path / 'bag'
    assert main(['import-folder', str(folder), '--output', str(bag)]) == 0
    topics = bag_topics(str(bag))
    assert topics['/tool_pose'] == ('geometry_msgs/msg/PoseStamped', 16)
    assert topics['/cam/image_raw/compressed'] == ('sensor_msgs/msg/CompressedImage', 8)
    assert topics['/cam/camera_info'] == ('sensor_msgs/msg/CameraInfo', 8)
    assert 'intrinsics_mode:\n    - fixed' in (bag / 'params.yaml').read_text()
    # The written parameter file, completed with the marker, calibrates the camera.
    (tmp_path / 'again').mkdir()
    report = import_and_calibrate(folder, tmp_path / 'again', marker_type='charuco',
                                  estimate_marker_offset='true', noise_model='fixed',
                                  free_distortion=[], min_samples=3, **BOARD_SIZE)
    cam = report['cameras']['cam']
    assert report['n_samples'] == 8
    np.testing.assert_allclose([cam['fx'], cam['fy'], cam['cx'], cam['cy']],
                               [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], atol=1e-3)
    assert np.linalg.norm(np.array(cam['translation']) - invert(T_CAM_BASE)[:3, 3]) < 3e-3
    check_mount(report['target']['T_link_target'])


def test_joint_angle_tables_and_bad_folders(tmp_path):
    root = tmp_path / 'joints'
    (root / 'images').mkdir(parents=True)
    (root / 'poses.csv').write_text('sample,j1,j2\n0,0.1,0.2\n1,0.3,0.4\n')
    cv2.imwrite(str(root / 'images' / '0_left.png'), np.zeros((4, 4), np.uint8))
    cv2.imwrite(str(root / 'images' / '1_left.png'), np.zeros((4, 4), np.uint8))
    f = read_capture_folder(str(root))
    assert f.joint_names == ['j1', 'j2'] and f.poses is None and f.cameras == ['left']
    write_capture_bag(f, str(tmp_path / 'jbag'))
    assert bag_topics(str(tmp_path / 'jbag'))['/joint_states'][1] == 4
    (root / 'poses.csv').write_text('sample,j1\n0,abc\n')
    with pytest.raises(FolderFormatError, match='poses.csv: every cell'):
        read_capture_folder(str(root))
    with pytest.raises(FolderFormatError, match='no poses.csv or ee_poses.csv'):
        read_capture_folder(str(tmp_path))


def test_the_fairo_layout_is_read():
    f = read_capture_folder(REAL)
    assert len(f.samples) == 20 and f.cameras == ['cam0', 'cam1', 'cam2']
    assert f.poses.shape == (20, 4, 4)
    assert sorted(f.intrinsics) == ['cam0', 'cam1', 'cam2']
    assert abs(f.intrinsics['cam0'].fx - 617.898) < 1e-3
    assert (f.intrinsics['cam1'].width, f.intrinsics['cam1'].height) == (640, 480)
    assert all(len(f.images[c]) == 20 for c in f.cameras)


def test_the_franka_set_calibrates_end_to_end(tmp_path):
    # docs/BENCHMARKS.md, "Real data: Franka Panda": with the factory intrinsics fixed and one
    # marker point estimated from a guess, every camera within 1 degree and 4 cm of the original
    # tool's poses (its per-camera marker points disagree with one another by centimetres).
    from scipy.spatial.transform import Rotation
    report = import_and_calibrate(REAL, tmp_path, marker_type='aruco',
                                  aruco_dictionary='DICT_4X4_50', aruco_id=0,
                                  marker_offset=[0.05, 0.05, -0.05],
                                  estimate_marker_offset='true', noise_model='fixed',
                                  free_distortion=[], min_samples=8)
    with open(os.path.join(os.path.dirname(REAL), 'reference', 'calibration.json')) as f:
        ref = json.load(f)
    for j, name in enumerate(('cam0', 'cam1', 'cam2')):
        cam = report['cameras'][name]
        assert cam['rms_px'] < 1.5 and cam['n_inliers'] >= 12, cam
        assert np.linalg.norm(np.array(cam['translation']) - ref[j]['camera_base_pos']) < 0.04
        dR = np.array(ref[j]['camera_base_ori']).T @ Rotation.from_quat(
            cam['rotation']).as_matrix()
        assert np.degrees(Rotation.from_matrix(dR).magnitude()) < 1.0


def test_given_intrinsics_from_the_bags_camera_info(tmp_path):
    # intrinsics_mode fixed without a file: the first CameraInfo beside the images is used.
    import yaml
    from armcal_ros.offline import calibrate_bag, CalibrateError
    from armcal_ros.settings import load_settings
    folder = tmp_path / 'captures'
    write_capture_folder(str(folder))
    bag = tmp_path / 'bag'
    assert main(['import-folder', str(folder), '--output', str(bag)]) == 0
    p = tmp_path / 'p.yaml'
    p.write_text(yaml.safe_dump({'armcal': {'ros__parameters': dict(
        camera_names=['cam'], image_topics=['/cam/image_raw/compressed'],
        pose_topic='/tool_pose', marker_type='charuco', estimate_marker_offset=True,
        noise_model='fixed', free_distortion=[], min_samples=3, intrinsics_mode=['fixed'],
        **BOARD_SIZE)}}))
    cam = calibrate_bag(str(bag), load_settings(str(p)), tmp_path / 'out').report['cameras']
    np.testing.assert_allclose([cam['cam'][k] for k in ('fx', 'fy', 'cx', 'cy')],
                               [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], atol=1e-3)
    # A folder without intrinsics gives a bag without CameraInfo: refused, naming the topic.
    import shutil
    shutil.rmtree(folder / 'camera_info')
    assert main(['import-folder', str(folder), '--output', str(tmp_path / 'bare')]) == 0
    with pytest.raises(CalibrateError, match='needs its CameraInfo on /cam/camera_info'):
        calibrate_bag(str(tmp_path / 'bare'), load_settings(str(p)), tmp_path / 'out2')


def test_the_franka_wrist_camera_calibrates_eye_in_hand(tmp_path):
    # The camera on the flange, a static tag: the original tool accepts < 2 px.
    wrist = os.path.join(os.path.dirname(REAL), 'caldata_wrist_cam')
    report = import_and_calibrate(wrist, tmp_path, marker_type='aruco', aruco_id=1,
                                  marker_offset=[0.5, 0.0, 0.0], estimate_marker_offset='true',
                                  eye_in_hand='true', noise_model='fixed', free_distortion=[],
                                  min_samples=8)
    cam = report['cameras']['cam0']
    assert cam['rms_px'] < 2.0 and cam['n_inliers'] >= 18, cam
    # The tag lies on the table: its centre's height in the base is about zero.
    assert abs(report['target']['T_link_target'][2]) < 0.02


def test_a_cell_with_static_cameras_and_a_wrist_camera_in_one_recording(tmp_path):
    # The real world-camera captures, then the wrist camera's, in one folder and one bag (as a
    # cell with both kinds records them), calibrated by two calibrators over that bag - as two
    # nodes run live (README, "Cameras on the arm"; test_ros_node_groups.py): the static
    # cameras with the tag on the gripper, the wrist camera (eye_in_hand) with the tag on the
    # table.  The static cameras come out in the base, the wrist camera on the flange.
    import yaml

    from armcal_ros.offline import calibrate_bag
    from armcal_ros.settings import load_settings
    bag = tmp_path / 'bag'
    assert main(['import-folder', write_mixed_cell_folder(tmp_path / 'cell'),
                 '--output', str(bag)]) == 0
    files = write_group_params(bag)
    static = calibrate_bag(str(bag), load_settings(files['static']), tmp_path / 'static').report
    hand = calibrate_bag(str(bag), load_settings(files['hand']), tmp_path / 'hand').report
    with open(os.path.join(os.path.dirname(REAL), 'reference', 'calibration.json')) as f:
        ref = json.load(f)
    for j, name in enumerate(('cam0', 'cam1', 'cam2')):
        cam = static['cameras'][name]
        assert np.linalg.norm(np.array(cam['translation']) - ref[j]['camera_base_pos']) < 0.04
    # The wrist captures show tag 1 only and the world captures tag 0 only (to these cameras).
    assert static['n_samples'] <= 20 and hand['n_samples'] <= 20
    assert hand['cameras']['wrist']['rms_px'] < 2.0
    ext = yaml.safe_load((tmp_path / 'hand' / 'extrinsics.yaml').read_text())
    assert ext['base_frame'] == 'tool0' and set(ext['cameras']) == {'wrist'}
    ext = yaml.safe_load((tmp_path / 'static' / 'extrinsics.yaml').read_text())
    assert ext['base_frame'] == 'base_link' and set(ext['cameras']) == {'cam0', 'cam1', 'cam2'}
