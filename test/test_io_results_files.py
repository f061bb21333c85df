"""calibration.json and target.yaml: written beside the camera YAMLs, read back exactly."""

import json
import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.core.camera import Camera
from armcal_ros.core.results import Calibration, CameraCalibration
from armcal_ros.core.target import pose_matrix
from armcal_ros.io.results_files import (load_calibration, read_target_yaml, target_yaml,
                                         write_calibration, write_target)


def _calibration():
    cams = {}
    for k, name in enumerate(('left', 'right')):
        cam = Camera(name, 640, 480, 800.0 + k, 801.0, 320.5, 239.5,
                     dist=np.array([-0.1, 0.02, 1e-4, -2e-4, 0.0]))
        cam.rotation = Rotation.from_rotvec([0.1, -0.2 * k, 0.3]).as_matrix()
        cam.translation = np.array([0.1, 0.2 + k, 1.5])
        cov = np.diag(np.arange(1.0, 7.0)) * 1e-6
        cams[name] = CameraCalibration(cam, {'fx': 0.5, 'cx': 0.25}, cov, 0.31, 120, 118)
    return Calibration(cams, 'hybrid', 12.5, 60, 1.25, 1.7e9, 'converged', 'ok',
                       {'model': 'kinematic', 'pixel_sigma': 0.2},
                       {'top': 'only 6 of its 18 observations fit (fewer than 50%)'})


def test_calibration_round_trip(tmp_path):
    cal = _calibration()
    files = write_calibration(str(tmp_path), cal, 'world')
    assert sorted(os.path.basename(f) for f in files) == [
        'calibration.json', 'extrinsics.yaml', 'left.yaml', 'right.yaml']
    back = load_calibration(str(tmp_path))
    a, b = back.summary(), json.loads(json.dumps(cal.summary()))
    for name in cal.cameras:
        for key in ('translation', 'rotation'):    # via the pose in the world: last bits
            np.testing.assert_allclose(a['cameras'][name].pop(key),
                                       b['cameras'][name].pop(key), rtol=0, atol=1e-12)
    assert a == b
    assert back.not_calibrated == cal.not_calibrated
    for name, c in cal.cameras.items():
        b = back.cameras[name]
        np.testing.assert_allclose(b.camera.rotation, c.camera.rotation, atol=1e-9)
        np.testing.assert_allclose(b.pose_covariance, c.pose_covariance)
        assert (b.n_observations, b.n_inliers) == (120, 118)


def test_an_unreadable_calibration_names_the_file(tmp_path):
    write_calibration(str(tmp_path), _calibration(), 'world')
    os.remove(tmp_path / 'right.yaml')
    with pytest.raises(ValueError, match='calibration.json: cannot restore'):
        load_calibration(str(tmp_path))


def test_target_yaml_round_trip_and_errors(tmp_path):
    T = pose_matrix([0.03, 0.08, 0.15], Rotation.from_rotvec([0.2, -1.9, 0.3]).as_quat())
    path = write_target(str(tmp_path), T, np.array([1e-4] * 3 + [2e-3] * 3), 'tool0', True)
    text = open(path).read()
    assert text == target_yaml(T, np.array([1e-4] * 3 + [2e-3] * 3), 'tool0', True)
    assert 'estimated: true' in text and 'std_rotation_rad' in text
    np.testing.assert_allclose(read_target_yaml(path), T, atol=1e-7)
    assert 'std_' not in target_yaml(T, None, 'tool0', False)
    (tmp_path / 'bad.yaml').write_text('translation: [0, 0]\n')
    with pytest.raises(ValueError, match='bad.yaml: cannot read the target pose'):
        read_target_yaml(str(tmp_path / 'bad.yaml'))


def test_driver_file_keeps_a_foreign_calibration_once_and_replaces_its_own(tmp_path):
    from armcal_ros.io.calib_files import read_camera_info
    from armcal_ros.io.results_files import DRIVER_FILE_MARK, write_driver_camera_info
    cam = Camera.look_at('cam1', 640, 480, 801.5, 799.25, 322.1, 236.7,
                         [-0.151, 0.049, 3e-4, -2e-4, 0.001], eye=[1.2, -0.9, 0.8],
                         target=[0.4, 0.1, 0.2])
    foreign = tmp_path / 'front_rgb.yaml'
    foreign.write_text('# from a checkerboard run\nimage_width: 640\n')
    path, kept = write_driver_camera_info(tmp_path, cam, 'front_rgb')
    assert kept == str(tmp_path / 'front_rgb.before_armcal.yaml')
    assert (tmp_path / 'front_rgb.before_armcal.yaml').read_text().startswith('# from a')
    assert (tmp_path / 'front_rgb.yaml').read_text().splitlines()[0] == DRIVER_FILE_MARK
    back = read_camera_info(path)
    assert back.name == 'front_rgb'
    np.testing.assert_allclose(back.K, cam.K)
    # Its own file is replaced without another copy; a kept file is never overwritten.
    cam.fx = 805.0
    path, kept = write_driver_camera_info(tmp_path, cam, 'front_rgb')
    assert kept is None and read_camera_info(path).fx == 805.0
    assert (tmp_path / 'front_rgb.before_armcal.yaml').read_text().startswith('# from a')
    assert sorted(p.name for p in tmp_path.iterdir()) == ['front_rgb.before_armcal.yaml',
                                                          'front_rgb.yaml']
