"""
Round trips of the camera_info YAML and extrinsics.yaml files, and reading ROS's own files.

The files camera_calibration and camera_calibration_parsers write (test/data/camera_info_files/,
its README says how they were made) are all read, whatever the camera's name and distortion
model; those armcal can use convert to a Camera that projects as OpenCV does with the file's K
and D, the others are refused on conversion with the reason.
"""

import os
import types

import cv2
import numpy as np
import pytest
import yaml

from armcal_ros.core.camera import Camera
from armcal_ros.io.calib_files import (
    camera_from_info_file, plumb_bob_coefficients, read_camera_info, read_camera_info_file,
    read_camera_info_sections, read_cameras, read_extrinsics, validate_camera_name,
    write_camera_info, write_cameras, write_extrinsics,
)
from armcal_ros.io.message_fields import camera_from_camera_info
from armcal_ros.params import defaults
from armcal_ros.settings import settings_from_values
from helpers.params_files import PUMA_URDF

DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'data', 'camera_info_files')


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


# --- ROS's own calibration files ----------------------------------------------------------

#: file -> (camera_name, distortion_model, len(D), armcal can use it)
FIXTURES = {
    'camera_calibration/mono/ost.yaml': ('narrow_stereo', 'plumb_bob', 5, True),
    'camera_calibration/mono/ost.txt': ('narrow_stereo', 'plumb_bob', 5, True),
    'camera_calibration/stereo/left.yaml': ('narrow_stereo/left', 'plumb_bob', 5, True),
    'camera_calibration/stereo/right.yaml': ('narrow_stereo/right', 'plumb_bob', 5, True),
    'camera_calibration/rational/ost.yaml': ('camera', 'rational_polynomial', 8, False),
    'camera_calibration/rational/ost.txt': ('camera', 'rational_polynomial', 8, False),
    'camera_calibration/fisheye/ost.yaml': ('narrow_stereo', 'equidistant', 4, False),
    'camera_calibration/fisheye/ost.txt': ('narrow_stereo', 'equidistant', 4, False),
    'camera_calibration_parsers/head_camera.yaml': ('head_camera', 'plumb_bob', 5, True),
    'camera_calibration_parsers/head_camera.ini': ('head_camera', 'plumb_bob', 5, True),
    'camera_calibration_parsers/camera_rational_8.yaml':
        ('camera', 'rational_polynomial', 8, True),
    'camera_calibration_parsers/rgb_camera_rational_14.yaml':
        ('rgb_camera', 'rational_polynomial', 14, True),
}


def _fixture(rel):
    return os.path.join(DATA, rel)


def test_every_fixture_is_listed():
    found = {os.path.relpath(os.path.join(root, f), DATA)
             for root, _, files in os.walk(DATA) for f in files if f != 'README.md'}
    assert found == set(FIXTURES) | {'camera_calibration/stereo/ost.txt'}


def _image_points(cam, info):
    """Points in front of an identity-pose camera that land all over its image."""
    u, v = np.meshgrid(np.linspace(0, info.width, 7), np.linspace(0, info.height, 5))
    z = np.linspace(0.4, 3.0, u.size)
    x = (u.ravel() - info.K[0, 2]) / info.K[0, 0] * z
    y = (v.ravel() - info.K[1, 2]) / info.K[1, 1] * z
    return np.column_stack([x, y, z])


@pytest.mark.parametrize('rel', sorted(FIXTURES))
def test_ros_calibration_files_are_read_whatever_the_name_and_model(rel):
    name, model, n, usable = FIXTURES[rel]
    info = read_camera_info_file(_fixture(rel))
    assert info.camera_name == name        # verbatim, '/' included
    assert info.distortion_model == model
    assert info.D.shape == (n,)
    assert info.K.shape == (3, 3) and info.R.shape == (3, 3) and info.P.shape == (3, 4)
    assert info.width > 0 and info.height > 0
    assert np.array_equal(info.K[2], [0, 0, 1]) and info.K[0, 0] > 100
    np.testing.assert_allclose(info.R @ info.R.T, np.eye(3), atol=1e-5)
    assert info.source == _fixture(rel)
    if not usable:
        with pytest.raises(ValueError) as err:
            camera_from_info_file(info)
        text = str(err.value)
        assert rel in text and repr(model) in text
        assert 'cannot be estimated or used by armcal' in text
        assert 'calibrate the lens with a plumb_bob model, or give no intrinsics file and let ' \
               'armcal estimate them' in text
        with pytest.raises(ValueError, match='cannot be estimated or used'):
            read_camera_info(_fixture(rel))
        return
    cam = camera_from_info_file(info)
    assert cam.name == name.replace('/', '_')
    assert (cam.width, cam.height) == (info.width, info.height)
    np.testing.assert_array_equal(cam.K, info.K)
    # The Camera projects as OpenCV does with the file's own K and D, all of D.
    X = _image_points(cam, info)
    uv, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), info.K, info.D)
    np.testing.assert_allclose(cam.project(X), uv.reshape(-1, 2), rtol=0, atol=1e-9)
    assert read_camera_info(_fixture(rel), 'cam1').name == 'cam1'


