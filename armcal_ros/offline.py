"""
``armcal calibrate BAG``: the whole pipeline on a recorded rosbag2 bag, no ROS middleware needed.

Messages are read with rosbags (mcap or sqlite3), fed in bag order to the same
:class:`~armcal_ros.pipeline.SampleCollector` and :class:`~armcal_ros.engine.CalibrationEngine`
the node uses, and the calibration is solved once at the end.  The arm's position comes from
``joint_states_topic`` and the robot model, or with pose input (``pose_topic`` set) from the
marker link's measured pose (PoseStamped or TransformStamped; no robot model needed).  A camera
topic that is missing or empty is reported and the other cameras are still calibrated; a message
that cannot be deserialised is counted and skipped.
"""

import json
import os
import sys
import time
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional

import numpy as np

from armcal_ros.core.kinematic_prior import KinematicData
from armcal_ros.engine import (CalibrationEngine, EngineSettings, quaternion_of,
                               SolveOutcome)
from armcal_ros.frontend.store import SampleStore
from armcal_ros.io.bag import bag_topics, DeserializationError, iter_raw
from armcal_ros.io.calib_files import atomic_write_text
from armcal_ros.params import (check_all, check_value, load_params_file, prior_settings,
                               solver_settings, urdf_text)
from armcal_ros.pipeline import (board_target, make_board, make_detectors, pose_from_msg,
                                 SampleCollector)
from armcal_ros.robot.kinematics import KinematicChain

JOINT_STATE = 'sensor_msgs/msg/JointState'
POSE_TYPES = ('geometry_msgs/msg/PoseStamped', 'geometry_msgs/msg/TransformStamped')
IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')


class CalibrateError(RuntimeError):
    """A failure the user can act on; the message is the one-line reason."""


@dataclass
class OfflineResult:
    """What :func:`calibrate_bag` did."""

    outcome: Optional[SolveOutcome]
    report: Dict
    warnings: List[str] = field(default_factory=list)
    files: List[str] = field(default_factory=list)


def stamp_ns(header_stamp):
    """Return a builtin_interfaces/Time as integer nanoseconds."""
    return int(header_stamp.sec) * 1_000_000_000 + int(header_stamp.nanosec)


def _board(values):
    """Return (CharucoBoard, BoardTarget) for a charuco marker_type, else (None, None)."""
    if values['marker_type'] != 'charuco':
        return None, None
    try:
        board = make_board(values)
        return board, board_target(values, board)
    except ValueError as exc:
        raise CalibrateError(str(exc)) from exc


def build_collector(values, log=None):
    """
    Robot chain, detectors and collector from parameter values.

    With pose input (``pose_topic``) no robot model is read and the chain is None.
    """
    chain = None
    if not values['pose_topic']:
        try:
            chain = KinematicChain.from_urdf(urdf_text(values), values['base_frame'],
                                             values['marker_link'])
        except ValueError as exc:
            raise CalibrateError(f'robot model (parameters robot_description/'
                                 f'robot_description_file, base_frame, marker_link): '
                                 f'{exc}') from exc
    board, target = _board(values)
    detectors = make_detectors(values, values['camera_names'], board)
    return chain, SampleCollector(chain, values['marker_offset'], values['camera_names'],
                                  detectors, values['max_marker_speed'], values['dwell_radius'],
                                  log=log, board=target,
                                  max_views_per_dwell=values['max_views_per_dwell'])


def build_engine(values, chain):
    """
    Engine and its sample store from parameter values.

    ``chain`` (None with pose input) gives the kinematic models their Jacobian; a board
    target has no use for it (those models are refused with a board).
    """
    store = SampleStore(max_samples=values['max_samples'],
                        min_sample_spacing=values['min_sample_spacing'],
                        same_point_tolerance=min(0.0005, values['min_sample_spacing']),
                        joint_names=None if chain is None else chain.joint_names)
    _, target = _board(values)
    try:
        settings = EngineSettings(list(values['camera_names']), prior_settings(values),
                                  solver_settings(values), min_samples=values['min_samples'],
                                  solve_period_s=values['solve_period'],
                                  min_new_samples=values['min_new_samples'],
                                  base_frame=values['base_frame'], board=target,
                                  marker_link=values['marker_link'])
    except ValueError as exc:
        raise CalibrateError(str(exc)) from exc
    if chain is None or target is not None:
        return CalibrationEngine(settings, store)
    offset = np.asarray(values['marker_offset'], float)

    def kinematics(Q):
        return KinematicData(chain.jacobian_errors(Q, offset), chain.error_names)
    return CalibrationEngine(settings, store, kinematics_fn=kinematics)


