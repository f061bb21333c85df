"""
The ``armcal`` node: background camera calibration on live topics.

Threads and why:

- the executor (a SingleThreadedExecutor in the main thread: rclpy's multi-threaded executor
  costs about twice the CPU per message) runs the subscription callbacks, which only append the
  message to a bounded :class:`EventQueue`, the timers (diagnostics, solve
  scheduling) and the services, which never wait: ``~/calibrate`` and ``~/reset`` hand their
  work to the front-end worker, in order with the inputs;
- one front-end worker thread owns the :class:`~armcal_ros.pipeline.SampleCollector` (not
  thread-safe): it pairs, decodes and detects, in arrival order, and adds samples to the engine;
- the engine's own solver thread runs each solve; its adjustments run in a child process
  (``solver_process``, :mod:`armcal_ros.solver_process`) while the thread waits on a pipe, so
  that a solve of seconds does not take the interpreter from the front end; its result
  callback publishes CameraInfo, poses, TF and markers, saves the files and commits to the
  camera drivers.

So a slow decode or a long solve never delays a callback, and a burst the worker cannot keep up
with costs images (counted in diagnostics), thinned evenly in time per camera so that every
dwell keeps some of its frames, never the joint states they need.

Interface (node ``armcal``; README, "The ROS 2 node"): subscribes to ``joint_states_topic`` (or,
with pose input, ``pose_topic`` carrying ``pose_type``) and ``image_topics`` (best effort);
publishes ``~/<camera>/camera_info`` and ``~/<camera>/pose``
(reliable, transient local), ``~/markers`` (RViz), ``/diagnostics`` (1 Hz) and ``~/samples``
(a PointStamped per stored sample, stamped with its dwell's median image time); serves
``~/calibrate``, ``~/reset`` and ``~/save`` (std_srvs/Trigger); calls each driver's
``SetCameraInfo`` service listed in ``set_camera_info_services``.

CameraInfo as a driver publishes it: once a camera is calibrated, one for every image of that
camera the node receives, with that image's header (stamp and frame_id, read from the serialized
bytes in the executor thread), so that exact-time synchronizers pair them; and, while no image
arrives, the latest one again every second, so that a subscriber without transient-local
durability still receives the calibration.  Every output names the optical frame the camera's
images carry (``<camera>_optical_frame`` until one has arrived).

Parameters are the table of :mod:`armcal_ros.params`, declared with descriptors and checked at
start-up (the node exits with the reason) and on every runtime set (refused with the reason).
Those that shape the subscriptions, the robot model or the front end are read-only; the noise
model, its hyperparameters, the solver's settings and the schedule may change while it runs and
take effect at the next solve.
"""

import collections
import dataclasses
import os
import signal
import sys
import tempfile
import threading
import time

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import (PointStamped, PoseStamped, PoseWithCovarianceStamped,
                               TransformStamped)
from rcl_interfaces.msg import (FloatingPointRange, IntegerRange, ParameterDescriptor,
                                ParameterType, SetParametersResult)
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import InvalidParameterTypeException, ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, JointState
from sensor_msgs.srv import SetCameraInfo
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from armcal_ros.compose import build_pipeline, engine_settings
from armcal_ros.frontend.collector import is_oversize
from armcal_ros.io.message_fields import camera_from_camera_info, pose_from_msg, stamp_ns
from armcal_ros.io.results_files import write_driver_camera_info
from armcal_ros.params import BY_NAME, check_value, NODE_NAME, PARAMS, resolve_paths
from armcal_ros.ros import conversions as conv
from armcal_ros.ros.event_queue import EventQueue
from armcal_ros.ros.memory import fix_allocator, release_free_memory
from armcal_ros.ros.raw_message import header_fields, LazyMessage
from armcal_ros.ros.status import diagnostic_statuses, NodeState
from armcal_ros.settings import (settings_from_values, with_given_intrinsics,
                                 with_solver_intrinsics)
from armcal_ros.solver_process import SolverProcess
from armcal_ros.stamp_latency import latency_differs, latency_report

#: Parameters that may change while the node runs (they apply from the next solve).
RUNTIME_PARAMETERS = frozenset([
    'noise_model', 'pixel_sigma', 'point_sigma', 'bias_sigma', 'coherence_length', 'kernel',
    'free_distortion', 'robust_loss', 'robust_loss_scale', 'outlier_gate_sigmas',
    'solve_period', 'min_samples', 'min_new_samples', 'publish_tf', 'set_camera_info_services',
])

_TYPES = {
    'string': ParameterType.PARAMETER_STRING, 'double': ParameterType.PARAMETER_DOUBLE,
    'int': ParameterType.PARAMETER_INTEGER, 'bool': ParameterType.PARAMETER_BOOL,
    'double[]': ParameterType.PARAMETER_DOUBLE_ARRAY,
    'string[]': ParameterType.PARAMETER_STRING_ARRAY,
}
_PTYPES = {
    'string': Parameter.Type.STRING, 'double': Parameter.Type.DOUBLE,
    'int': Parameter.Type.INTEGER, 'bool': Parameter.Type.BOOL,
    'double[]': Parameter.Type.DOUBLE_ARRAY, 'string[]': Parameter.Type.STRING_ARRAY,
}
#: Parameter names rclpy or the ROS tooling declare or accept on every node.
_FOREIGN_PARAMETERS = ('use_sim_time', 'start_type_description_service')

