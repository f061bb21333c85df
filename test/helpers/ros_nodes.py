"""
The node on real rclpy and DDS: its processes, the test's own client, bounded waits.

Imports rclpy: import this module only from tests that ran ``pytest.importorskip('rclpy')`` (the
``ros_env`` and ``client`` fixtures of conftest.py do).  Every process runs in the module's own
ROS_DOMAIN_ID (:func:`isolated_ros_env`) with discovery kept on localhost, every wait is bounded
(:func:`wait_until`, :meth:`Proc.stop`), and the callers kill every process in teardown.
"""

import os
import signal
import subprocess
import sys
import threading
import time
import zlib

import numpy as np
import rclpy
from rcl_interfaces.srv import SetParameters
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from std_srvs.srv import Trigger

from armcal_ros.ros import conversions as conv
from helpers.params_files import ROOT

KEYS = ('ROS_DOMAIN_ID', 'ROS_LOG_DIR', 'ROS_AUTOMATIC_DISCOVERY_RANGE', 'ROS_HOME')
DOMAINS = 200
LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                     durability=DurabilityPolicy.TRANSIENT_LOCAL)

_domains = {}


def domain_id(module_name):
    """
    Return the ROS_DOMAIN_ID (1-200) of test module ``module_name`` in this run.

    Derived from the pid, so concurrent test runs on one machine do not see each other's nodes,
    plus a CRC of the module's name; should two modules of one run land on the same id, the later
    one takes the next free id, so no two modules of a run ever share a domain.
    """
    if module_name not in _domains:
        domain = 1 + (os.getpid() + zlib.crc32(module_name.encode())) % DOMAINS
        while domain in _domains.values():
            domain = 1 + domain % DOMAINS
        _domains[module_name] = domain
    return _domains[module_name]


def isolated_ros_env(tmp_path_factory, module_name):
    """
    Set the variables for this process (and its children), yield the environment, restore.

    The module's own domain (:func:`domain_id`), a fresh log and ROS_HOME directory, localhost
    discovery.
    """
    saved = {k: os.environ.get(k) for k in KEYS}
    os.environ['ROS_DOMAIN_ID'] = str(domain_id(module_name))
    os.environ['ROS_LOG_DIR'] = str(tmp_path_factory.mktemp('ros_log'))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    # The node's default places ($ROS_HOME/armcal, $ROS_HOME/camera_info) inside the test's
    # own directory, never the user's ~/.ros.
    os.environ['ROS_HOME'] = str(tmp_path_factory.mktemp('ros_home'))
    yield dict(os.environ, PYTHONUNBUFFERED='1')
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


def wait_until(pred, timeout, what, context=None):
    """
    Poll ``pred`` until true; fail naming ``what`` after ``timeout`` seconds.

    ``context()``, when given, adds what explains a time-out to the failure (e.g. a node's log).
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = pred()
        if value:
            return value
        time.sleep(0.05)
    extra = '' if context is None else '\n' + str(context())
    raise AssertionError(f'timed out after {timeout} s waiting for {what}{extra}')


class Proc:
    """A subprocess with its output in a file; stopped with SIGINT, killed if it hangs."""

    def __init__(self, args, env, log_path, ignore_sigint=False):
        self.log_path = log_path
        self._log = open(log_path, 'w')
        # ignore_sigint: started as a shell starts a background job (`node &` in a script),
        # with SIGINT ignored, which the child inherits.
        self.p = subprocess.Popen(
            args, env=env, cwd=ROOT, stdout=self._log, stderr=subprocess.STDOUT,
            preexec_fn=(lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if ignore_sigint
            else None)

    def alive(self):
        return self.p.poll() is None

    def log(self):
        with open(self.log_path) as f:
            return f.read()

    def stop(self, timeout=30.0):
        if self.alive():
            self.p.send_signal(signal.SIGINT)
            try:
                self.p.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()
        self._log.close()
        return self.p.returncode

    def kill(self):
        if self.alive():
            self.p.kill()
            self.p.wait(10)


class Client:
    """The test's own rclpy node, spun in a background thread."""

    def __init__(self):
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = rclpy.create_node('armcal_test_client', context=self.ctx)
        self.executor = MultiThreadedExecutor(num_threads=2, context=self.ctx)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _spin(self):
        # Destroying a subscription or client from the test thread while the executor builds
        # its wait set can raise InvalidHandle in the executor thread (an rclpy race), which
        # would end a plain spin() and time out every later call.  Keep spinning.
        while not self._stop.is_set() and self.ctx.ok():
            try:
                self.executor.spin_once(timeout_sec=0.1)
            except _rclpy.InvalidHandle:
                continue
            except ExternalShutdownException:
                return

    def record(self, mtype, topic, qos=LATCHED):
        """Subscribe; return the list every (receive time, message) is appended to."""
        got = []
        sub = self.node.create_subscription(mtype, topic,
                                            lambda m: got.append((time.monotonic(), m)), qos)
        return got, sub

    def record_headers(self, mtype, topic, qos):
        """
        Subscribe serialized; return the list every (sec, nanosec, frame_id) is appended to.

        For image topics: only the header is read from the bytes, so the test process does
        not deserialize every frame.
        """
        from armcal_ros.ros.raw_message import header_fields
        got = []
        sub = self.node.create_subscription(mtype, topic,
                                            lambda raw: got.append(header_fields(raw)), qos,
                                            raw=True)
        return got, sub

    def call(self, srv_type, name, request, timeout=60.0):
        cli = self.node.create_client(srv_type, name)
        try:
            assert cli.wait_for_service(timeout_sec=15.0), f'service {name} not available'
            fut = cli.call_async(request)
            wait_until(fut.done, timeout, f'the answer of {name}')
            return fut.result()
        finally:
            self.node.destroy_client(cli)

    def trigger(self, name, timeout=60.0):
        return self.call(Trigger, f'/armcal/{name}', Trigger.Request(), timeout)

    def set_parameters(self, **values):
        req = SetParameters.Request()
        req.parameters = [Parameter(k, value=v).to_parameter_msg() for k, v in values.items()]
        return self.call(SetParameters, '/armcal/set_parameters', req).results

    def close(self):
        self._stop.set()
        self.thread.join(10.0)
        self.executor.shutdown(timeout_sec=5.0)
        self.node.destroy_node()
        self.ctx.try_shutdown()