@dataclass
class FrontEnd:
    """The samples a bag gave, with everything needed to solve and report on them."""

    chain: Optional[KinematicChain]       # None with pose input
    store: SampleStore
    image_sizes: Dict[str, tuple]
    counts: Dict[str, int]
    warnings: List[str]
    added: Dict[str, int]
    messages: int
    time_s: float


def collect_samples(bag, values, progress: Callable[[int, int], None] = None,
                    log: Callable[[str], None] = None) -> FrontEnd:
    """Read ``bag`` and turn its joint states and images into samples (the front end)."""
    t0 = time.perf_counter()
    try:
        topics = bag_topics(bag)
    except Exception as exc:
        raise CalibrateError(f'cannot open bag {bag}: {exc}') from exc
    warnings = []
    pose_input = bool(values['pose_topic'])
    if pose_input:
        jt, kind, types = values['pose_topic'], 'pose_topic', POSE_TYPES
    else:
        jt, kind, types = values['joint_states_topic'], 'joint_states_topic', (JOINT_STATE,)
    if jt not in topics or topics[jt][1] == 0:
        raise CalibrateError(f'bag {bag} has no messages on {kind} {jt} '
                             f'(topics: {sorted(topics)})')
    if topics[jt][0] not in types:
        raise CalibrateError(f'{kind} {jt} carries {topics[jt][0]}, not '
                             f'{" or ".join(types)}')
    cam_of_topic = {}
    for cam, topic in zip(values['camera_names'], values['image_topics']):
        if topic not in topics or topics[topic][1] == 0:
            warnings.append(f'camera {cam}: no messages on {topic}; it is not calibrated')
            continue
        if topics[topic][0] not in IMAGE_TYPES:
            warnings.append(f'camera {cam}: {topic} carries {topics[topic][0]}, not an image; '
                            f'it is not calibrated')
            continue
        cam_of_topic[topic] = cam
    if not cam_of_topic:
        raise CalibrateError(f'bag {bag}: none of the image_topics {values["image_topics"]} '
                             f'has images')
    for w in warnings:
        if log:
            log(w)
    chain, collector = build_collector(values, log)
    store = build_engine(values, chain).store
    total = topics[jt][1] + sum(topics[t][1] for t in cam_of_topic)
    n = 0
    added = {'added': 0, 'merged': 0, 'replaced': 0, 'dropped': 0}
    for raw in iter_raw(bag, [jt] + list(cam_of_topic)):
        n += 1
        if progress and n % 500 == 0:
            progress(n, total)
        try:
            msg = raw.deserialize()
            if raw.topic == jt and pose_input:
                samples = collector.add_pose(stamp_ns(msg.header.stamp), *pose_from_msg(msg))
            elif raw.topic == jt:
                samples = collector.add_joint_state(stamp_ns(msg.header.stamp), msg.name,
                                                    msg.position)
            else:
                samples = collector.add_image(cam_of_topic[raw.topic],
                                              stamp_ns(msg.header.stamp), msg)
        except DeserializationError as exc:
            collector.counts['corrupt_message'] += 1
            collector.log('corrupt_message', f'skipped: {exc}')
            continue
        for s in samples:
            added[store.add(s).value] += 1
    for s in collector.flush():
        added[store.add(s).value] += 1
    if progress:
        progress(total, total)
    return FrontEnd(chain, store, dict(collector.image_sizes), dict(collector.counts), warnings,
                    added, n, time.perf_counter() - t0)