#: Queue bounds: ~10 s of joint states at 500 Hz; 60 images, ~1.3 s of three 15 Hz cameras
#: (about 18 MB of VGA mono8) - the front end's budget before it thins the queued images
#: (evenly in time per camera, so that a worker behind its input keeps frames of every dwell).
QUEUE_BOUNDS = {'joint': 5000, 'image': 60, 'control': None}
#: With no input at all for this long, pending frames are decided and the open dwell closed.
IDLE_FLUSH_S = 1.0
SOLVE_CHECK_PERIOD_S = 0.5
#: The worker takes its inputs in batches at most this often: waking it for each of 200 joint
#: states a second cost more CPU (thread switches, condition hand-offs) than the work itself,
#: and 20 ms is nothing against a dwell's latency (frames are decided ~0.1 s after arrival).
WORKER_BATCH_PERIOD_S = 0.02
BATCH_SIZE = 256
DIAGNOSTICS_PERIOD_S = 1.0
#: With no image of a camera for this long, its latest CameraInfo is published again once per
#: period (a driver publishes CameraInfo only with images; a volatile subscriber that comes
#: after the images stopped would otherwise never receive the calibration).
IDLE_CAMERA_INFO_S = 1.0
#: Shutdown: what is still queued is worked through for at most this long, then the open dwell
#: is closed and everything saved, so that the node is gone within 2 s of SIGINT or SIGTERM.
SHUTDOWN_DRAIN_S = 0.7
#: Seconds between estimates of each camera's stamp latency from the frames in motion, the
#: first as soon as there is a calibration (the worker thread; an estimate of the demo bag's
#: three cameras from all of their 730 frames in motion takes 0.24 s of CPU, and a latency
#: is a property of the driver: it does not drift).
LATENCY_PERIOD_S = 10.0


def _no_events(kind):
    """
    Event callbacks that create no QoS event handlers.

    rclpy's default gives every publisher and subscription handlers for incompatible-QoS (and
    type) events, and the Python executor rebuilds its wait set over all of them on every
    wake-up - with 200 Hz joint states and 45 images/s that bookkeeping was the largest single
    CPU cost of the node.  Our QoS cannot be incompatible: subscriptions ask the least
    (best effort, volatile) and the latched publishers offer the most (reliable, transient
    local), so the handlers could never fire.
    """
    return kind(use_default_callbacks=False)


class ParameterError(ValueError):
    """A parameter value the node refuses; the message names it and says why."""


def descriptor(p) -> ParameterDescriptor:
    """Return the ROS parameter descriptor of a :class:`~armcal_ros.params.Param`."""
    read_only = p.name not in RUNTIME_PARAMETERS
    text = p.description + (' (read-only: set it at start-up)' if read_only else
                            ' (may change at runtime; used from the next solve)')
    # An integer is a valid double, as in the parameter files the offline CLI reads
    # (`pixel_sigma: 1`, `marker_offset: [0, 0, 0.05]`): rclpy would refuse the type, so doubles
    # are declared with dynamic typing and params.check_value converts and checks them.
    d = ParameterDescriptor(name=p.name, type=_TYPES[p.type], description=text,
                            read_only=read_only,
                            dynamic_typing=p.type in ('double', 'double[]'))
    if p.type == 'double' and (p.minimum is not None or p.maximum is not None):
        lo = p.minimum if p.minimum is not None else -sys.float_info.max
        hi = p.maximum if p.maximum is not None else sys.float_info.max
        d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                     step=0.0)]
    if p.type == 'int' and (p.minimum is not None or p.maximum is not None):
        lo = int(p.minimum) if p.minimum is not None else -2 ** 63
        hi = int(p.maximum) if p.maximum is not None else 2 ** 63 - 1
        d.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
    return d


def _params_file_dirs(argv):
    """Directories of the ``--params-file`` arguments in ``argv`` (last first)."""
    out = []
    argv = list(argv or ())
    for i, a in enumerate(argv[:-1]):
        if a == '--params-file':
            out.append(os.path.dirname(os.path.abspath(argv[i + 1])))
    return out[::-1]