def test_the_non_usable_models_are_named_with_their_coefficients():
    info = read_camera_info_file(_fixture('camera_calibration/rational/ost.yaml'))
    with pytest.raises(ValueError, match=r"'rational_polynomial' .*k4=2\.74125, k5=1\.52031, "
                                         r"k6=0\.11867 are not zero\. armcal fits plumb_bob"):
        camera_from_info_file(info)
    info = read_camera_info_file(_fixture('camera_calibration/fisheye/ost.txt'))
    with pytest.raises(ValueError, match=r"'equidistant' .*k1=-0\.00812, k2=0\.04371, "
                                         r"k3=-0\.04126, k4=0\.00769 are not zero"):
        camera_from_info_file(info)


def test_stereo_files_keep_rectification_and_baseline():
    left = read_camera_info_file(_fixture('camera_calibration/stereo/left.yaml'))
    right = read_camera_info_file(_fixture('camera_calibration/stereo/right.yaml'))
    for info in (left, right):
        assert not np.allclose(info.R, np.eye(3), atol=1e-3)
    assert left.P[0, 3] == 0.0
    assert right.P[0, 3] == -34.88828
    assert -right.P[0, 3] / right.P[0, 0] == pytest.approx(0.06, abs=1e-6)   # the baseline
    # The stereo ost.txt holds both cameras, the same numbers as the YAMLs (%8f: R to 1e-6).
    both = read_camera_info_sections(_fixture('camera_calibration/stereo/ost.txt'))
    assert [c.camera_name for c in both] == ['narrow_stereo/left', 'narrow_stereo/right']
    for ini, yml in zip(both, (left, right)):
        for key in ('K', 'D', 'R', 'P'):
            np.testing.assert_array_equal(getattr(ini, key), getattr(yml, key))
        assert (ini.width, ini.height, ini.distortion_model) == \
            (yml.width, yml.height, yml.distortion_model)
    picked = read_camera_info_file(_fixture('camera_calibration/stereo/ost.txt'),
                                   'narrow_stereo/right')
    np.testing.assert_array_equal(picked.P, right.P)
    with pytest.raises(ValueError, match=r"holds 2 cameras \('narrow_stereo/left', "
                                         r"'narrow_stereo/right'\).*left\.yaml"):
        read_camera_info(_fixture('camera_calibration/stereo/ost.txt'))


@pytest.mark.parametrize('yml, ini', [
    ('camera_calibration_parsers/head_camera.yaml', 'camera_calibration_parsers/head_camera.ini'),
    ('camera_calibration/mono/ost.yaml', 'camera_calibration/mono/ost.txt'),
    ('camera_calibration/rational/ost.yaml', 'camera_calibration/rational/ost.txt'),
    ('camera_calibration/fisheye/ost.yaml', 'camera_calibration/fisheye/ost.txt'),
])
def test_the_ini_and_yaml_of_one_calibration_read_the_same(yml, ini):
    a, b = read_camera_info_file(_fixture(yml)), read_camera_info_file(_fixture(ini))
    assert (a.camera_name, a.width, a.height, a.distortion_model) == \
        (b.camera_name, b.width, b.height, b.distortion_model)
    for key in ('K', 'D', 'R', 'P'):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key))


def test_ini_is_told_by_content_when_the_extension_does_not_say(tmp_path):
    text = open(_fixture('camera_calibration_parsers/head_camera.ini')).read()
    (tmp_path / 'head_camera.calib').write_text(text)
    info = read_camera_info_file(tmp_path / 'head_camera.calib')
    assert info.camera_name == 'head_camera' and info.K[0, 0] == 847.25375
    yml = open(_fixture('camera_calibration_parsers/head_camera.yaml')).read()
    (tmp_path / 'head_camera.calib').write_text('# saved by camera_info_manager\n' + yml)
    assert read_camera_info_file(tmp_path / 'head_camera.calib').D[0] == -0.33125


def _info_yaml(tmp_path, model, d, name='narrow_stereo/left', extra=''):
    path = tmp_path / 'cam.yaml'
    path.write_text(
        f'image_width: 640\nimage_height: 480\ncamera_name: {name}\n'
        'camera_matrix: {rows: 3, cols: 3, data: [612.5, 0, 318.25, 0, 611.75, 242.5, 0, 0, 1]}\n'
        f'distortion_model: {model}\n'
        f'distortion_coefficients: {{rows: 1, cols: {len(d)}, data: {list(d)}}}\n' + extra)
    return path