def solve_and_write(front: FrontEnd, values, output_dir) -> OfflineResult:
    """Solve the collected samples with ``values``' noise model and write the files."""
    if len(front.store) < values['min_samples']:
        raise CalibrateError(f'only {len(front.store)} samples (min_samples '
                             f'{values["min_samples"]}): did the arm dwell in view of the '
                             f'cameras? front-end counts: {front.counts}')
    engine = build_engine(values, front.chain)
    engine.store = front.store
    for cam, (w, h) in front.image_sizes.items():
        engine.set_image_size(cam, w, h)
    outcome = engine.solve(force=True)
    report = make_report(values, engine, outcome, front,
                         dict(front_end_s=front.time_s, solve_s=outcome.time_s,
                              total_s=front.time_s + outcome.time_s, messages=front.messages))
    if not outcome.accepted:
        raise CalibrateError(f'calibration failed: {outcome.reason}')
    os.makedirs(output_dir, exist_ok=True)
    files = engine.save(output_dir)
    path = os.path.join(output_dir, 'report.json')
    atomic_write_text(path, json.dumps(report, indent=1))
    files.append(path)
    return OfflineResult(outcome, report, front.warnings, files)


def calibrate_bag(bag, values, output_dir, progress: Callable[[int, int], None] = None,
                  log: Callable[[str], None] = None) -> OfflineResult:
    """Run the pipeline on ``bag`` with checked parameter ``values``; write to ``output_dir``."""
    return solve_and_write(collect_samples(bag, values, progress, log), values, output_dir)


def make_report(values, engine, outcome, front, timings):
    """Return the report.json content."""
    cal = outcome.calibration
    cams = {}
    if cal is not None:
        for name, c in cal.summary()['cameras'].items():
            cams[name] = c
        init = outcome.result.init if outcome.result is not None else {}
        for name in values['camera_names']:
            if name not in cams:
                r = init.get(name)
                cams[name] = dict(status='not calibrated',
                                  message=(r.message if r is not None else
                                           'no usable images'))
    target = None
    if engine.settings.board is not None:
        T = engine.T_link_target
        target = dict(
            T_link_target=(None if T is None else
                           [float(x) for x in np.concatenate([T[:3, 3], quaternion_of(T)])]),
            estimated=bool(engine.settings.board.estimate_mount),
            std=(None if engine.mount_std is None else [float(x) for x in engine.mount_std]))
    return dict(
        input=dict(arm=('pose_topic ' + values['pose_topic'] if values['pose_topic'] else
                        'joint_states_topic ' + values['joint_states_topic']),
                   marker_type=values['marker_type']),
        target=target,
        noise_model=values['noise_model'],
        hyperparameters=dict(pixel_sigma=values['pixel_sigma'],
                             point_sigma=values['point_sigma'],
                             bias_sigma=values['bias_sigma'],
                             coherence_length=values['coherence_length'],
                             kernel=values['kernel'],
                             free_distortion=list(values['free_distortion']),
                             robust_loss=values['robust_loss'],
                             robust_loss_scale=values['robust_loss_scale']),
        chosen=(dict(cal.hyperparameters) if cal is not None else {}),
        accepted=bool(outcome.accepted), message=outcome.reason,
        n_samples=len(engine.store), samples=front.added, cameras=cams,
        front_end=dict(front.counts), warnings=front.warnings, timings=timings,
        stages=[list(s) for s in (outcome.result.stages if outcome.result else [])])


def format_table(report):
    """Return the short table printed by the CLI."""
    chosen = report.get('chosen', {})
    lines = [f'noise model {report["noise_model"]}: {report["n_samples"]} samples; '
             f'{report["message"]}']
    if report['noise_model'] == 'auto' and chosen:
        lines.append(f'auto chose {chosen.get("model")}: {chosen.get("auto_reason", "")}')
    lines.append(f'{"camera":<10} {"fx":>9} {"fy":>9} {"cx":>8} {"cy":>8} {"k1":>8} '
                 f'{"obs":>5} {"inl":>5} {"rms px":>7}')
    for name, c in report['cameras'].items():
        if 'fx' not in c:
            lines.append(f'{name:<10} {c["status"]}: {c["message"]}')
            continue
        s = c['std']
        lines.append(f'{name:<10} {c["fx"]:9.2f} {c["fy"]:9.2f} {c["cx"]:8.2f} {c["cy"]:8.2f} '
                     f'{c["dist"][0]:8.4f} {c["n_observations"]:5d} {c["n_inliers"]:5d} '
                     f'{c["rms_px"]:7.3f}')
        lines.append(f'{"  +/-":<10} {s["fx"]:9.2f} {s["fy"]:9.2f} {s["cx"]:8.2f} '
                     f'{s["cy"]:8.2f} {s.get("k1", 0.0):8.4f}')
    t = report['timings']
    lines.append(f'front end {t["front_end_s"]:.1f} s, solve {t["solve_s"]:.1f} s')
    return '\n'.join(lines)


