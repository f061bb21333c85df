"""
``armcal calibrate SOURCE``: the whole pipeline on a recording, no ROS middleware needed.

A recording is a rosbag2 bag (mcap or sqlite3, read with rosbags) or a robot_cal_tools data
folder (images and link poses).  Either becomes one time-ordered stream of inputs - joint
states or measured link poses, and images - fed to the pipeline the node uses
(:func:`~armcal_ros.compose.build_pipeline`: the same collector pools each dwell into one
sample, the same engine solves), and the calibration is solved once at the end.  A folder's
views are replayed as still dwells one second apart, so the offline and the live paths never
differ in what they make of the same data.

A camera topic that is missing or empty is reported and the other cameras are still calibrated;
a message that cannot be deserialised is counted and skipped.  A corrupt bag is read as far as it
is readable (:func:`~armcal_ros.io.bag.iter_raw`): the messages it lost are counted per topic
into the report's ``lost_messages`` and a warning; one that cannot be read at all is a
:class:`CalibrateError` naming why.
"""

import copy
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from typing import Callable, Dict, Iterator, List, Optional

import numpy as np

from armcal_ros.change_tracking import ChangeTracker
from armcal_ros.compose import build_engine, build_pipeline, build_store, latency_detectors
from armcal_ros.core.target import pose_vector
from armcal_ros.engine import SolveOutcome
from armcal_ros.frontend.collector import SampleCollector, why_few_samples
from armcal_ros.frontend.samples import BoardTarget
from armcal_ros.frontend.store import SampleStore
from armcal_ros.io.bag import (bag_topics, BagLosses, BagReadError, DeserializationError,
                               iter_raw)
from armcal_ros.io.calib_files import atomic_write_text
from armcal_ros.io.folder_import import capture_stamp, POSE_MARGIN_NS
from armcal_ros.io.message_fields import camera_from_camera_info, pose_from_msg, stamp_ns
from armcal_ros.io.output_dir import OutputDirectory, OutputDirError
from armcal_ros.io.rct_import import is_rct_folder, load_rct_folder, RctFormatError
from armcal_ros.io.results_files import write_calibration
from armcal_ros.robot.kinematics import KinematicChain
from armcal_ros.settings import load_settings, Settings, with_given_intrinsics
from armcal_ros.stamp_latency import latency_differs, latency_report, measure_latencies

JOINT_STATE = 'sensor_msgs/msg/JointState'
POSE_TYPES = ('geometry_msgs/msg/PoseStamped', 'geometry_msgs/msg/TransformStamped')
IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')


class CalibrateError(RuntimeError):
    """A failure the user can act on; the message is the one-line reason."""


@dataclass
class EncodedImage:
    """An image file's bytes as a CompressedImage-like message (``format``, ``data``)."""

    format: str
    data: bytes


@dataclass
class Recording:
    """
    A recording as a stream of front-end inputs.

    ``events()`` yields ``('joints', stamp_ns, names, positions)``, ``('pose', stamp_ns,
    translation, quaternion)``, ``('image', camera, stamp_ns, message)`` or
    ``('corrupt', reason[, topic])``, in time order.  ``board_target`` and ``board_guess``
    complete a board from the data set's own files (a robot_cal_tools ``target.yaml`` and
    ``pose_guesses.yaml``).  ``losses`` is what reading a bag lost, complete once ``events()``
    is exhausted.
    """

    events: Callable[[], Iterator[tuple]]
    total: int
    info: Dict
    warnings: List[str] = field(default_factory=list)
    board_target: Optional[tuple] = None
    board_guess: Optional[object] = None
    #: The source gives the link's poses whatever ``pose_topic`` says (a folder).
    poses_given: bool = False
    #: Intrinsics read from the recording's CameraInfo (cameras given without a file).
    intrinsics: Dict = field(default_factory=dict)
    losses: Optional[BagLosses] = None


