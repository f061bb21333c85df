"""
Board targets with pose input, offline: a robot_cal_tools folder through the whole calibration.

``armcal calibrate DIR`` with a folder holding ``cal_data.yaml`` comes here: the folder's images
and link poses are read (:mod:`armcal_ros.io.rct_import`), the ChArUco board of ``target.yaml``
(completed or checked by the ``charuco_*`` parameters) is detected in every image, and the camera
is calibrated with :func:`~armcal_ros.core.board_calibration.calibrate_board` - T_link_target
estimated when ``estimate_marker_offset`` is set, seeded from ``target_pose_guess`` or the
folder's ``pose_guesses.yaml`` (else found by hand-eye).  No robot model is needed: the poses
are measured.  It writes the same files as a bag calibration (``<camera>.yaml``,
``extrinsics.yaml``, ``calibration.json``) plus ``target.yaml`` (the mount) and
``report.json``.
"""

import json
import os
import time
from typing import Callable, Optional

import numpy as np

from armcal_ros.core.board_calibration import calibrate_board, CameraSpec, MountSettings
from armcal_ros.core.target import optional_pose
from armcal_ros.engine import calibration_from_result
from armcal_ros.frontend.charuco import CharucoBoard, CharucoDetector
from armcal_ros.io.calib_files import atomic_write_text, write_cameras
from armcal_ros.io.rct_import import (board_data, detect_views, load_rct_folder, pose_vector,
                                      RctFormatError)
from armcal_ros.params import charuco_settings, prior_settings, solver_settings


class BoardPipelineError(RuntimeError):
    """A failure the user can act on; the message is the one-line reason."""


def _target_yaml(T, std, link, estimated):
    v = pose_vector(T)
    lines = [f'# T_{link}_target: pose of the target frame in {link}',
             f'estimated: {str(bool(estimated)).lower()}',
             'translation: [' + ', '.join(f'{x:.6f}' for x in v[:3]) + ']',
             'rotation_xyzw: [' + ', '.join(f'{x:.8f}' for x in v[3:]) + ']']
    if std is not None:
        lines.append('std_translation_m: [' + ', '.join(f'{x:.6f}' for x in std[:3]) + ']')
        lines.append('std_rotation_rad: [' + ', '.join(f'{x:.6f}' for x in std[3:]) + ']')
    return '\n'.join(lines) + '\n'


def calibrate_rct_folder(path, values, output_dir, log: Optional[Callable[[str], None]] = None):
    """
    Calibrate the camera of a robot_cal_tools folder with checked parameter ``values``.

    Returns ``(report dict, files written, BoardCalibrationResult)``; raises
    BoardPipelineError with a one-line reason on failure.
    """
    t0 = time.perf_counter()
    try:
        data = load_rct_folder(path)
        t = data.target
        board = CharucoBoard(**charuco_settings(
            values, (t.rows, t.cols, t.square_size, t.marker_size, t.dictionary)))
    except (RctFormatError, ValueError) as exc:
        raise BoardPipelineError(str(exc)) from exc
    name = values['camera_names'][0]
    warnings = []
    if len(values['camera_names']) > 1:
        warnings.append(f'a robot_cal_tools folder has one camera: calibrating it as {name!r} '
                        f'(camera_names lists {len(values["camera_names"])})')
    for w in warnings:
        if log:
            log(w)
    uvs, ids, size = detect_views(data, CharucoDetector(board))
    n_used = sum(1 for i in ids if len(i))
    t_front = time.perf_counter() - t0
    if n_used < 3:
        raise BoardPipelineError(f'the board was found in {n_used} of {len(ids)} images; 3 or '
                                 'more are needed (check the charuco_* parameters and '
                                 'charuco_legacy_pattern)')
    bd = board_data(data.poses, board.points(), uvs, ids)
    seed = optional_pose(values['target_pose_guess'] or None)
    seed_from = 'target_pose_guess'
    if seed is None and data.target_guess is not None:
        seed, seed_from = data.target_guess, 'pose_guesses.yaml'
    estimate = values['estimate_marker_offset']
    if seed is None and not estimate:
        raise BoardPipelineError('the board\'s pose on the link is unknown: set '
                                 'estimate_marker_offset or target_pose_guess')
    t1 = time.perf_counter()
    try:
        res = calibrate_board([CameraSpec(name, *size)], bd, prior_settings(values),
                              solver_settings(values), T_link_target=seed,
                              mount=MountSettings(estimate=estimate))
    except ValueError as exc:
        raise BoardPipelineError(f'calibration failed: {exc}') from exc
    t_solve = time.perf_counter() - t1
    cal = res.calibration
    if cal.adjustment is None or not cal.success:
        raise BoardPipelineError(f'calibration failed: {cal.message}')
    hyper = dict(point_sigma=values['point_sigma'], bias_sigma=values['bias_sigma'],
                 coherence_length=values['coherence_length'],
                 pixel_sigma=values['pixel_sigma'])
    calib = calibration_from_result(cal, len(bd), hyper)
    os.makedirs(output_dir, exist_ok=True)
    cams = [c.camera for c in calib.cameras.values()]
    write_cameras(output_dir, cams, values['base_frame'])
    files = [os.path.join(output_dir, f'{c.name}.yaml') for c in cams]
    files.append(os.path.join(output_dir, 'extrinsics.yaml'))
    summary = calib.summary()
    p = os.path.join(output_dir, 'calibration.json')
    atomic_write_text(p, json.dumps(summary, indent=1))
    files.append(p)
    p = os.path.join(output_dir, 'target.yaml')
    atomic_write_text(p, _target_yaml(res.T_link_target, res.mount_std, values['marker_link'],
                                      estimate))
    files.append(p)
    report = dict(
        input=dict(kind='robot_cal_tools folder', path=os.path.abspath(path),
                   images=len(ids), images_with_board=n_used, corners=int(len(bd))),
        noise_model=values['noise_model'], solved_as=res.model, accepted=True,
        message=cal.message, n_samples=int(len(bd)), cameras=summary['cameras'],
        target=dict(T_link_target=[float(x) for x in pose_vector(res.T_link_target)],
                    estimated=bool(estimate),
                    seed=(seed_from if seed is not None else res.init.mount_seed),
                    std=None if res.mount_std is None else [float(x) for x in res.mount_std],
                    rounds=res.rounds, stages=res.stages),
        warnings=warnings,
        timings=dict(front_end_s=t_front, solve_s=t_solve, total_s=t_front + t_solve))
    p = os.path.join(output_dir, 'report.json')
    atomic_write_text(p, json.dumps(report, indent=1, default=_json_default))
    files.append(p)
    return report, files, res


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f'not JSON serialisable: {type(o).__name__}')