@pytest.mark.parametrize('model, d, expected', [
    ('plumb_bob', [0.1, -0.2, 0.001, -0.002], [0.1, -0.2, 0.001, -0.002, 0]),
    ('plumb_bob', [0.1, -0.2, 0.001, -0.002, 0.05, 0, 0, 0], [0.1, -0.2, 0.001, -0.002, 0.05]),
    ('plumb_bob', [], [0, 0, 0, 0, 0]),
    ('rational_polynomial', [0.1, -0.2, 0.001, -0.002, 0.05, 0, 0, 0],
     [0.1, -0.2, 0.001, -0.002, 0.05]),
    ('rational_polynomial', [0.1, -0.2, 0.001, -0.002, 0.05] + [0] * 9,
     [0.1, -0.2, 0.001, -0.002, 0.05]),
    ('equidistant', [0, 0, 0, 0], [0, 0, 0, 0, 0]),
    ('fisheye', [0, 0, 0, 0], [0, 0, 0, 0, 0]),
])
def test_what_the_estimator_can_use_converts(tmp_path, model, d, expected):
    cam = read_camera_info(_info_yaml(tmp_path, model, d))
    assert cam.name == 'narrow_stereo_left'
    np.testing.assert_array_equal(cam.dist, expected)


@pytest.mark.parametrize('model, d, named', [
    ('plumb_bob', [0.1, -0.2, 0.001, -0.002, 0.05, 0.3, 0, 0], 'k4=0.3 is'),
    ('rational_polynomial', [0.1, -0.2, 0.001, -0.002, 0.05, 0, 0.7, 0] + [0] * 6,
     'k5=0.7 is'),
    ('rational_polynomial', [0.1, -0.2, 0.001, -0.002, 0.05] + [0] * 8 + [0.001],
     'tauY=0.001 is'),
    ('equidistant', [0.01, 0, 0, 0], 'k1=0.01 is'),
    ('kannala_brandt', [0, 0.2], 'D\\[1\\]=0.2 is'),
])
def test_what_the_estimator_cannot_use_is_read_and_then_refused(tmp_path, model, d, named):
    path = _info_yaml(tmp_path, model, d)
    info = read_camera_info_file(path)               # reading never refuses a model
    assert info.distortion_model == model and list(info.D) == d
    with pytest.raises(ValueError, match=f"{model!r} cannot be estimated or used by armcal: "
                                         f".*{named} not zero. armcal fits plumb_bob"):
        camera_from_info_file(info)


@pytest.mark.parametrize('change, key', [
    ('image_width: 640\n', 'image_width'),
    ('camera_matrix: {rows: 3, cols: 3, data: [612.5, 0, 318.25, 0, 611.75, 242.5, 0, 0, 1]}\n',
     'camera_matrix'),
])
def test_missing_keys_are_named(tmp_path, change, key):
    path = _info_yaml(tmp_path, 'plumb_bob', [0.0] * 5)
    path.write_text(path.read_text().replace(change, ''))
    with pytest.raises(ValueError, match=f'{path}: missing key {key}'):
        read_camera_info_file(path)


@pytest.mark.parametrize('extra, key', [
    ('projection_matrix: {rows: 3, cols: 4, data: [1, 0, 0, 0, 1, 0, 0, 0, 1]}\n',
     'projection_matrix must be 3x4'),
    ('rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, .nan, 0, 0, 0, 1]}\n',
     r'rectification_matrix: data\[4\]: nan is not a finite number'),
    ('rectification_matrix: {rows: 3, cols: 3, data: [1, 0, 0, 0, one, 0, 0, 0, 1]}\n',
     r"rectification_matrix: data\[4\]: 'one' is not a number"),
])
def test_malformed_matrices_are_named(tmp_path, extra, key):
    path = _info_yaml(tmp_path, 'plumb_bob', [0.0] * 5, extra=extra)
    with pytest.raises(ValueError, match=f'{path}: {key}'):
        read_camera_info_file(path)


def test_malformed_ini_is_named(tmp_path):
    text = open(_fixture('camera_calibration_parsers/head_camera.ini')).read()
    bad = tmp_path / 'bad.ini'
    bad.write_text(text.replace('0.00000 846.80625 361.91750 \n', '0.00000 846.80625\n'))
    with pytest.raises(ValueError, match=r'bad\.ini: \[head_camera\]: camera matrix, line 15: '
                                         'expected 3 numbers'):
        read_camera_info_file(bad)
    bad.write_text(text.replace('projection\n', 'projektion\n'))
    with pytest.raises(ValueError, match=r"bad\.ini: \[head_camera\]: missing key 'projection'"):
        read_camera_info_file(bad)
    bad.write_text(text.replace('[image]', '[imago]'))
    with pytest.raises(ValueError, match=r'bad\.ini: missing section \[image\]'):
        read_camera_info_file(bad)


