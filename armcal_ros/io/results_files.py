"""
The files of an accepted calibration besides the camera YAMLs: calibration.json, target.yaml.

``calibration.json`` holds what the camera_calibration_parsers YAML cannot: standard
deviations, the pose covariance, fit figures and how the calibration was obtained; with the
``<camera>.yaml`` files it restores a :class:`~armcal_ros.core.results.Calibration` on resume.
``target.yaml`` holds a board's pose on its link (T_link_target) and, when estimated, its
standard deviations.
"""

import json
import os

import numpy as np
import yaml

from armcal_ros.core.results import Calibration, CameraCalibration
from armcal_ros.core.target import pose_matrix, pose_vector
from armcal_ros.io.calib_files import (atomic_write_text, camera_info_yaml, read_cameras,
                                       write_cameras)

CALIBRATION_FILE = 'calibration.json'
TARGET_FILE = 'target.yaml'


def write_calibration(directory, cal: Calibration, base_frame, frame_ids=None):
    """
    Write ``<camera>.yaml``, ``extrinsics.yaml`` and ``calibration.json`` (each atomically).

    ``frame_ids``: camera name -> optical frame for extrinsics.yaml (the images' frame_id).
    Returns the paths written.
    """
    cams = [c.camera for c in cal.cameras.values()]
    write_cameras(directory, cams, base_frame, frame_ids)
    written = [os.path.join(directory, f'{c.name}.yaml') for c in cams]
    written.append(os.path.join(directory, 'extrinsics.yaml'))
    path = os.path.join(directory, CALIBRATION_FILE)
    atomic_write_text(path, json.dumps(cal.summary(), indent=1))
    written.append(path)
    return written


def _nan_if_none(x):
    """Return a float, NaN for a missing or null entry (files of earlier versions)."""
    return float('nan') if x is None else float(x)


def load_calibration(directory) -> Calibration:
    """Read a calibration written by :func:`write_calibration`; ValueError names the file."""
    path = os.path.join(directory, CALIBRATION_FILE)
    try:
        with open(path) as f:
            doc = json.load(f)
        _, cams = read_cameras(directory, names=list(doc['cameras']))
    except (OSError, ValueError, KeyError) as exc:
        raise ValueError(f'{path}: cannot restore the calibration: {exc}') from exc
    out = {}
    for cam in cams:
        d = doc['cameras'][cam.name]
        out[cam.name] = CameraCalibration(
            cam, dict(d['std']), np.asarray(d['pose_covariance'], float).reshape(6, 6),
            float(d['rms_px']), int(d['n_observations']), int(d['n_inliers']),
            _nan_if_none(d.get('redundancy')), _nan_if_none(d.get('sigma_px')),
            _nan_if_none(d.get('workspace_error_mm')))
    return Calibration(out, doc['model'], doc['cost'], doc['n_samples'], doc['solve_time_s'],
                       doc['solved_at'], doc['status'], doc['message'],
                       doc.get('hyperparameters', {}), dict(doc.get('not_calibrated') or {}))


def target_yaml(T, std, link, estimated, scale=1.0):
    """
    Return the text of ``target.yaml``: T_link_target and, when estimated, its std.

    ``scale`` (written unless 1) multiplies the target's points (a tag's estimated size over
    its guess); ``std`` has its standard deviation as a seventh entry then.
    """
    x = pose_vector(T)
    lines = [f'# T_{link}_target: pose of the target frame in {link}',
             f'estimated: {str(bool(estimated)).lower()}',
             'translation: [' + ', '.join(f'{v:.6f}' for v in x[:3]) + ']',
             'rotation_xyzw: [' + ', '.join(f'{v:.8f}' for v in x[3:]) + ']']
    if scale != 1.0:
        lines.append(f'scale: {scale:.6f}')
    if std is not None:
        lines.append('std_translation_m: [' + ', '.join(f'{v:.6f}' for v in std[:3]) + ']')
        if len(std) > 3:     # a point marker's place has no orientation
            lines.append('std_rotation_rad: [' + ', '.join(f'{v:.6f}' for v in std[3:6])
                         + ']')
        if len(std) > 6:
            lines.append(f'std_scale: {std[6]:.6f}')
    return '\n'.join(lines) + '\n'


def write_target(directory, T, std, link, estimated, scale=1.0):
    """Write ``target.yaml`` (atomically); return its path."""
    path = os.path.join(directory, TARGET_FILE)
    atomic_write_text(path, target_yaml(T, std, link, estimated, scale))
    return path


def read_target_scale(path):
    """Return the target's scale from a ``target.yaml`` (1 when it has none)."""
    try:
        with open(path) as f:
            return float((yaml.safe_load(f) or {}).get('scale', 1.0))
    except (OSError, yaml.YAMLError, TypeError, ValueError, AttributeError) as exc:
        raise ValueError(f'{path}: cannot read the target scale: {exc}') from exc


def read_target_yaml(path):
    """Return T_link_target (4, 4) from a ``target.yaml``; ValueError naming the file."""
    try:
        with open(path) as f:
            doc = yaml.safe_load(f)
        return pose_matrix(doc['translation'], doc['rotation_xyzw'])
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f'{path}: cannot read the target pose: {exc}') from exc


#: The first line of every file :func:`write_driver_camera_info` writes: how a later write tells
#: its own file from one a person or another tool put there.
DRIVER_FILE_MARK = '# written by armcal_ros (the camera calibrator); camera_info_manager format'


def write_driver_camera_info(directory, cam, camera_name):
    """
    Write ``<directory>/<camera_name>.yaml`` for a driver's camera_info_manager to load.

    camera_info_manager's default URL is ``file://${ROS_HOME}/camera_info/${NAME}.yaml`` with
    NAME the driver's ``camera_name``, which the file's ``camera_name`` field repeats (the
    manager warns on a mismatch).  A file already there that this function did not write (a
    checkerboard calibration, a factory file) is kept once as ``<camera_name>.before_armcal.yaml``
    before it is replaced.  Returns (path written, path of the kept earlier file or None).
    """
    path = os.path.join(directory, f'{camera_name}.yaml')
    kept = None
    if os.path.exists(path):
        with open(path, encoding='utf-8', errors='replace') as f:
            ours = f.readline().rstrip('\n') == DRIVER_FILE_MARK
        backup = os.path.join(directory, f'{camera_name}.before_armcal.yaml')
        if not ours and not os.path.exists(backup):
            os.replace(path, backup)
            kept = backup
    atomic_write_text(path, DRIVER_FILE_MARK + '\n' + camera_info_yaml(cam, camera_name))
    return path, kept