@dataclass
class FrontEnd:
    """The samples a recording gave, with everything needed to solve and report on them."""

    chain: Optional[KinematicChain]       # None with pose input
    board: Optional[BoardTarget]          # None for a point marker
    store: SampleStore
    image_sizes: Dict[str, tuple]
    counts: Dict[str, int]
    warnings: List[str]
    added: Dict[str, int]
    messages: int
    time_s: float
    source: Dict = field(default_factory=dict)
    intrinsics: Dict = field(default_factory=dict)
    #: What change detection found reading the recording in time order (None: not run).
    changes: Optional[ChangeTracker] = None
    monitor_solves: int = 0
    #: Camera name -> the frame_id of its first image (the optical frame the outputs name).
    frame_ids: Dict[str, str] = field(default_factory=dict)
    #: Robot-model joints the joint states lacked, and the names such a message carried.
    missing_joints: tuple = ()
    seen_joint_names: tuple = ()
    #: Topic -> messages of the recording that never reached the front end (corrupt data).
    lost: Dict[str, int] = field(default_factory=dict)


@dataclass
class OfflineResult:
    """What :func:`calibrate_bag` did."""

    outcome: Optional[SolveOutcome]
    report: Dict
    warnings: List[str] = field(default_factory=list)
    files: List[str] = field(default_factory=list)


def open_bag(bag, settings: Settings) -> Recording:
    """Check a bag's topics against ``settings`` and return it as a :class:`Recording`."""
    try:
        topics = bag_topics(bag)
    except BagReadError as exc:
        raise CalibrateError(str(exc)) from exc
    except Exception as exc:
        raise CalibrateError(f'cannot open bag {bag}: {exc}') from exc
    inputs = settings.inputs
    arm = inputs.arm_topic
    kind, types = (('pose_topic', POSE_TYPES) if inputs.pose_input else
                   ('joint_states_topic', (JOINT_STATE,)))
    if arm not in topics or topics[arm][1] == 0:
        raise CalibrateError(f'bag {bag} has no messages on {kind} {arm} '
                             f'(topics: {sorted(topics)})')
    if topics[arm][0] not in types:
        raise CalibrateError(f'{kind} {arm} carries {topics[arm][0]}, not '
                             f'{" or ".join(types)}')
    warnings, cam_of_topic = [], {}
    for cam, topic in zip(inputs.camera_names, inputs.image_topics):
        if topic not in topics or topics[topic][1] == 0:
            warnings.append(f'camera {cam}: no messages on {topic}; it is not calibrated')
        elif topics[topic][0] not in IMAGE_TYPES:
            warnings.append(f'camera {cam}: {topic} carries {topics[topic][0]}, not an image; '
                            f'it is not calibrated')
        else:
            cam_of_topic[topic] = cam
    if not cam_of_topic:
        raise CalibrateError(f'bag {bag}: none of the image_topics {list(inputs.image_topics)} '
                             f'has images')

    losses = BagLosses()

    def events():
        try:
            for raw in iter_raw(bag, [arm] + list(cam_of_topic), losses):
                try:
                    msg = raw.deserialize()
                except DeserializationError as exc:
                    yield ('corrupt', str(exc), raw.topic)
                    continue
                if raw.topic != arm:
                    yield ('image', cam_of_topic[raw.topic], stamp_ns(msg.header.stamp), msg)
                elif inputs.pose_input:
                    yield ('pose', stamp_ns(msg.header.stamp)) + pose_from_msg(msg)
                else:
                    yield ('joints', stamp_ns(msg.header.stamp), msg.name, msg.position)
        except BagReadError as exc:
            raise CalibrateError(str(exc)) from exc
    total = topics[arm][1] + sum(topics[t][1] for t in cam_of_topic)
    info = dict(kind='bag', path=os.path.abspath(str(bag)), arm=inputs.describe_arm())
    return Recording(events, total, info, warnings,
                     intrinsics=_bag_intrinsics(bag, topics, settings), losses=losses)