class CalibratorNode(Node):
    """The calibrator node; raises :class:`ParameterError` if its parameters are refused."""

    def __init__(self, argv=None, **node_kwargs):
        super().__init__(NODE_NAME, **node_kwargs)
        self._closing = False
        self._pub_lock = threading.Lock()
        self._solve_lock = threading.Lock()
        self.values, self.settings = self._declare_and_check(argv)
        v = self.values
        self.camera_names = list(self.settings.inputs.camera_names)
        # The frame the cameras' poses are given in: the arm's link when they ride on it.
        self.base_frame = (self.settings.robot.marker_link if self.settings.target.eye_in_hand
                           else self.settings.robot.base_frame)
        self.output_dir = self.settings.outputs.output_dir
        self._check_output_dir()
        try:
            pipe = build_pipeline(self.settings, log=self._log_input)
        except ValueError as exc:
            raise ParameterError(str(exc)) from exc
        self.chain, self.collector, self.engine = pipe.chain, pipe.collector, pipe.engine
        # Each camera's stamp latency, timed from the frames in motion (worker thread only).
        self.latency = pipe.latency
        self._latency_cal = None
        self._latency_due = 0.0
        self._latency_report = {}
        self._latency_said = {}
        self.engine.on_result(self._on_solve)
        self.engine.on_change(self._on_change)
        # Started by the first solve; it gives its heap's free pages back after each.
        self.solver = (SolverProcess(after_call=release_free_memory)
                       if self.settings.schedule.solver_process else None)
        if self.solver is not None:
            self.engine.run_solver = self.solver.call
        self.queue = EventQueue(QUEUE_BOUNDS, thinned=('image',))
        self._counts = {}
        self._per_camera = {}
        self._last_outcome_wall = None
        self._restored = ''
        self._markers_revision = -1
        self._last_estimated = None
        self._tf_pub = None
        self._tf_warned = False
        # Per camera: the header of its latest image (sec, nanosec, frame_id) and when it came
        # (monotonic), and the CameraInfo stamped afresh for each image (None: not calibrated).
        # Written by the executor thread only, but for _info_msg, which the solver replaces.
        self._last_header = {}
        self._last_image_wall = {}
        self._info_msg = {}
        self._drain_until = None
        self._n_published = 0
        self._raw_typical = {}
        self._callback_counts = collections.Counter()

        latched = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        quiet = {'event_callbacks': _no_events(PublisherEventCallbacks)}
        self.pub_info = {c: self.create_publisher(CameraInfo, f'~/{c}/camera_info', latched,
                                                  **quiet) for c in self.camera_names}
        self.pub_pose = {c: self.create_publisher(PoseWithCovarianceStamped, f'~/{c}/pose',
                                                  latched, **quiet) for c in self.camera_names}
        self.pub_image = {}
        if self.settings.outputs.republish_images:
            # Reliable: it matches reliable and best-effort subscribers alike.
            image_qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                                   reliability=ReliabilityPolicy.RELIABLE,
                                   durability=DurabilityPolicy.VOLATILE)
            for c, topic in zip(self.camera_names, v['image_topics']):
                compressed = topic.rstrip('/').endswith('/compressed')
                self.pub_image[c] = self.create_publisher(
                    CompressedImage if compressed else Image,
                    f'~/{c}/image_raw' + ('/compressed' if compressed else ''), image_qos, **quiet)
        self.pub_markers = self.create_publisher(MarkerArray, '~/markers', latched, **quiet)
        self.pub_diag = self.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self.pub_samples = self.create_publisher(PointStamped, '~/samples', 100)
        self._set_info_clients = {}
        self._make_set_info_clients(v['set_camera_info_services'])

        self.create_service(Trigger, '~/calibrate', self._srv_calibrate)
        self.create_service(Trigger, '~/reset', self._srv_reset)
        self.create_service(Trigger, '~/save', self._srv_save)

        # Best effort so that reliable and best-effort publishers both match (a reliable
        # subscription never connects to a best-effort publisher: no message, one warning).
        # Deep histories (2 s of images at 15 Hz, 5 s of joint states at 200 Hz) ride out a
        # process that is not scheduled for a while; best effort drops what overflows them.
        def sensor_qos(depth):
            return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                              reliability=ReliabilityPolicy.BEST_EFFORT,
                              durability=DurabilityPolicy.VOLATILE)
        quiet = {'event_callbacks': _no_events(SubscriptionEventCallbacks)}
        if v['pose_topic']:
            # Pose input: the marker link's measured pose replaces the joint states and the
            # robot model; poses travel in the joint states' queue (the arm's stream).
            ptype = PoseStamped if v['pose_type'] == 'pose_stamped' else TransformStamped
            self.create_subscription(ptype, v['pose_topic'], self._on_joint_state,
                                     sensor_qos(1000), **quiet)
            arm = f'{ptype.__name__} poses on {v["pose_topic"]}'
        else:
            self.create_subscription(JointState, v['joint_states_topic'],
                                     self._on_joint_state, sensor_qos(1000), **quiet)
            arm = f'joint states on {v["joint_states_topic"]}'
        for cam, topic in zip(self.camera_names, v['image_topics']):
            mtype = CompressedImage if topic.rstrip('/').endswith('/compressed') else Image
            # raw: kept serialized until the front end wants the pixels (raw_message.py).
            self.create_subscription(mtype, topic, self._image_callback(cam, mtype),
                                     sensor_qos(30), raw=True, **quiet)
            self.get_logger().info(f'{cam}: {mtype.__name__} on {topic}')
        # Given intrinsics without a file: the driver's CameraInfo (its first calibrated
        # message); until it arrives the camera's images are collected but it is not solved.
        self._info_intrinsics = {}
        self._info_pending = dict(self.settings.intrinsics.topics)
        for cam, topic in self.settings.intrinsics.topics:
            self.create_subscription(CameraInfo, topic, self._camera_info_callback(cam),
                                     sensor_qos(5), **quiet)
            self.get_logger().info(f'{cam}: intrinsics from CameraInfo on {topic}')

        if v['resume']:
            self._resume()
        self._worker = threading.Thread(target=self._work, name='armcal-frontend', daemon=True)
        self._worker.start()
        self.create_timer(SOLVE_CHECK_PERIOD_S, self._maybe_solve)
        self.create_timer(DIAGNOSTICS_PERIOD_S, self._publish_diagnostics)
        self.create_timer(IDLE_CAMERA_INFO_S, self._republish_idle_camera_info)
        self.add_on_set_parameters_callback(self._check_runtime_parameters)
        self.add_post_set_parameters_callback(self._apply_runtime_parameters)
        self.get_logger().info(
            f'calibrating {self.camera_names} ({v["noise_model"]} model) with {arm}; '
            f'{v["marker_type"]} on {v["marker_link"]}; output in {self.output_dir}')

    def _check_output_dir(self):
        """Refuse to start when output_dir cannot hold the samples (they must survive)."""
        d = self.output_dir
        try:
            if os.path.exists(d) and not os.path.isdir(d):
                raise OSError('it exists and is not a directory')
            os.makedirs(d, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=d, prefix='.armcal-write-test-'):
                pass
        except OSError as exc:
            raise ParameterError(f'parameter output_dir: {d} cannot hold the samples and the '
                                 f'calibration: {exc.strerror or exc}') from None

    # -- parameters ----------------------------------------------------------------------
    def _declare_and_check(self, argv):
        errors, values = [], {}
        for p in PARAMS:
            try:
                if isinstance(p.default, list) and not p.default:
                    # An empty list cannot tell rclpy its element type: declare by type, or
                    # without one for a dynamically typed double[] (rclpy allows no type then).
                    d = descriptor(p)
                    param = self.declare_parameter(
                        p.name, None if d.dynamic_typing else _PTYPES[p.type], d)
                else:
                    param = self.declare_parameter(p.name, p.default, descriptor(p))
                value = param.value
            except InvalidParameterTypeException as exc:
                errors.append(f'parameter {p.name}: expected {p.type} ({exc})')
                continue
            except ParameterException as exc:
                errors.append(f'parameter {p.name}: {exc}')
                continue
            if value is None:
                # rcl reads an empty list in a parameter file (`free_distortion: []`) as a
                # parameter without a type, and rclpy then returns None: the user asked for an
                # empty list, which is not the default.  A list parameter declared by type
                # without an override is None as well, and its default is empty.  Initialise it
                # (so that `ros2 param get` works); runtime checks are not registered yet.
                value = []
                self.set_parameters([Parameter(p.name, _PTYPES[p.type], value)])
            try:
                values[p.name] = check_value(p.name, value)
            except ValueError as exc:
                errors.append(str(exc))
        overrides = getattr(self, '_parameter_overrides', {}) or {}
        unknown = sorted(k for k in overrides if k not in BY_NAME
                         and k not in _FOREIGN_PARAMETERS and not k.startswith('qos_overrides.'))
        if unknown:
            errors.append(f'unknown parameter(s) {unknown} (misspelt? see the parameter table '
                          f'in the README or `ros2 param describe`)')
        if errors:
            raise ParameterError('; '.join(errors))
        # Relative file names: beside a --params-file that has them, else the working directory.
        resolve_paths(values, _params_file_dirs(argv) + [os.getcwd()])
        try:
            return values, settings_from_values(values, node_name=self.get_name())
        except ValueError as exc:
            raise ParameterError(str(exc)) from exc

    def _check_runtime_parameters(self, params):
        new = dict(self.values)
        for p in params:
            if p.name in _FOREIGN_PARAMETERS:
                continue
            if p.name not in BY_NAME:
                return SetParametersResult(successful=False,
                                           reason=f'unknown parameter {p.name!r}')
            if p.name not in RUNTIME_PARAMETERS:
                return SetParametersResult(
                    successful=False, reason=f'parameter {p.name} is read-only: it shapes the '
                    f'subscriptions, robot model or front end; restart the node to change it')
            try:
                new[p.name] = check_value(p.name, p.value)
            except ValueError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
        try:
            self._engine_settings(new)
        except ValueError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _engine_settings(self, values):
        """Return the engine's settings under new parameter values (same target, cameras)."""
        settings = with_given_intrinsics(settings_from_values(values, node_name=self.get_name()),
                                         self._info_intrinsics)
        return engine_settings(settings, self.engine.settings.board)

    def _camera_info_callback(self, camera):
        def callback(msg):
            if camera not in self._info_pending:
                return
            try:
                info = camera_from_camera_info(msg, camera)
                given = self.settings.intrinsics.prior_from(camera, info)
            except ValueError as exc:
                self._log_input(f'{camera}: CameraInfo not usable as given intrinsics: {exc}')
                return
            topic = self._info_pending.pop(camera)
            self._info_intrinsics[camera] = given
            self.engine.settings = dataclasses.replace(
                self.engine.settings, solver=with_solver_intrinsics(self.engine.settings.solver,
                                                                    {camera: given}))
            self.get_logger().info(f'{camera}: intrinsics given by CameraInfo on {topic} '
                                   f'({given.mode}: fx {info.fx:.2f}, fy {info.fy:.2f}, '
                                   f'cx {info.cx:.2f}, cy {info.cy:.2f})')
        return callback

    def _apply_runtime_parameters(self, params):
        changed = [p for p in params if p.name in BY_NAME]
        if not changed:
            return
        new = dict(self.values)
        for p in changed:
            new[p.name] = check_value(p.name, p.value)
        self.engine.settings = self._engine_settings(new)
        if new['set_camera_info_services'] != self.values['set_camera_info_services']:
            self._make_set_info_clients(new['set_camera_info_services'])
        self.values = new
        self.get_logger().info('parameters changed (used from the next solve; call ~/calibrate '
                               'to solve now): ' + ', '.join(f'{p.name}={p.value!r}'
                                                             for p in changed))

    # -- inputs (executor threads: append only) ------------------------------------------
    def _on_joint_state(self, msg):
        self.queue.put('joint', msg)

    def _image_callback(self, camera, msg_type):
        def callback(raw):
            typical = self._raw_typical.setdefault(camera, max(len(raw), 1))
            if is_oversize(len(raw), typical):
                # Not one of this camera's frames; never queued (sixty of them would hold
                # gigabytes), counted, said once in 10 s.
                self._callback_counts['image_oversize'] += 1
                self.get_logger().warning(
                    f'{camera}: message of {len(raw) / 1e6:.1f} MB, its images are about '
                    f'{typical / 1e6:.2f} MB: skipped', throttle_duration_sec=10.0)
                return
            try:
                sec, nanosec, frame = header_fields(raw)
            except ValueError:
                # The front end counts and logs it when it reads the stamp; without a stamp
                # it is not thinned among its camera's frames.
                self.queue.put('image', (camera, LazyMessage(raw, msg_type)))
                return
            self.queue.put('image', (camera, LazyMessage(raw, msg_type)), key=camera,
                           stamp=sec * 1_000_000_000 + nanosec)
            self._image_arrived(camera, sec, nanosec, frame, raw)
        return callback

    def _image_arrived(self, camera, sec, nanosec, frame, raw):
        """Follow the image's frame, publish its CameraInfo (and the image); executor thread."""
        if frame and frame != self.engine.frame_ids.get(camera):
            self._frame_seen(camera, frame)
        frame = self.engine.frame_id(camera)
        self._last_header[camera] = (sec, nanosec, frame)
        self._last_image_wall[camera] = time.monotonic()
        info = self._info_msg.get(camera)
        if info is not None:
            info.header.stamp.sec, info.header.stamp.nanosec = sec, nanosec
            info.header.frame_id = frame
            self._publish(self.pub_info[camera], info)
        pub = self.pub_image.get(camera)
        if pub is not None:
            self._publish(pub, raw)

    def _frame_seen(self, camera, frame):
        """Use from now on the frame a camera's images name (the outputs did not use it yet)."""
        before = self.engine.frame_ids.get(camera)
        self.engine.frame_ids[camera] = frame
        if before is None:
            self.get_logger().info(f'{camera}: images in frame {frame!r}: CameraInfo, TF and '
                                   f'extrinsics.yaml name it')
        else:
            self.get_logger().warning(f'{camera}: images now in frame {frame!r} (were in '
                                      f'{before!r}): the outputs follow')
        cal = self.engine.published or self.engine.current
        if cal is not None:
            self._publish_tf(cal, self.get_clock().now().to_msg())

    def _log_input(self, message):
        self.get_logger().warning(message)

    # -- front-end worker ----------------------------------------------------------------
    def _work(self):
        last_input = time.monotonic()
        flushed = True
        while True:
            batch = self.queue.get_batch(timeout=0.2, max_items=BATCH_SIZE)
            if self._drain_until is not None and (not batch or
                                                  time.monotonic() > self._drain_until):
                # Shutting down: the open dwell becomes a sample if it can, so it is saved.
                self._store(self._guard(self.collector.flush))
                self._snapshot()
                return
            if not batch:
                if not flushed and time.monotonic() - last_input > IDLE_FLUSH_S:
                    self._store(self._guard(self.collector.flush))
                    flushed = True
                    self._snapshot()
                continue
            for kind, item in batch:
                if self._drain_until is not None and time.monotonic() > self._drain_until:
                    break       # shutting down: what is left is not worth the wait
                if kind == 'control':
                    self._guard(item)
                    continue
                last_input = time.monotonic()
                flushed = False
                if kind == 'joint' and self.collector.pose_input:
                    samples = self._guard(self._add_pose, item)
                elif kind == 'joint':
                    stamp = stamp_ns(item.header.stamp)
                    samples = self._guard(self.collector.add_joint_state,
                                          stamp, item.name, item.position)
                    if self.latency is not None:
                        self._guard(self.latency.add_joint_state, stamp, item.name,
                                    item.position)
                else:
                    samples = self._guard(self._add_image, *item)
                self._store(samples)
            for cam, (w, h) in list(self.collector.image_sizes.items()):
                # A camera still waiting for its CameraInfo stays out of the solves.
                if cam not in self._info_pending and self.engine.image_sizes.get(cam) != (w, h):
                    self.engine.set_image_size(cam, w, h)
            self._snapshot()
            self._guard(self._time_stamps)
            if len(batch) < BATCH_SIZE:
                time.sleep(WORKER_BATCH_PERIOD_S)

    def _add_pose(self, msg):
        return self.collector.add_pose(stamp_ns(msg.header.stamp), *pose_from_msg(msg))

    def _add_image(self, camera, msg: LazyMessage):
        try:
            stamp = msg.stamp_ns()
        except ValueError as exc:
            self.collector.counts['image_malformed'] += 1
            self.collector.log('image_malformed', f'{camera}: malformed image message '
                               f'(skipped): {exc}')
            return []
        if self.latency is not None:
            self._guard(self.latency.add_image, camera, stamp, msg)
        return self.collector.add_image(camera, stamp, msg)

    def _time_stamps(self):
        """
        Keep the stamp-latency timer on the current calibration; estimate now and then (worker).

        A latency that differs from the one given (``image_stamp_latency``) as much as the
        offline job would pair again with (stamp_latency.latency_differs) is said in the log,
        once per camera until it agrees again.
        """
        if self.latency is None:
            return
        cal = self.engine.current
        if cal is None:
            return
        if cal is not self._latency_cal:
            self._latency_cal = cal
            self.latency.set_cameras({n: c.camera for n, c in cal.cameras.items()})
        now = time.monotonic()
        if now < self._latency_due:
            return
        self._latency_due = now + LATENCY_PERIOD_S
        T = self.engine.T_link_target
        estimates = self.latency.estimate(cal, None if T is None else np.asarray(T)[:3, 3])
        given = dict(self.settings.front_end.image_stamp_latency)
        self._latency_report = latency_report(estimates, given)
        for cam, e in estimates.items():
            off = latency_differs(e, given.get(cam, 0.0))
            if off and not self._latency_said.get(cam):
                self.get_logger().warning(
                    f'{cam}: its images are stamped {1e3 * e.latency_s:.1f} +- '
                    f'{1e3 * e.std_s:.1f} ms after their exposure (timed from {e.frames} '
                    f'frames in motion); image_stamp_latency gives '
                    f'{1e3 * given.get(cam, 0.0):.1f} ms: set it to pair the frames at their '
                    f'exposure')
            self._latency_said[cam] = off

    def _guard(self, fn, *args):
        """Run ``fn``; a failure costs the input (counted and logged), never the worker."""
        try:
            return fn(*args)
        except Exception as exc:  # noqa: B902 - the worker must survive any bad input
            self.collector.counts['worker_error'] += 1
            self.collector.log('worker_error', f'front end error (input skipped): '
                               f'{type(exc).__name__}: {exc}')
            return []

    def _store(self, samples):
        for s in samples or ():
            result = self.engine.add_sample(s)
            self.collector.counts[f'sample_{result.value}'] += 1
            if result.value != 'dropped':
                self._publish(self.pub_samples, conv.point_stamped_msg(
                    s.point_nominal, self.settings.robot.base_frame,
                    conv.time_msg(s.stamp_ns)))
        if samples:
            self._count_per_camera()

    def _count_per_camera(self):
        counts = {c: 0 for c in self.camera_names}
        for s in self.engine.store.samples:
            for c in s.observations:
                if c in counts:
                    counts[c] += 1
        self._per_camera = counts

    def _snapshot(self):
        self._counts = dict(self.collector.counts)

    # -- solving -------------------------------------------------------------------------
    def _maybe_solve(self):
        if not self._solve_lock.acquire(blocking=False):
            return
        try:
            self.engine.maybe_solve_async()
        finally:
            self._solve_lock.release()

    def _on_solve(self, outcome):
        """Engine callback (solver or service thread): log, save, publish, commit."""
        if self._closing:
            return
        try:
            self._handle_outcome(outcome)
        except Exception as exc:  # noqa: B902 - publishing must not kill the solver thread
            if not self._closing:
                self.get_logger().error(f'cannot publish the calibration: '
                                        f'{type(exc).__name__}: {exc}')
        # A solve frees tens of MB of blocks; without this the heap's free pages stay resident
        # and the process grows for hours (see armcal_ros/ros/memory.py).
        release_free_memory()

    def _on_change(self, record):
        """Engine callback (the worker thread): say it, withdraw a changed camera's calibration."""
        try:
            start = self.engine.store.first_stamp_ns()
            if record.kind == 'disagreement':
                # It may repeat for as long as bad detections last: once per 10 s.
                self.get_logger().warning(record.summary(start), throttle_duration_sec=10.0)
                return
            self.get_logger().warning(record.summary(start))
            if record.camera is not None and record.camera in self.engine.withheld():
                # An uncalibrated CameraInfo (K all zero) is how a driver says it has no
                # calibration: consumers stop using the old one until the camera is re-solved.
                cam = record.camera
                w, h = self.engine.image_sizes.get(cam, (0, 0))

                def uncalibrated():
                    return conv.uncalibrated_camera_info_msg(
                        cam, w, h, self._header_stamp(cam), self.engine.frame_id(cam))
                self._publish(self.pub_info[cam], uncalibrated())
                self._info_msg[cam] = uncalibrated()
            self._publish_diagnostics()
        except Exception as exc:  # noqa: B902 - reporting must not kill the worker thread
            if not self._closing:
                self.get_logger().error(f'cannot report a change: {type(exc).__name__}: {exc}')

    def _handle_outcome(self, outcome):
        self._last_outcome_wall = time.time()
        if not outcome.accepted:
            self.get_logger().warning(f'solve on {outcome.n_samples} samples not accepted: '
                                      f'{outcome.reason}')
            return
        cal = outcome.calibration
        adj = outcome.result.adjustment if outcome.result is not None else None
        self._last_estimated = None if adj is None else np.array(adj.points)
        self.get_logger().info(
            f'calibration accepted: {cal.model} model, {outcome.n_samples} samples, cost '
            f'{cal.cost:.4g}, {outcome.time_s:.1f} s; RMS '
            + ', '.join(f'{n} {c.rms_px:.3f} px' for n, c in cal.cameras.items()))
        # Files first: a consumer woken by the new CameraInfo finds them written.  Cameras
        # withheld after a change are left out until they are recalibrated.
        self._save('after a solve')
        cal = self.engine.published or cal
        self._write_driver_files(cal)
        self._publish_calibration(cal)
        self._commit_to_drivers(cal)

    def _publish(self, pub, msg):
        with self._pub_lock:
            if not self._closing:
                pub.publish(msg)

    def _header_stamp(self, camera):
        """Return the stamp of the camera's latest image, or now when none has arrived."""
        last = self._last_header.get(camera)
        if last is None:
            return self.get_clock().now().to_msg()
        return conv.time_msg(last[0] * 1_000_000_000 + last[1])

    def _publish_calibration(self, cal):
        now = self.get_clock().now().to_msg()
        for name in self.camera_names:
            c = cal.cameras.get(name)
            if c is None:
                continue
            frame = self.engine.frame_id(name)
            # Stamped like the latest image, so a synchronizer pairs it even before the next.
            self._publish(self.pub_info[name], conv.camera_info_msg(
                c.camera, self._header_stamp(name), frame))
            self._info_msg[name] = conv.camera_info_msg(c.camera, self._header_stamp(name),
                                                        frame)
            self._publish(self.pub_pose[name], conv.pose_msg(c.camera, c.pose_covariance,
                                                             self.base_frame, now))
        self._publish_tf(cal, now)
        self._publish_markers(force=True)
        self._n_published += 1

    def _republish_idle_camera_info(self):
        """Publish again the latest CameraInfo of each camera whose images stopped (timer)."""
        now = time.monotonic()
        for cam, info in list(self._info_msg.items()):
            if now - self._last_image_wall.get(cam, -np.inf) > IDLE_CAMERA_INFO_S:
                info.header.stamp = self._header_stamp(cam)
                info.header.frame_id = self.engine.frame_id(cam)
                self._publish(self.pub_info[cam], info)

    def _publish_tf(self, cal, stamp):
        """
        Publish T_base_camera of every calibrated camera on /tf_static (tf2_msgs/TFMessage).

        As tf2_ros' StaticTransformBroadcaster does (reliable, transient local, depth 1, the
        whole set in one message), without needing tf2_ros: only the message package.  The set
        is rebuilt each time, so a camera's frame that changed leaves no stale child behind.
        """
        cams = [(cal.cameras[c].camera, self.engine.frame_id(c)) for c in self.camera_names
                if c in cal.cameras]
        if not self.values['publish_tf'] or not cams:
            return
        if self._tf_pub is None:
            try:
                from tf2_msgs.msg import TFMessage
            except ImportError:
                if not self._tf_warned:
                    self._tf_warned = True
                    self.get_logger().warning(
                        'tf2_msgs is not importable here: static TF base_frame -> optical '
                        'frames is not published; the poses are on ~/<camera>/pose and in '
                        'extrinsics.yaml (README, "Using the calibration": TF)')
                return
            qos = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                             reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
            self._tf_pub = (TFMessage, self.create_publisher(
                TFMessage, '/tf_static', qos,
                event_callbacks=_no_events(PublisherEventCallbacks)))
        msg_type, pub = self._tf_pub
        self._publish(pub, msg_type(transforms=[
            conv.transform_msg(c, self.base_frame, stamp, frame) for c, frame in cams]))

    def _write_driver_files(self, cal):
        """Write each calibrated camera's YAML where camera_info_manager looks by default."""
        out = self.settings.outputs
        if out.camera_info_dir is None:
            return
        names = dict(out.camera_info_names)
        for cam, c in cal.cameras.items():
            if cam not in names:
                continue
            try:
                path, kept = write_driver_camera_info(out.camera_info_dir, c.camera, names[cam])
            except OSError as exc:
                self.get_logger().error(f'{cam}: cannot write the driver\'s calibration file '
                                        f'in {out.camera_info_dir}: {exc}',
                                        throttle_duration_sec=60.0)
                continue
            if kept:
                self.get_logger().warning(f'{cam}: {path} held a calibration armcal did not '
                                          f'write: kept as {kept}')

    def _publish_markers(self, force=False):
        rev = self.engine.store.revision
        if not force and rev == self._markers_revision:
            return
        self._markers_revision = rev
        cal = self.engine.current
        cams = [] if cal is None else [cal.cameras[c].camera for c in self.camera_names
                                       if c in cal.cameras]
        if self.settings.target.eye_in_hand:
            # The cameras are in the moving link's frame; the samples in the base: draw only
            # the cameras (RViz places them with the link through TF).
            pts = np.zeros((0, 3))
        else:
            pts = np.array([s.point_nominal for s in self.engine.store.samples]).reshape(-1, 3)
        self._publish(self.pub_markers, conv.marker_array_msg(
            self.base_frame, self.get_clock().now().to_msg(), pts, cams, self._last_estimated))

    def _save(self, why):
        try:
            files = self.engine.save(self.output_dir)
        except (OSError, ValueError) as exc:
            self.get_logger().error(f'cannot save to {self.output_dir} ({why}): {exc}')
            return None
        return files

    def _resume(self):
        try:
            said = self.engine.load(self.output_dir)
        except (OSError, ValueError) as exc:
            self.get_logger().error(f'cannot resume from {self.output_dir}: {exc}; starting '
                                    f'without the saved samples and calibration')
            return
        self._restored = said
        # The restored cameras' image sizes hold until the calibrator is restarted fresh: a
        # frame of another size is refused (counted), not taken as the camera's new size.
        self.collector.image_sizes.update(self.engine.image_sizes)
        self.get_logger().info(f'{said} from {self.output_dir}')
        self._count_per_camera()
        cal = self.engine.current
        if cal is not None:
            self._publish_calibration(cal)

    # -- camera drivers (SetCameraInfo) --------------------------------------------------
    def _make_set_info_clients(self, services):
        for client in self._set_info_clients.values():
            self.destroy_client(client)
        self._set_info_clients = {
            cam: self.create_client(SetCameraInfo, srv)
            for cam, srv in zip(self.camera_names, services)}

    def _commit_to_drivers(self, cal):
        for cam, client in list(self._set_info_clients.items()):
            c = cal.cameras.get(cam)
            if c is None:
                continue
            if not client.service_is_ready():
                self.get_logger().warning(f'{cam}: {client.srv_name} is not available; the '
                                          f'calibration was not committed to the driver')
                continue
            req = SetCameraInfo.Request()
            req.camera_info = conv.camera_info_msg(c.camera, self.get_clock().now().to_msg())
            future = client.call_async(req)
            future.add_done_callback(self._commit_answer(cam, client.srv_name))

    def _commit_answer(self, cam, srv):
        def done(future):
            try:
                res = future.result()
            except Exception as exc:  # noqa: B902 - any failure of the call is reported
                self.get_logger().error(f'{cam}: {srv} failed: {exc}')
                return
            if res.success:
                self.get_logger().info(f'{cam}: driver accepted the calibration via {srv}: '
                                       f'{res.status_message!r}')
            else:
                self.get_logger().error(f'{cam}: driver refused the calibration via {srv}: '
                                        f'{res.status_message!r}')
        return done

    # -- services (never block the executor: the work goes to the worker or solver) --------
    def _srv_calibrate(self, request, response):
        n = len(self.engine.store)
        if self.engine.solving:
            response.success = False
            response.message = ('a solve is running already; its result will be published '
                                'when it ends (call again to solve once more)')
            return response
        self.queue.put('control', self._flush_and_solve)
        response.success = True
        response.message = (f'solving on {n} samples and the open dwell; the result is '
                            f'published on ~/<camera>/camera_info, ~/<camera>/pose and '
                            f'/diagnostics')
        return response

    def _flush_and_solve(self):
        """Worker job: close the open dwell, then start a forced background solve."""
        self._store(self.collector.flush())
        with self._solve_lock:
            if not self.engine.maybe_solve_async(force=True):
                self.get_logger().warning('~/calibrate: a solve was running already')

    def _srv_reset(self, request, response):
        n = len(self.engine.store)
        self.queue.put('control', self._reset)
        response.success = True
        response.message = (f'forgetting {n} samples; the current calibration stays published '
                            f'until a new solve replaces it')
        return response

    def _reset(self):
        """Worker job: forget the samples and the front end's state, in order with inputs."""
        n = len(self.engine.store)
        self.collector.reset()
        self.engine.reset()
        self._count_per_camera()
        self._save('after a reset')
        self._publish_markers(force=True)
        self.get_logger().info(f'reset: forgot {n} samples')

    def _srv_save(self, request, response):
        files = self._save('on request')
        response.success = files is not None
        response.message = (f'wrote {", ".join(os.path.basename(f) for f in files)} to '
                            f'{self.output_dir}' if files is not None else
                            f'cannot write to {self.output_dir} (see the log)')
        return response

    # -- diagnostics ---------------------------------------------------------------------
    def _solver_where(self):
        if self.solver is None:
            return 'in the node (solver_process false)'
        pid = self.solver.pid
        return 'child process (starts with the first solve)' if pid is None else \
            f'child process {pid}'

    def node_state(self) -> NodeState:
        """Return a snapshot of what the diagnostics report."""
        e = self.engine
        return NodeState(
            camera_names=self.camera_names, n_samples=len(e.store),
            min_samples=e.settings.min_samples, samples_per_camera=dict(self._per_camera),
            image_sizes=dict(e.image_sizes), solving=e.solving, n_solves=e.n_solves,
            n_rejected=e.n_rejected, calibration=e.current, last_outcome=e.last_outcome,
            last_outcome_wall=self._last_outcome_wall,
            input_counts=dict(collections.Counter(self._counts) + self._callback_counts),
            queue_dropped=dict(self.queue.dropped), queue_depth=self.queue.depth(),
            restored=self._restored, changes=list(e.changes.records),
            withheld=e.withheld(), start_ns=self.engine.store.first_stamp_ns(),
            recalibration_samples=e.settings.recalibration_samples,
            n_published=self._n_published, frame_ids=dict(e.frame_ids),
            missing_joints=tuple(sorted(self.collector.missing_joints)),
            seen_joint_names=self.collector.seen_joint_names,
            light_pooling={k: f'{p.status}: {p.message}' for k, p in e.light_pooling.items()},
            solver=self._solver_where(),
            solver_starts=0 if self.solver is None else self.solver.starts,
            stamp_latency=dict(self._latency_report))

    def _publish_diagnostics(self):
        stamp = self.get_clock().now().to_msg()
        self._publish(self.pub_diag, conv.diagnostic_array_msg(
            diagnostic_statuses(self.node_state(), self.get_name()), stamp))
        self._publish_markers()

    # -- shutdown ------------------------------------------------------------------------
    def close(self, solve_timeout=0.5):
        """
        Stop the worker, save the samples; call before destroy_node().

        Bounded so that the process is gone within 2 s: the front end works through its queue
        for at most :data:`SHUTDOWN_DRAIN_S`, closes the open dwell and stops; a running solve
        gets ``solve_timeout`` to finish, after which its result is discarded (its samples are
        saved, and the next start solves them again).
        """
        self.get_logger().info('shutting down: stopping the front end'
                               + (', a solve is running' if self.engine.solving else ''))
        self._drain_until = time.monotonic() + SHUTDOWN_DRAIN_S
        self.queue.close()
        self._worker.join(timeout=SHUTDOWN_DRAIN_S + 0.5)
        if self._worker.is_alive():
            self.get_logger().warning(f'the front-end worker did not stop within '
                                      f'{SHUTDOWN_DRAIN_S + 0.5:.1f} s')
        if not self.engine.wait(solve_timeout):
            self.get_logger().warning('a solve is still running at shutdown; its result is '
                                      'discarded (the samples are saved)')
        with self._pub_lock:
            self._closing = True
        if self.solver is not None:
            self.solver.close()
        if self._save('at shutdown') is not None:
            self.get_logger().info(f'saved {len(self.engine.store)} samples to '
                                   f'{self.output_dir}')