def diag_values(records, name, after=0.0):
    """Latest diagnostics values of status ``name`` received after ``after`` (or None)."""
    for t, msg in reversed(records):
        if t < after:
            return None
        v = conv.diagnostic_values(msg, name)
        if v is not None:
            return v
    return None


def start_node(env, params, log_path, ignore_sigint=False):
    return Proc([sys.executable, '-m', 'armcal_ros.ros.node', '--ros-args', '--params-file',
                 params], env, log_path, ignore_sigint)


def start_replay(env, bag, rate, log_path, *options, delay=5.0):
    """Start ``armcal replay`` of ``bag`` at ``rate``, after ``delay`` s of discovery at most."""
    return Proc([sys.executable, '-m', 'armcal_ros.cli', 'replay', str(bag), *options,
                 '--rate', str(rate), '--delay', str(delay)], env, log_path)


def refused_start(env, params, log_path):
    """Start the node with ``params`` it must refuse: exit code 2 and the reason; its log."""
    proc = start_node(env, params, log_path)
    try:
        proc.p.wait(timeout=60)
    finally:
        proc.kill()
    log = proc.log()
    assert proc.p.returncode == 2, log
    assert 'refusing to start' in log, log
    return log


def replay_and_calibrate(client, env, params, bag, log_dir, duration, rate, procs, diag,
                         info, delay=5.0):
    """
    Start the node, replay ``bag`` into it and call ~/calibrate once its solve has ended.

    The node runs with ``params``; every camera's CameraInfo in ``info`` (the recorder lists)
    is awaited after the call.  The replay waits for discovery, ``delay`` seconds at most.  The
    processes go into ``procs`` (the caller kills them).
    Returns (node, monotonic time of the call).
    """
    node = start_node(env, params, log_dir / 'node.log')
    procs.append(node)
    wait_until(lambda: diag_values(diag, 'armcal: calibration') or not node.alive(), 30,
               'node diagnostics')
    assert node.alive(), node.log()
    replay = start_replay(env, bag, rate, log_dir / 'replay.log', delay=delay)
    procs.append(replay)
    replay.p.wait(timeout=duration / rate + 60.0)
    assert replay.p.returncode == 0, replay.log()

    def calibrate():
        # A background solve may start between the diagnostics saying none runs and the call
        # (the worker adds a late sample on a loaded machine): wait for it and call again.
        v = wait_until(lambda: (lambda v: v if v and v.get('solving') == 'False' else None)(
            diag_values(diag, 'armcal: calibration')), 120, 'the background solve to end')
        t = time.monotonic()
        res = client.trigger('calibrate')
        return (t, int(v['published']), res) \
            if res.success or 'running already' not in res.message else None
    t_cal, published, res = wait_until(calibrate, 240,
                                       'a ~/calibrate call that is not refused as busy')
    assert res.success, res.message
    t_new = wait_until_published(diag, t_cal, published, 120)
    for c, got in info.items():
        # The node repeats the latest CameraInfo every second once images stop: one received
        # after the diagnostics counted the new calibration published is the new one.
        wait_until(lambda: got and got[-1][0] >= t_new, 30, f'CameraInfo of {c} after '
                   '~/calibrate')
    return node, t_cal


def wait_until_published(diag, after, published, timeout):
    """
    Wait for diagnostics (received after ``after``) counting more than ``published`` calibrations.

    Returns the monotonic time that message was received: every CameraInfo received later
    carries the new calibration.
    """
    def newer():
        for t, msg in reversed(list(diag)):
            if t < after:
                return None
            for st in msg.status:
                if st.name == 'armcal: calibration':
                    v = {kv.key: kv.value for kv in st.values}
                    if int(v.get('published', 0)) > published:
                        return t
        return None
    return wait_until(newer, timeout, 'a newly published calibration in /diagnostics')


def check_camera_info(info, truth, cams, rel=0.03):
    """Assert each camera's last CameraInfo: 640 x 480, focal lengths within ``rel`` of truth."""
    for c in cams:
        msg = info[c][-1][1]
        K = np.asarray(msg.k).reshape(3, 3)
        assert (msg.width, msg.height) == (640, 480)
        assert abs(K[0, 0] / truth[c].fx - 1.0) < rel, (c, K[0, 0], truth[c].fx)
        assert abs(K[1, 1] / truth[c].fy - 1.0) < rel, (c, K[1, 1], truth[c].fy)


def write_sim_bag_with_short_dwells(path, duration, **options):
    """
    Simulate the geometric-error cell (seed 3) with short dwells; write it uncompressed.

    ``options`` go to ``write_sim_bag`` (a pose topic, for instance).
    """
    from armcal_ros.sim.cell import simulate_cell, SimSettings
    from armcal_ros.sim.output import write_sim_bag
    settings = SimSettings(duration=duration, dwell=(0.5, 0.8), speed_fraction=0.8,
                           min_move_time=0.3)
    write_sim_bag(simulate_cell('geometric', seed=3, settings=settings), str(path),
                  compress=False, **options)
    return path