def _bag_intrinsics(bag, topics, settings: Settings):
    """Read the first CameraInfo of each camera whose given intrinsics come from its topic."""
    out = {}
    for cam, topic in settings.intrinsics.topics:
        if topic not in topics or topics[topic][1] == 0:
            mode = dict(settings.intrinsics.modes)[cam]
            raise CalibrateError(f'camera {cam}: intrinsics_mode {mode} without an '
                                 f'intrinsics_files entry needs its CameraInfo on {topic}, '
                                 f'which bag {bag} does not have')
        # the first CameraInfo that reads: one lost to corruption is no reason to stop
        losses, error = BagLosses(), None
        messages = iter_raw(bag, [topic], losses)
        try:
            for raw in messages:
                try:
                    msg = raw.deserialize()
                    out[cam] = settings.intrinsics.prior_from(cam,
                                                              camera_from_camera_info(msg, cam))
                    break
                except (DeserializationError, ValueError) as exc:
                    error = error or exc
        except BagReadError as exc:
            raise CalibrateError(str(exc)) from exc
        finally:
            messages.close()            # the reader is open until the generator ends
        if cam not in out:
            why = error or f'none of its messages is readable ({losses.describe()})'
            raise CalibrateError(f'camera {cam}: CameraInfo on {topic}: {why}')
    return out


def open_folder(path, settings: Settings) -> Recording:
    """
    Return a robot_cal_tools folder as a :class:`Recording` of still views.

    The folder has one camera: its images are the first of ``camera_names``.  View k is
    replayed as a capture folder's (:func:`~armcal_ros.io.folder_import.capture_stamp`): the
    image with its link pose given just before and after it, so the front end pairs it as a
    still frame and pools it as a dwell of its own.
    """
    try:
        data = load_rct_folder(path)
    except RctFormatError as exc:
        raise CalibrateError(str(exc)) from exc
    names = settings.inputs.camera_names
    camera = names[0]
    warnings = []
    if len(names) > 1:
        warnings.append(f'a robot_cal_tools folder has one camera: calibrating it as '
                        f'{camera!r} (camera_names lists {len(names)})')

    def events():
        for k, (image, T) in enumerate(zip(data.image_paths, data.poses)):
            t = capture_stamp(k)
            x = pose_vector(T)
            yield ('pose', t - POSE_MARGIN_NS, x[:3], x[3:])
            try:
                with open(image, 'rb') as f:
                    msg = EncodedImage(os.path.splitext(image)[1].lstrip('.').lower(),
                                       f.read())
            except OSError as exc:
                yield ('corrupt', f'{image}: {exc}')
            else:
                yield ('image', camera, t, msg)
            yield ('pose', t + POSE_MARGIN_NS, x[:3], x[3:])
    info = dict(kind='robot_cal_tools folder', path=os.path.abspath(path),
                images=len(data.image_paths), arm='link poses of the folder')
    return Recording(events, 3 * len(data.image_paths), info, warnings,
                     data.target.board_args, data.target_guess, poses_given=True)


def feed(collector: SampleCollector, event) -> List:
    """Hand one :class:`Recording` event to the collector; return the samples it completed."""
    kind = event[0]
    if kind == 'joints':
        return collector.add_joint_state(*event[1:])
    if kind == 'pose':
        return collector.add_pose(*event[1:])
    if kind == 'image':
        return collector.add_image(*event[1:])
    collector.counts['corrupt_message'] += 1
    collector.log('corrupt_message', f'skipped: {event[1]}')
    return []