def test_a_name_yaml_would_read_as_something_else_is_kept_verbatim(tmp_path):
    for name in ('yes', '0123', 'null', 'cam/left:1'):
        path = _info_yaml(tmp_path, 'plumb_bob', [0.0] * 5, name=f"'{name}'")
        assert read_camera_info_file(path).camera_name == name
    assert read_camera_info_file(_info_yaml(tmp_path, 'plumb_bob', [0.0] * 5, name='yes')) \
        .camera_name == 'yes'


def test_armcal_own_files_still_round_trip(tmp_path):
    cam = _camera('cam_7')
    write_camera_info(tmp_path / 'cam_7.yaml', cam)
    info = read_camera_info_file(tmp_path / 'cam_7.yaml')
    assert (info.camera_name, info.distortion_model) == ('cam_7', 'plumb_bob')
    np.testing.assert_array_equal(info.R, np.eye(3))
    np.testing.assert_array_equal(info.P, np.hstack([cam.K, np.zeros((3, 1))]))
    back = read_camera_info(tmp_path / 'cam_7.yaml')
    assert back.name == 'cam_7'
    np.testing.assert_array_equal(back.K, cam.K)
    np.testing.assert_array_equal(back.dist, cam.dist)
    # What armcal writes stays within its own names.
    with pytest.raises(ValueError, match='camera name'):
        write_camera_info(tmp_path / 'x.yaml', cam, camera_name='narrow_stereo/left')


# --- the settings' intrinsics_files and a driver's CameraInfo -------------------------------

def _settings(files, modes=('fixed', 'estimate')):
    return settings_from_values({**defaults(), 'robot_description_file': PUMA_URDF,
                                 'camera_names': ['l', 'r'], 'image_topics': ['/l', '/r'],
                                 'intrinsics_mode': list(modes), 'intrinsics_files': files})


def test_intrinsics_files_take_camera_calibration_files():
    s = _settings([_fixture('camera_calibration/stereo/left.yaml'), ''])
    given = s.solver.intrinsics['l']
    assert tuple(given.intrinsics) == (598.72375, 598.105, 321.40625, 239.8725)
    assert (given.width, given.height) == (640, 480)
    s = _settings([_fixture('camera_calibration_parsers/head_camera.ini'),
                   _fixture('camera_calibration_parsers/camera_rational_8.yaml')],
                  modes=('fixed', 'fixed'))
    assert s.solver.intrinsics['l'].intrinsics[0] == 847.25375
    assert s.solver.intrinsics['r'].intrinsics[0] == 615.91875


def test_intrinsics_files_refuse_a_model_armcal_cannot_use():
    path = _fixture('camera_calibration/rational/ost.yaml')
    with pytest.raises(ValueError) as err:
        _settings([path, ''])
    text = str(err.value)
    assert text.startswith('parameter intrinsics_files: camera l: ')
    assert "'rational_polynomial'" in text and path in text
    assert 'k4=2.74125' in text and 'let armcal estimate them' in text


def _message(model, d):
    return types.SimpleNamespace(
        width=640, height=480, distortion_model=model, d=list(d),
        k=[612.5, 0.0, 318.25, 0.0, 611.75, 242.5, 0.0, 0.0, 1.0])


def test_a_drivers_camera_info_follows_the_same_rule():
    cam = camera_from_camera_info(
        _message('rational_polynomial', [0.1, -0.2, 0.001, -0.002, 0.05, 0, 0, 0]), 'cam1')
    assert cam.name == 'cam1'
    np.testing.assert_array_equal(cam.dist, [0.1, -0.2, 0.001, -0.002, 0.05])
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (612.5, 611.75, 318.25, 242.5)
    with pytest.raises(ValueError, match=r"camera_info of cam1: read, but its distortion model "
                                         r"'rational_polynomial' cannot be estimated or used by "
                                         r"armcal: k4=0\.3, k6=-0\.01 are not zero\. armcal fits "
                                         r"plumb_bob .*intrinsics_mode"):
        camera_from_camera_info(
            _message('rational_polynomial', [0.1, -0.2, 0.001, -0.002, 0.05, 0.3, 0, -0.01]),
            'cam1')


def test_plumb_bob_coefficients_is_the_one_rule():
    np.testing.assert_array_equal(plumb_bob_coefficients('plumb_bob', [1, 2, 3, 4]),
                                  [1, 2, 3, 4, 0])
    with pytest.raises(ValueError, match='finite'):
        plumb_bob_coefficients('plumb_bob', [0, np.nan, 0, 0, 0])