def add_arguments(p):
    """Arguments of ``armcal calibrate``."""
    p.add_argument('bag', metavar='BAG',
                   help='rosbag2 bag directory (mcap or sqlite3), or a robot_cal_tools data '
                   'folder (cal_data.yaml, images, poses, target.yaml)')
    p.add_argument('--params', required=True, metavar='PARAMS.yaml',
                   help='the node\'s ROS 2 parameter file (armcal: ros__parameters: ...)')
    p.add_argument('--output', required=True, metavar='DIR', help='where to write the files')
    p.add_argument('--noise-model', default=None,
                   help='override the parameter file\'s noise_model')
    p.add_argument('--quiet', action='store_true', help='no progress or log lines')


def run(args):
    """Run ``armcal calibrate``; return the exit status (errors raise with a one-line reason)."""
    from armcal_ros.io.rct_import import is_rct_folder
    rct = is_rct_folder(args.bag)
    try:
        values = load_params_file(args.params, require_robot_model=not rct)
        if args.noise_model is not None:
            values['noise_model'] = check_value('noise_model', args.noise_model)
            check_all(values, require_robot_model=not rct)
    except ValueError as exc:
        raise CalibrateError(str(exc)) from exc

    def progress(i, n):
        if not args.quiet:
            print(f'\r  {i}/{n} messages ({100.0 * i / max(n, 1):.0f} %)', end='',
                  file=sys.stderr, flush=True)

    def log(message):
        if not args.quiet:
            print(f'\n[armcal] {message}', file=sys.stderr)

    if rct:
        from armcal_ros.board_pipeline import BoardPipelineError, calibrate_rct_folder
        try:
            report, files, _ = calibrate_rct_folder(args.bag, values, args.output, log)
        except BoardPipelineError as exc:
            raise CalibrateError(str(exc)) from exc
        print(format_table(report))
        tgt = report['target']
        print(f'T_{values["marker_link"]}_target (x y z qx qy qz qw): ' +
              ' '.join(f'{v:.5f}' for v in tgt['T_link_target']) +
              (' (estimated)' if tgt['estimated'] else ' (given)'))
        print(f'wrote {", ".join(os.path.basename(f) for f in files)} to {args.output}')
        return 0
    if values['pose_topic'] and values['marker_type'] == 'charuco':
        # A board with pose input: every still frame is a view of its own (views from
        # robot_cal_tools-style recordings are single frames), solved by the board pipeline.
        from armcal_ros.board_pipeline import BoardPipelineError, calibrate_board_bag
        try:
            report, files, _ = calibrate_board_bag(args.bag, values, args.output, log)
        except BoardPipelineError as exc:
            raise CalibrateError(str(exc)) from exc
        print(format_table(report))
        print(f'wrote {", ".join(os.path.basename(f) for f in files)} to {args.output}')
        return 0
    res = calibrate_bag(args.bag, values, args.output, progress, log)
    if not args.quiet:
        print('', file=sys.stderr)
    print(format_table(res.report))
    tgt = res.report.get('target')
    if tgt and tgt['T_link_target'] is not None:
        print(f'T_{values["marker_link"]}_target (x y z qx qy qz qw): ' +
              ' '.join(f'{v:.5f}' for v in tgt['T_link_target']) +
              (' (estimated)' if tgt['estimated'] else ' (given)'))
    print(f'wrote {", ".join(os.path.basename(f) for f in res.files)} to {args.output}')
    return 0