def _lost_messages(source, rec: Recording, undecodable):
    """Return {topic: messages lost} (storage and deserialisation) and a warning, or None."""
    losses = rec.losses or BagLosses()
    lost = dict(losses.lost)
    for topic, n in undecodable.items():
        lost[topic] = lost.get(topic, 0) + n
    if not lost:
        return lost, None
    counts = ', '.join(f'{t} {n} of {losses.expected.get(t, "?")}'
                       for t, n in sorted(lost.items()))
    why = [losses.reasons()] if losses.lost else []
    if undecodable:
        why.append(f'{sum(undecodable.values())} did not deserialise')
    return lost, (f'{source}: {sum(lost.values())} messages lost to corrupt data and not used '
                  f'({counts}): {"; ".join(why)}')


def collect_samples(source, settings: Settings, progress: Callable[[int, int], None] = None,
                    log: Callable[[str], None] = None) -> FrontEnd:
    """Read a bag or a robot_cal_tools folder and turn it into samples (the front end)."""
    t0 = time.perf_counter()
    rec = open_folder(source, settings) if is_rct_folder(source) else open_bag(source, settings)
    for w in rec.warnings:
        if log:
            log(w)
    try:
        pipe = build_pipeline(settings, log, rec.board_target, rec.board_guess,
                              pose_input=rec.poses_given or None)
    except ValueError as exc:
        raise CalibrateError(str(exc)) from exc
    collector, engine = pipe.collector, pipe.engine
    store = engine.store
    follow = engine.changes.enabled
    n, solves = 0, 0
    added = {'added': 0, 'merged': 0, 'replaced': 0, 'dropped': 0}

    def add(sample):
        nonlocal solves
        if not follow:
            added[store.add(sample).value] += 1
            return
        # In time order, as the node would: each sample is tested against the calibration
        # of the samples before it, solved as they (or a camera's views) double
        # (CalibrationEngine.solve_if_grown).
        added[engine.add_sample(sample).value] += 1
        for cam, (w, h) in collector.image_sizes.items():
            if cam in engine.settings.camera_names:
                engine.set_image_size(cam, w, h)
        outcome = engine.solve_if_grown()
        if outcome is not None:
            solves += 1
            if outcome.result is None and outcome.reason.startswith('solve failed') and log:
                log(f'a solve while reading the recording failed ({outcome.reason}); reading on')

    frame_ids, undecodable = {}, {}
    for event in rec.events():
        n += 1
        if event[0] == 'corrupt' and len(event) > 2:
            undecodable[event[2]] = undecodable.get(event[2], 0) + 1
        if progress and n % 500 == 0:
            progress(n, rec.total)
        if event[0] == 'image' and event[1] not in frame_ids:
            frame = getattr(getattr(event[3], 'header', None), 'frame_id', '')
            if isinstance(frame, str) and frame:
                frame_ids[event[1]] = frame
                engine.frame_ids[event[1]] = frame
        for s in feed(collector, event):
            add(s)
    for s in collector.flush():
        add(s)
    if progress:
        progress(rec.total, rec.total)
    lost, warning = _lost_messages(source, rec, undecodable)
    if warning:
        rec.warnings.append(warning)
        if log:
            log(warning)
    for r in engine.changes.records:
        if log:
            log(r.summary(store.first_stamp_ns()))
    return FrontEnd(pipe.chain, engine.settings.board, store, dict(collector.image_sizes),
                    dict(collector.counts), rec.warnings, added, n, time.perf_counter() - t0,
                    rec.info, rec.intrinsics, engine.changes if follow else None, solves,
                    frame_ids, tuple(sorted(collector.missing_joints)),
                    collector.seen_joint_names, lost=lost)


def solve_and_write(front: FrontEnd, settings: Settings, output_dir) -> OfflineResult:
    """Solve the collected samples with ``settings``' noise model and write the files."""
    engine, outcome, report = _solve(front, settings)
    if not isinstance(output_dir, OutputDirectory):
        with _output_directory(output_dir) as out:
            return _write(engine, outcome, report, front, out)
    return _write(engine, outcome, report, front, output_dir)


