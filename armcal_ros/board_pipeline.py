"""
Board targets with pose input, offline: a robot_cal_tools folder through the whole calibration.

``armcal calibrate DIR`` with a folder holding ``cal_data.yaml`` comes here (and a bag with
``pose_topic`` set and a ``charuco`` target, :func:`calibrate_board_bag`): the folder's images
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
from armcal_ros.engine import calibration_from_result, target_yaml
from armcal_ros.frontend.charuco import CharucoBoard, CharucoDetector
from armcal_ros.io.calib_files import atomic_write_text, write_cameras
from armcal_ros.io.rct_import import (board_data, detect_views, load_rct_folder, pose_vector,
                                      RctFormatError)
from armcal_ros.params import charuco_settings, prior_settings, solver_settings
from armcal_ros.pipeline import pose_from_msg


class BoardPipelineError(RuntimeError):
    """A failure the user can act on; the message is the one-line reason."""


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
    inp = dict(kind='robot_cal_tools folder', path=os.path.abspath(path), images=len(ids),
               images_with_board=n_used, corners=int(len(bd)))
    return solve_board_and_write([CameraSpec(name, *size)], bd, values, output_dir, inp,
                                 warnings, t_front, data.target_guess)


def solve_board_and_write(specs, bd, values, output_dir, input_info, warnings, t_front,
                          data_guess=None):
    """Calibrate ``bd`` with ``values``, write the files; return (report, files, result)."""
    seed = optional_pose(values['target_pose_guess'] or None)
    seed_from = 'target_pose_guess'
    if seed is None and data_guess is not None:
        seed, seed_from = data_guess, 'the data set\'s guess'
    estimate = values['estimate_marker_offset']
    if seed is None and not estimate:
        raise BoardPipelineError('the board\'s pose on the link is unknown: set '
                                 'estimate_marker_offset or target_pose_guess')
    t1 = time.perf_counter()
    try:
        res = calibrate_board(specs, bd, prior_settings(values), solver_settings(values),
                              T_link_target=seed, mount=MountSettings(estimate=estimate))
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
    atomic_write_text(p, target_yaml(res.T_link_target, res.mount_std, values['marker_link'],
                                     estimate))
    files.append(p)
    report = dict(
        input=input_info, noise_model=values['noise_model'], solved_as=res.model,
        accepted=True, message=cal.message, n_samples=int(len(bd)), cameras=summary['cameras'],
        target=dict(T_link_target=[float(x) for x in pose_vector(res.T_link_target)],
                    estimated=bool(estimate),
                    seed=(seed_from if seed is not None else res.init.mount_seed),
                    std=None if res.mount_std is None else [float(x) for x in res.mount_std],
                    rounds=res.rounds, stages=res.stages),
        warnings=warnings,
        timings=dict(front_end_s=t_front, solve_s=t_solve, total_s=t_front + t_solve))
    for name in values['camera_names']:
        if name not in report['cameras']:
            r = cal.init.get(name)
            msg = res.init.method.get(name) or (r.message if r is not None else 'no views')
            report['cameras'][name] = dict(status='not calibrated', message=msg)
    p = os.path.join(output_dir, 'report.json')
    atomic_write_text(p, json.dumps(report, indent=1, default=_json_default))
    files.append(p)
    return report, files, res


POSE_TYPES = ('geometry_msgs/msg/PoseStamped', 'geometry_msgs/msg/TransformStamped')


def calibrate_board_bag(bag, values, output_dir, log: Optional[Callable[[str], None]] = None,
                        max_gap_s=0.1):
    """
    Calibrate from a bag with pose input (``pose_topic``) and a ChArUco board.

    Each image whose stamp lies inside the pose history (bracketing gap at most ``max_gap_s``)
    and at which the board moved slower than ``max_marker_speed`` (a point at the board's
    diagonal from the link origin) is one view: the interpolated link pose and the corners.
    Returns ``(report, files, result)``; raises BoardPipelineError with a one-line reason.
    """
    from armcal_ros.frontend.image_decode import decode_image_msg, ImageDecodeError
    from armcal_ros.frontend.pose_input import PoseTrack
    from armcal_ros.io.bag import bag_topics, DeserializationError, iter_raw
    t0 = time.perf_counter()
    try:
        board = CharucoBoard(**charuco_settings(values))
        topics = bag_topics(bag)
    except ValueError as exc:
        raise BoardPipelineError(str(exc)) from exc
    except Exception as exc:
        raise BoardPipelineError(f'cannot open bag {bag}: {exc}') from exc
    pt = values['pose_topic']
    if pt not in topics or topics[pt][1] == 0 or topics[pt][0] not in POSE_TYPES:
        raise BoardPipelineError(f'bag {bag}: pose_topic {pt} has no PoseStamped or '
                                 f'TransformStamped messages (topics: {sorted(topics)})')
    track = PoseTrack(max_gap_s)
    counts = dict(corrupt_message=0, bad_pose=0, outside=0, gap=0, moving=0, no_board=0,
                  undecodable=0, views=0)
    for raw in iter_raw(bag, [pt]):
        try:
            msg = raw.deserialize()
            track.add(int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec),
                      *pose_from_msg(msg))
        except DeserializationError:
            counts['corrupt_message'] += 1
        except ValueError:
            counts['bad_pose'] += 1
    cam_of_topic = {t: c for c, t in zip(values['camera_names'], values['image_topics'])
                    if t in topics and topics[t][1] > 0}
    warnings = [f'camera {c}: no messages on {t}; it is not calibrated'
                for c, t in zip(values['camera_names'], values['image_topics'])
                if t not in cam_of_topic]
    for w in warnings:
        if log:
            log(w)
    detectors = {c: CharucoDetector(board) for c in cam_of_topic.values()}
    radius = float(np.linalg.norm(board.points().max(axis=0))) + 0.0
    names = list(values['camera_names'])
    poses, view, camera, corner, uv, sizes = [], [], [], [], [], {}
    for raw in iter_raw(bag, list(cam_of_topic)):
        cam = cam_of_topic[raw.topic]
        try:
            msg = raw.deserialize()
        except DeserializationError:
            counts['corrupt_message'] += 1
            continue
        stamp = int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)
        at = track.at(stamp, radius)
        if at.status != 'ok':
            counts[at.status] += 1
            continue
        if at.speed > values['max_marker_speed']:
            counts['moving'] += 1
            continue
        try:
            img = decode_image_msg(msg)
        except ImageDecodeError:
            counts['undecodable'] += 1
            continue
        sizes[cam] = (img.shape[1], img.shape[0])
        u, i = detectors[cam].detect_arrays(img)
        if not len(i):
            counts['no_board'] += 1
            continue
        v = len(poses)
        poses.append(at.pose)
        view += [v] * len(i)
        camera += [names.index(cam)] * len(i)
        corner += list(i)
        uv.append(u)
        counts['views'] += 1
    t_front = time.perf_counter() - t0
    if counts['views'] < 3:
        raise BoardPipelineError(f'only {counts["views"]} usable board views in {bag} '
                                 f'(counts: {counts})')
    from armcal_ros.core.board_calibration import BoardData
    bd = BoardData(np.array(poses), board.points(), view, camera, corner, np.vstack(uv))
    specs = [CameraSpec(n, *sizes.get(n, (0, 0))) for n in names if n in sizes]
    keep = [names.index(s.name) for s in specs]
    remap = -np.ones(len(names), np.int64)
    remap[keep] = np.arange(len(keep))
    bd.camera = remap[bd.camera]
    inp = dict(kind='bag with pose input', path=os.path.abspath(bag), pose_topic=pt,
               corners=int(len(bd)), counts=counts)
    return solve_board_and_write(specs, bd, values, output_dir, inp, warnings, t_front)


def _json_default(o):
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f'not JSON serialisable: {type(o).__name__}')