def _interrupt(signum, frame):
    raise KeyboardInterrupt(f'signal {signum}')


def main(args=None):
    """
    Entry point of ``calibrator_node``; returns the exit status (2 for refused parameters).

    SIGINT and SIGTERM end the spin in the main thread while the context is still valid, so
    that the node can stop its threads, save and log before rclpy shuts down (a thread still
    spinning at ``rclpy.shutdown()`` aborts the process, so threads are joined first).  Both
    handlers are installed explicitly: a process started in the background by a shell inherits
    SIGINT ignored, and Python then installs no KeyboardInterrupt handler of its own.
    """
    argv = sys.argv if args is None else args
    fix_allocator()       # before DDS starts its threads (armcal_ros/ros/memory.py)
    rclpy.init(args=argv, signal_handler_options=SignalHandlerOptions.NO)
    signal.signal(signal.SIGINT, _interrupt)
    signal.signal(signal.SIGTERM, _interrupt)
    try:
        node = CalibratorNode(argv=argv)
    except ParameterError as exc:
        print(f'[armcal] refusing to start: {exc}', file=sys.stderr, flush=True)
        rclpy.try_shutdown()
        return 2
    executor = SingleThreadedExecutor()
    executor.add_node(node)
    try:
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.close()
        # Bounded: a KeyboardInterrupt raised while a callback's task was suspended can leave
        # rclpy's count of executing work above zero, and shutdown() without a timeout then
        # waits forever (a node killed after 30 s of silence on SIGINT was seen once).
        if not executor.shutdown(timeout_sec=5.0):
            node.get_logger().warning('executor: callbacks still running after 5 s; exiting')
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