def _solve(front: FrontEnd, settings: Settings):
    """Return (engine, outcome, report) of a solve of ``front``'s samples (raise if refused)."""
    if len(front.store) < settings.schedule.min_samples:
        why = why_few_samples(front.counts, front.missing_joints, front.seen_joint_names)
        raise CalibrateError(f'only {len(front.store)} samples (min_samples '
                             f'{settings.schedule.min_samples}): '
                             f'{why or "did the arm dwell in view of the cameras?"}; '
                             f'front-end counts: {dict(front.counts)}')
    settings = with_given_intrinsics(settings, front.intrinsics)
    try:
        engine = build_engine(settings, front.chain, front.board)
    except ValueError as exc:
        raise CalibrateError(str(exc)) from exc
    engine.store = front.store
    engine.frame_ids.update(front.frame_ids)
    if front.changes is not None:
        engine.changes = copy.deepcopy(front.changes)
        engine.changes.monitor = engine.changes.pending = None
    for cam, (w, h) in front.image_sizes.items():
        engine.set_image_size(cam, w, h)
    outcome = engine.solve(force=True)
    report = make_report(settings, engine, outcome, front,
                         dict(front_end_s=front.time_s, solve_s=outcome.time_s,
                              total_s=front.time_s + outcome.time_s, messages=front.messages))
    if not outcome.accepted:
        raise CalibrateError(f'calibration failed: {outcome.reason}')
    return engine, outcome, report


def _measure_latency(recording, front, engine, outcome, settings):
    """Return {camera: LatencyEstimate} on ``recording``, or None where it does not apply."""
    detectors = latency_detectors(settings, list(outcome.calibration.cameras), front.chain)
    if recording is None or detectors is None:
        return None
    T = engine.T_link_target
    offset = settings.robot.marker_offset if T is None else np.asarray(T)[:3, 3]
    return measure_latencies(recording, detectors, front.chain, offset, outcome.calibration)


def _latencies_to_apply(estimates, settings):
    """Return {camera: latency (s)} to pair with, when a measured one differs from the given."""
    given = dict(settings.front_end.image_stamp_latency)
    new = {}
    for cam, e in estimates.items():
        if latency_differs(e, given.get(cam, 0.0)):
            new[cam] = e.latency_s
    return dict(given, **new) if new else {}


def _write(engine, outcome, report, front: FrontEnd, out: OutputDirectory) -> OfflineResult:
    """Write the run's files into ``out``'s staging area, then put them in place as a set."""
    stage = out.staging
    engine.save(stage)
    for epoch, cal in sorted(engine.changes.epoch_calibrations.items()):
        write_calibration(os.path.join(stage, 'epochs', f'epoch_{epoch}'), cal,
                          engine.settings.base_frame, dict(engine.frame_ids))
    atomic_write_text(os.path.join(stage, 'report.json'), json.dumps(report, indent=1))
    return OfflineResult(outcome, report, front.warnings, out.commit())


def _output_directory(path) -> OutputDirectory:
    try:
        return OutputDirectory(path)
    except OutputDirError as exc:
        raise CalibrateError(str(exc)) from None


