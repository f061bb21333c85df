"""Round trips of the camera_info YAML and extrinsics.yaml files."""

import numpy as np
import pytest
import yaml

from armcal_ros.core.camera import Camera
from armcal_ros.io.calib_files import (
    read_camera_info, read_cameras, read_extrinsics, validate_camera_name, write_camera_info,
    write_cameras, write_extrinsics,
)


def _camera(name='cam1'):
    return Camera.look_at(name, 640, 480, 801.5, 799.25, 322.1, 236.7,
                          [-0.151, 0.049, 3e-4, -2e-4, 0.001], eye=[1.2, -0.9, 0.8],
                          target=[0.4, 0.1, 0.2])


def test_camera_info_round_trip_and_field_names(tmp_path):
    cam = _camera()
    path = tmp_path / 'cam1.yaml'
    write_camera_info(path, cam)
    doc = yaml.safe_load(path.read_text())
    # The keys camera_calibration_parsers / camera_info_manager read.
    assert set(doc) == {'image_width', 'image_height', 'camera_name', 'camera_matrix',
                        'distortion_model', 'distortion_coefficients',
                        'rectification_matrix', 'projection_matrix'}
    assert doc['distortion_model'] == 'plumb_bob'
    for key, (r, c) in {'camera_matrix': (3, 3), 'distortion_coefficients': (1, 5),
                        'rectification_matrix': (3, 3), 'projection_matrix': (3, 4)}.items():
        assert doc[key]['rows'] == r and doc[key]['cols'] == c
        assert len(doc[key]['data']) == r * c
    P = np.array(doc['projection_matrix']['data']).reshape(3, 4)
    np.testing.assert_allclose(P[:, :3], cam.K)
    np.testing.assert_allclose(P[:, 3], 0.0)
    np.testing.assert_allclose(np.array(doc['rectification_matrix']['data']).reshape(3, 3),
                               np.eye(3))
    back = read_camera_info(path)
    assert (back.name, back.width, back.height) == ('cam1', 640, 480)
    np.testing.assert_allclose(back.K, cam.K, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back.dist, cam.dist, rtol=0, atol=1e-15)
    assert not list(tmp_path.glob('.*')), 'temporary files must not be left behind'


def test_extrinsics_round_trip_gives_the_same_projection(tmp_path):
    cams = [_camera('cam1'), _camera('cam_2')]
    cams[1].apply_pose_increment([0.1, -0.2, 0.05], [0.01, 0.02, -0.03])
    write_cameras(tmp_path, cams, base_frame='world')
    base, poses = read_extrinsics(tmp_path / 'extrinsics.yaml')
    assert base == 'world'
    assert poses['cam_2'][2] == 'cam_2_optical_frame'
    base, back = read_cameras(tmp_path)
    X = np.random.default_rng(1).uniform(-0.3, 0.5, (20, 3))
    for a, b in zip(cams, back):
        assert a.name == b.name
        np.testing.assert_allclose(b.project(X), a.project(X), atol=1e-9)
        np.testing.assert_allclose(b.center, a.center, atol=1e-12)


def test_bad_names_and_files_are_refused(tmp_path):
    with pytest.raises(ValueError, match='camera name'):
        validate_camera_name('cam/1')
    with pytest.raises(ValueError, match='camera name'):
        write_extrinsics(tmp_path / 'e.yaml', [_camera('bad name')])
    bad = tmp_path / 'bad.yaml'
    bad.write_text('image_width: 640\nimage_height: 480\n'
                   'camera_matrix: {rows: 3, cols: 3, data: [1, 0, 0]}\n'
                   'distortion_coefficients: {rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}\n')
    with pytest.raises(ValueError, match='camera_matrix'):
        read_camera_info(bad)