def calibrate_bag(source, settings: Settings, output_dir,
                  progress: Callable[[int, int], None] = None,
                  log: Callable[[str], None] = None, latency: bool = True) -> OfflineResult:
    """
    Run the pipeline on a bag or robot_cal_tools folder; write to ``output_dir``.

    The directory is checked and locked before the recording is read (a run that cannot write
    its results fails at once), and the run's files replace the previous run's as a set
    (:mod:`armcal_ros.io.output_dir`).  With ``latency`` (a bag, a point marker) each camera's
    stamp latency is measured in a second pass over the bag and reported; where it differs
    from the one given (``image_stamp_latency``) by more than its noise and 2 ms
    (:func:`~armcal_ros.stamp_latency.latency_differs`), the frames are paired again at
    stamp - latency and the samples solved again.
    """
    with _output_directory(output_dir) as out:
        front = collect_samples(source, settings, progress, log)
        latency = latency and not is_rct_folder(source)
        try:
            engine, outcome, report = _solve(front, settings)
            probe = (front, engine, outcome)
        except CalibrateError as exc:
            if not (latency and front.store.retired):
                raise
            # The frames were paired at their stamps, which may be late: the changes followed
            # may be the stamps' (an arm in motion seen where it was some tens of ms before),
            # and what they left is too little to solve.  The latency is then measured on a
            # calibration of every sample, changes not followed, and the frames paired again;
            # a change that is real is found again in that pass.
            failed = exc
            if log:
                log(f'{exc}; the changes found may come from late stamps: measuring the stamp '
                    f'latency on every sample, changes not followed')
            everything = _with_retired(front, settings)
            try:
                probe = (everything,) + _solve(everything, settings)[:2]
            except CalibrateError:
                raise failed from None      # the first pass's own reason says more
            engine = outcome = report = None
        if latency:
            t0 = time.perf_counter()
            estimates = _measure_latency(open_bag(source, settings), *probe, settings)
            seconds = time.perf_counter() - t0
            apply = _latencies_to_apply(estimates, settings) if estimates else {}
            if outcome is None and not apply:
                raise failed            # nothing to pair again: the first pass's failure stands
            if apply:
                # Pair every frame again at its exposure time, and solve again.
                if log:
                    log('stamp latency measured (' + ', '.join(
                        f'{c} {1e3 * v:.1f} ms' for c, v in apply.items()) +
                        '): pairing the frames again with it')
                settings = replace(settings, front_end=replace(
                    settings.front_end, image_stamp_latency=tuple(apply.items())))
                first_s = front.time_s
                front = collect_samples(source, settings, None, log)
                engine, outcome, report = _solve(front, settings)
                report['timings']['front_end_s'] += first_s
                report['timings']['total_s'] += first_s
            if estimates:
                report['stamp_latency'] = latency_report(estimates, apply or None)
                report['timings']['latency_s'] = seconds
        return _write(engine, outcome, report, front, out)


def _with_retired(front: FrontEnd, settings: Settings) -> FrontEnd:
    """
    Return ``front`` with the observations its changes retired put back, changes not followed.

    Each retired observation goes back as a sample of its own place (a new store, in the order
    the samples were made): for a calibration that only has to time the stamps.
    """
    store = build_store(settings, front.chain)
    samples = [s for _, s in front.store.retired] + list(front.store)
    for s in sorted(samples, key=lambda s: (s.id, s.stamp_ns)):
        store.add(replace(s, observations=dict(s.observations), id=-1))
    return replace(front, store=store, changes=None)


def make_report(settings: Settings, engine, outcome, front: FrontEnd, timings):
    """Return the report.json content."""
    cal = outcome.calibration
    cams = {}
    if cal is not None:
        cams.update(cal.summary()['cameras'])
        init = outcome.result.init if outcome.result is not None else {}
        for name in settings.inputs.camera_names:
            if name not in cams:
                r = init.get(name)
                why = cal.not_calibrated.get(name)
                cams[name] = dict(status='not calibrated',
                                  message=(why if why else r.message if r is not None else
                                           'no usable images'))
    target = None
    board = engine.settings.board
    if engine.target_estimated is not None:
        T = engine.T_link_target
        target = dict(
            T_link_target=None if T is None else pose_vector(T),
            estimated=engine.target_estimated,
            std=(None if engine.mount_std is None else [float(x) for x in engine.mount_std]))
        if board is not None and board.estimate_scale:
            target.update(scale=engine.target_scale,
                          aruco_size=settings.target.aruco_size * engine.target_scale)
    prior, solver = settings.prior, settings.solver
    return dict(
        input=dict(front.source, marker_type=settings.target.marker_type),
        target=target,
        noise_model=prior.model,
        hyperparameters=dict(pixel_sigma=solver.pixel_sigma, point_sigma=prior.point_sigma,
                             bias_sigma=prior.bias_sigma,
                             coherence_length=prior.coherence_length, kernel=prior.kernel,
                             free_distortion=list(solver.free_distortion),
                             robust_loss=solver.loss, robust_loss_scale=solver.loss_scale),
        chosen=(dict(cal.hyperparameters) if cal is not None else {}),
        accepted=bool(outcome.accepted), message=outcome.reason,
        n_samples=len(engine.store), samples=front.added, cameras=cams,
        front_end=dict(front.counts), lost_messages=dict(front.lost), warnings=front.warnings,
        timings=timings,
        stages=[list(s) for s in (outcome.result.stages if outcome.result else [])],
        changes=_changes_report(engine, front),
        light_pooling=({name: dict(status=p.status, message=p.message, views=int(len(p.shift)),
                                   loo_rms_px=(p.loo_rms if math.isfinite(p.loo_rms) else None),
                                   mean_shift_px=[float(v) for v in p.shift.mean(axis=0)])
                        for name, p in engine.light_pooling.items()}
                       if engine.settings.pool_light_shift else None))


def _changes_report(engine, front):
    """Return the report's account of change detection (None when it was off)."""
    if front.changes is None:
        return None
    start = front.store.first_stamp_ns()
    return dict(
        epochs=engine.changes.epoch + 1, solves_while_reading=front.monitor_solves,
        withheld=engine.withheld(),
        events=[dict(_json_safe_record(r), summary=r.summary(start),
                     onset_s=(r.onset_ns - start) * 1e-9,
                     detected_s=(r.detected_ns - start) * 1e-9)
                for r in engine.changes.records])


def _json_safe_record(r):
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in asdict(r).items()}


def format_table(report):
    """Return the short table printed by the CLI."""
    chosen = report.get('chosen', {})
    message = report['message']
    reason = chosen.get('auto_reason', '') if report['noise_model'] == 'auto' else ''
    if reason and message.startswith(reason):
        # The solve's message opens with auto's reason: say it once.
        message = message[len(reason):].lstrip('; ')
    lines = [f'noise model {report["noise_model"]}: {report["n_samples"]} samples'
             + (f'; {message}' if message else '')]
    if reason:
        lines.append(f'auto {reason}' if reason.startswith('chose') else
                     f'auto chose {chosen.get("model")}: {reason}')
    if chosen.get('pixel_sigma') is not None:
        lines.append(f'image noise {chosen["pixel_sigma"]:.3f} px '
                     f'({chosen.get("pixel_sigma_source", "given")}); uncertainty: '
                     f'{chosen.get("uncertainty", "model")}; expected 3-D error the '
                     f'calibration adds over the workspace '
                     f'{chosen.get("triangulation_error_mm") or float("nan"):.2f} mm')
    lines.append(f'{"camera":<10} {"fx":>9} {"fy":>9} {"cx":>8} {"cy":>8} {"k1":>8} '
                 f'{"obs":>5} {"inl":>5} {"rms px":>7} {"3-D mm":>7}')
    for name, c in report['cameras'].items():
        if 'fx' not in c:
            lines.append(f'{name:<10} {c["status"]}: {c["message"]}')
            continue
        s = c['std']
        lines.append(f'{name:<10} {c["fx"]:9.2f} {c["fy"]:9.2f} {c["cx"]:8.2f} {c["cy"]:8.2f} '
                     f'{c["dist"][0]:8.4f} {c["n_observations"]:5d} {c["n_inliers"]:5d} '
                     f'{c["rms_px"]:7.3f} {c.get("workspace_error_mm") or float("nan"):7.2f}')
        lines.append(f'{"  +/-":<10} {s["fx"]:9.2f} {s["fy"]:9.2f} {s["cx"]:8.2f} '
                     f'{s["cy"]:8.2f} {s.get("k1", 0.0):8.4f}')
    changes = report.get('changes') or {}
    for e in changes.get('events', []):
        lines.append(f'change: {e["summary"]}')
    for name in changes.get('withheld', []):
        lines.append(f'{name:<10} withheld: it changed and has too few new views to be '
                     'recalibrated (recalibration_samples)')
    for name, e in (report.get('stamp_latency') or {}).items():
        lines.append(f'{name:<10} stamp latency ' + (
            f'{e["latency_ms"]:.1f} ms +/- {e["std_ms"]:.1f} ({e["frames"]} frames in motion)'
            if e['status'] == 'ok' else f'not measured: {e["message"]}') + (
            f'; frames paired at stamp - {e["applied_ms"]:.1f} ms' if e.get('applied_ms')
            else ''))
    t = report['timings']
    lines.append(f'front end {t["front_end_s"]:.1f} s, solve {t["solve_s"]:.1f} s'
                 + (f', latency {t["latency_s"]:.1f} s' if 'latency_s' in t else ''))
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
    p.add_argument('--no-latency', action='store_true',
                   help='do not measure each camera\'s stamp latency (a second pass over the bag '
                        'timing the frames in motion; point markers)')
    p.add_argument('--quiet', action='store_true',
                   help='print nothing but errors and lost or skipped input (the results are '
                        'in DIR: report.json)')


def _is_loss(message):
    """Whether a log line reports input that was lost or skipped (printed even when quiet)."""
    return any(w in message for w in ('lost', 'not calibrated'))


def run(args):
    """Run ``armcal calibrate``; return the exit status (errors raise with a one-line reason)."""
    folder = is_rct_folder(args.bag)
    overrides = {} if args.noise_model is None else {'noise_model': args.noise_model}
    try:
        settings = load_settings(args.params, overrides, require_robot_model=not folder)
    except ValueError as exc:
        raise CalibrateError(str(exc)) from exc
    if folder and settings.target.marker_type != 'charuco':
        raise CalibrateError('parameter marker_type: a robot_cal_tools folder holds a ChArUco '
                             f'board, not a {settings.target.marker_type}; set charuco')

    # Progress only on a terminal: '\r' updates in a CI log make one line of kilobytes.
    live = not args.quiet and sys.stderr.isatty()

    def progress(i, n):
        if live:
            print(f'\r  {i}/{n} messages ({100.0 * i / max(n, 1):.0f} %)', end='',
                  file=sys.stderr, flush=True)

    def log(message):
        # Quiet means quiet, but for what was lost or skipped: that is never hidden.
        if not args.quiet or _is_loss(message):
            print(('\n' if live else '') + f'[armcal] {message}', file=sys.stderr)

    res = calibrate_bag(args.bag, settings, args.output, progress, log,
                        latency=not getattr(args, 'no_latency', False))
    if live:
        print('', file=sys.stderr)
    if args.quiet:
        return 0
    print(format_table(res.report))
    tgt = res.report.get('target')
    where = (settings.robot.base_frame if settings.target.eye_in_hand
             else settings.robot.marker_link)
    if tgt and tgt['T_link_target'] is not None and not settings.target.is_board:
        std = tgt['std'] or [float('nan')] * 3
        print(f'marker place in {where} (estimated), m: ' +
              ' '.join(f'{v:.5f}' for v in tgt['T_link_target'][:3]) + ' +/- ' +
              ' '.join(f'{v:.5f}' for v in std[:3]))
    elif tgt and tgt['T_link_target'] is not None:
        print(f'T_{where}_target (x y z qx qy qz qw): ' +
              ' '.join(f'{v:.5f}' for v in tgt['T_link_target']) +
              (' (estimated)' if tgt['estimated'] else ' (given)'))
    names = ', '.join(os.path.relpath(f, args.output) for f in res.files)
    print(f'wrote {names} to {args.output}')
    return 0
