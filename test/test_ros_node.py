"""
The node end to end on real rclpy and DDS: ``armcal replay`` drives ``calibrator_node``.

One simulated bag (40 s, ~33 dwells, ground truth known; its images in driver-style frames,
``<camera>_color_optical_frame``) is calibrated offline and replayed at 2x into the node started
as a subprocess with a parameter file.  The tests below share that
session and run in file order: the node's outputs are checked against the offline result and
the ground truth, then its services, runtime parameters, a restart (the second node resumes
from the first one's output_dir), bad inputs and a reset.  Every process runs in this test's
own ROS_DOMAIN_ID with discovery kept on localhost, every wait is bounded, and every process
is killed in teardown.
"""
import os
import time
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from rclpy.qos import (DurabilityPolicy, qos_profile_sensor_data, QoSProfile,  # noqa: E402
                       ReliabilityPolicy)
from sensor_msgs.msg import CameraInfo, Image, JointState  # noqa: E402
from sensor_msgs.srv import SetCameraInfo  # noqa: E402
from visualization_msgs.msg import Marker, MarkerArray  # noqa: E402

from armcal_ros.io.calib_files import read_camera_info, read_cameras  # noqa: E402
from armcal_ros.io.message_fields import camera_from_camera_info  # noqa: E402
from armcal_ros.ros import conversions as conv  # noqa: E402
from helpers.params_files import PUMA_URDF, write_params  # noqa: E402
from helpers.ros_nodes import (diag_values, refused_start, start_node, start_replay,  # noqa: E402
                               wait_until, wait_until_published,
                               write_sim_bag_with_short_dwells)

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

CAMS = ['cam1', 'cam2', 'cam3']
RATE = 2.0
FRAME = '{camera}_color_optical_frame'      # as a RealSense driver names its frames
DRIVER_NAMES = ['left_rgb', 'right_rgb', 'top_rgb']     # the drivers' camera_name
FOREIGN_FILE = 'image_width: 640\nimage_height: 480\ncamera_name: left_rgb\n# a checkerboard run\n'
NODE_PARAMS = dict(
    robot_description_file=PUMA_URDF, marker_link='marker', marker_offset=[0.0, 0.0, 0.0],
    solve_period=2.0, min_samples=15,
    # One continuous model: auto's discrete choice can differ between the node and the CLI when
    # the node loses a dwell, and then the estimates need not agree to within one standard
    # deviation; auto itself is tested through the CLI (test_offline.py) and the engine
    # (test_engine.py).
    noise_model='correlated')


# -- fixtures (ros_env and client: conftest.py) -----------------------------------------

@pytest.fixture(scope='module')
def sim(tmp_path_factory):
    """Simulate a 40 s geometric-error cell with short dwells (~33 samples), ground truth."""
    bag = write_sim_bag_with_short_dwells(tmp_path_factory.mktemp('sim') / 'bag', 40.0,
                                          frame_id_format=FRAME)
    return SimpleNamespace(bag=str(bag), truth=str(bag / 'ground_truth'),
                           markers=np.load(bag / 'ground_truth' / 'markers.npz'))


@pytest.fixture(scope='module')
def offline(sim, tmp_path_factory):
    from armcal_ros.offline import calibrate_bag
    from armcal_ros.settings import load_settings
    root = tmp_path_factory.mktemp('offline')
    values = load_settings(write_params(root / 'params.yaml', NODE_PARAMS))
    return calibrate_bag(sim.bag, values, str(root / 'out'), latency=False).report


@pytest.fixture(scope='module')
def live(ros_env, sim, client, tmp_path_factory):
    """Node A calibrating from a 2x replay; ~/calibrate called at the end."""
    root = tmp_path_factory.mktemp('live')
    s = SimpleNamespace(root=root, out=str(root / 'out'), procs=[], commits={})

    def driver(cam):
        def serve(req, res):
            s.commits.setdefault(cam, []).append(req.camera_info)
            res.success = cam != 'cam3'
            res.status_message = 'stored' if res.success else 'flash is read-only'
            return res
        return serve
    for cam in CAMS:
        client.node.create_service(SetCameraInfo, f'/{cam}/set_camera_info', driver(cam))
    s.params = write_params(root / 'params.yaml', NODE_PARAMS, output_dir=s.out,
                            set_camera_info_services=[f'/{c}/set_camera_info' for c in CAMS],
                            camera_info_names=DRIVER_NAMES)
    # A calibration of another tool where drivers look: armcal keeps it before replacing it.
    s.driver_dir = os.path.join(os.environ['ROS_HOME'], 'camera_info')
    os.makedirs(s.driver_dir, exist_ok=True)
    with open(os.path.join(s.driver_dir, 'left_rgb.yaml'), 'w') as f:
        f.write(FOREIGN_FILE)
    s.info = {c: client.record(CameraInfo, f'/armcal/{c}/camera_info')[0] for c in CAMS}
    s.pose = {c: client.record(PoseWithCovarianceStamped, f'/armcal/{c}/pose')[0]
              for c in CAMS}
    s.diag, _ = client.record(DiagnosticArray, '/diagnostics', 10)
    s.markers, _ = client.record(MarkerArray, '/armcal/markers')
    # Headers only (read from the serialized bytes), deep queues: the pairing test wants them
    # all.  The replay publishes the images reliably; the node listens best effort.
    deep = QoSProfile(depth=500, reliability=ReliabilityPolicy.RELIABLE)
    s.image_headers = {c: client.record_headers(Image, f'/{c}/image_raw', deep)[0]
                       for c in ('cam1', 'cam3')}
    s.info_headers = {c: client.record_headers(CameraInfo, f'/armcal/{c}/camera_info', deep)[0]
                      for c in ('cam1', 'cam3')}
    try:
        s.node = start_node(ros_env, s.params, root / 'node_a.log')
        s.procs.append(s.node)
        wait_until(lambda: diag_values(s.diag, 'armcal: calibration'), 30, 'node A diagnostics')
        t0 = time.monotonic()
        replay = start_replay(ros_env, sim.bag, RATE, root / 'replay.log')
        s.procs.append(replay)
        replay.p.wait(timeout=40.0 / RATE + 60.0)
        s.replay_wall = time.monotonic() - t0
        assert replay.p.returncode == 0, replay.log()
        s.replay_log = replay.log()
        # ~/calibrate refuses while a background solve runs: wait for it, then solve on all.
        # One may start between the diagnostics saying none runs and the call (the worker
        # adds a late sample on a loaded machine): then wait again and call again.

        def call():
            wait_until(lambda: (diag_values(s.diag, 'armcal: calibration') or {}).get(
                'solving') == 'False', 120, 'the background solve to end')
            t = time.monotonic()
            n = int(diag_values(s.diag, 'armcal: calibration')['published'])
            res = client.trigger('calibrate')
            return (t, n, res) if res.success or 'running already' not in res.message \
                else None
        t_cal, published, s.calibrate = wait_until(
            call, 240, 'a ~/calibrate call that is not refused as busy')

        def final():
            v = diag_values(s.diag, 'armcal: calibration', t_cal)
            return v if (v and v['solving'] == 'False' and v.get('last_solve_samples') ==
                         v['samples'] and v['state'] == 'calibrated') else None
        s.main_diag = wait_until(final, 120, 'the solve ~/calibrate started')
        # Once the images stop, the node repeats the latest CameraInfo every second: one
        # received after the diagnostics counted the new calibration published is the new one.
        t_new = wait_until_published(s.diag, t_cal, published, 20)
        for c in CAMS:
            wait_until(lambda: s.info[c] and s.info[c][-1][0] >= t_new, 20,
                       f'CameraInfo of {c} after ~/calibrate')
            wait_until(lambda: s.pose[c] and s.pose[c][-1][0] >= t_cal, 20, f'pose of {c}')
        t_pub = max(s.info[c][-1][0] for c in CAMS)
        s.cam_diag = {c: wait_until(lambda: diag_values(s.diag, f'armcal: {c}', t_pub), 10,
                                    f'diagnostics of {c}') for c in CAMS}
        yield s
    finally:
        for p in s.procs:
            p.kill()


# -- tests (in order: they share one session) --------------------------------------------

def test_calibrate_service_and_camera_info_for_every_camera(live, offline, sim):
    assert live.calibrate.success, live.calibrate.message
    assert live.calibrate.message.startswith('solving on ')
    truth = {c.name: c for c in read_cameras(sim.truth)[1]}
    n_node = int(live.main_diag['samples'])
    # Best-effort DDS on a shared two-core machine may lose a few images of a dwell (counted
    # in diagnostics); the offline run reads every message.
    assert 0.8 * offline['n_samples'] <= n_node <= offline['n_samples'], (
        n_node, offline['n_samples'], live.main_diag)
    for cam in CAMS:
        msg = live.info[cam][-1][1]
        assert msg.header.frame_id == FRAME.format(camera=cam)
        assert (msg.width, msg.height) == (640, 480)
        assert msg.distortion_model == 'plumb_bob' and len(msg.d) == 5
        np.testing.assert_allclose(np.asarray(msg.r).reshape(3, 3), np.eye(3))
        K = np.asarray(msg.k).reshape(3, 3)
        np.testing.assert_allclose(np.asarray(msg.p).reshape(3, 4)[:, :3], K)
        assert np.all(np.asarray(msg.p).reshape(3, 4)[:, 3] == 0)
        got = dict(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], k1=msg.d[0], k2=msg.d[1],
                   p1=msg.d[2], p2=msg.d[3])
        off = offline['cameras'][cam]
        off_vals = dict(fx=off['fx'], fy=off['fy'], cx=off['cx'], cy=off['cy'],
                        k1=off['dist'][0], k2=off['dist'][1], p1=off['dist'][2],
                        p2=off['dist'][3])
        t = truth[cam]
        true_vals = dict(fx=t.fx, fy=t.fy, cx=t.cx, cy=t.cy, k1=t.dist[0], k2=t.dist[1],
                         p1=t.dist[2], p2=t.dist[3])
        for k, v in got.items():
            std = float(live.cam_diag[cam][f'std_{k}'])
            assert std > 0
            # The node and the offline CLI saw the same bag and parameters: same estimate up to
            # a fraction of its standard deviation (warm start, a dwell lost under load).
            assert abs(v - off_vals[k]) <= 1.0 * off['std'][k] + 1e-9, (cam, k, v, off_vals[k])
            # Against the truth: a 4-sigma bound; the sigmas are honest only up to the robot's
            # correlated bias, which the intrinsics hardly see (the poses absorb it).
            assert abs(v - true_vals[k]) <= 4.0 * std, (cam, k, v, true_vals[k], std)
        assert float(live.cam_diag[cam]['rms_px']) < 0.5
    # The solves ran in one child process of the node (solver_process, the default).
    where = live.main_diag['solver']
    assert where.startswith('child process ') and live.main_diag['solver_process_starts'] == '1'
    with open(f'/proc/{int(where.split()[-1])}/stat') as f:
        assert int(f.read().rsplit(')', 1)[1].split()[1]) == live.node.p.pid, where


def test_camera_info_consumer_reproduces_ground_truth_pixels(live, sim):
    """cv2 with the received K, D and pose reproduces the true pixels of the true marker."""
    g = sim.markers
    for j, cam in enumerate(CAMS):
        info = live.info[cam][-1][1]
        pose = live.pose[cam][-1][1]
        assert pose.header.frame_id == 'base_link'
        cov = np.asarray(pose.pose.covariance).reshape(6, 6)
        assert np.all(np.linalg.eigvalsh(cov) > 0), 'pose covariance must be positive definite'
        est = conv.camera_from_pose(camera_from_camera_info(info, cam), pose)
        K, D = np.asarray(info.k).reshape(3, 3), np.asarray(info.d)
        sel = (g['frame_camera'] == j) & (g['frame_occlusion'] == 0)
        X, uv_true = g['frame_marker'][sel], g['frame_uv'][sel]
        assert len(X) > 100
        uv, _ = cv2.projectPoints(X, est.rvec, est.translation, K, D)
        err = np.linalg.norm(uv.reshape(-1, 2) - uv_true, axis=1)
        # Offline on this bag the error is ~0.35 px RMS, 0.6 px max: the ~1 mm of robot bias
        # that the cameras cannot tell from their own pose, seen from 1.5-2 m at f = 800 px.
        assert np.sqrt(np.mean(err ** 2)) < 1.0 and err.max() < 2.0, (cam, err.max())
        xn = cv2.undistortPoints(uv_true.reshape(-1, 1, 2), K, D).reshape(-1, 2)
        Xc = est.to_camera(X)
        ray_err = np.linalg.norm(xn - Xc[:, :2] / Xc[:, 2:], axis=1) * K[0, 0]
        assert np.sqrt(np.mean(ray_err ** 2)) < 1.0 and ray_err.max() < 2.0, cam


def test_markers_show_samples_bias_and_frusta(live):
    def complete():
        if not live.markers:
            return None
        by_ns = {m.ns: m for m in live.markers[-1][1].markers}
        ok = ('samples' in by_ns and len(by_ns['samples'].points) == int(
            live.main_diag['samples']) and len(by_ns.get('frusta', Marker()).points) == 16)
        return by_ns if ok else None
    by_ns = wait_until(complete, 10, 'markers with every sample and the frusta')
    bias = [m for ns, m in by_ns.items() if ns.startswith('bias_x')]
    assert bias and len(bias[0].points) == 2 * len(by_ns['samples'].points), \
        'one bias vector per sample (the correlated model estimates the points)'
    assert all(m.header.frame_id == 'base_link' for m in by_ns.values())


def test_late_subscriber_gets_the_latest_camera_info(live, client):
    got, sub = client.record(CameraInfo, '/armcal/cam2/camera_info')
    try:
        wait_until(lambda: got, 10, 'a late CameraInfo (transient local)')
        assert list(got[-1][1].k) == list(live.info['cam2'][-1][1].k)
    finally:
        client.node.destroy_subscription(sub)


def test_a_camera_info_with_the_identical_header_beside_every_image(live):
    """As an exact-time synchronizer pairs them: (stamp, frame_id) equal, image by image."""
    for cam in ('cam1', 'cam3'):
        images = list(live.image_headers[cam])
        infos = set(live.info_headers[cam])
        assert len(images) > 200, len(images)
        # From the first image paired (the first calibration, part-way through the replay) on.
        first = next(k for k, h in enumerate(images) if h in infos)
        after = images[first:]
        paired = sum(h in infos for h in after)
        # Each image the node receives gets its CameraInfo; best-effort delivery to the node on
        # a loaded two-core machine loses some images (counted in its diagnostics): 193 of 216
        # paired beside a benchmark, 49 of 62 in a fresh-clone run.  A node that published
        # CameraInfo at its solves only would pair next to none; the bound sits well between.
        assert paired >= 0.6 * len(after), (cam, paired, len(after))
        # The first calibration comes part-way through (later on a loaded machine): enough
        # images after it to judge, at least two seconds of one camera at 2x.
        assert len(after) >= 50, ('calibrated too late in the replay to judge', len(after),
                                  len(images))
        # Every CameraInfo carries the header of an image: the latest image's one when it
        # is published at a solve or repeated after the images stopped.
        stray = infos - set(images)
        assert len(stray) <= 0.02 * len(infos), (cam, sorted(stray)[:5])
        assert {h[2] for h in infos} == {FRAME.format(camera=cam)}


@pytest.mark.parametrize('qos', ['default', 'sensor_data'])
def test_a_late_volatile_subscriber_gets_the_calibration(live, client, qos):
    """No transient-local durability needed: the node repeats CameraInfo once images stop."""
    profile = QoSProfile(depth=10) if qos == 'default' else qos_profile_sensor_data
    assert profile.durability == DurabilityPolicy.VOLATILE
    got, sub = client.record(CameraInfo, '/armcal/cam2/camera_info', profile)
    try:
        wait_until(lambda: got, 10, f'CameraInfo for a late {qos} subscriber')
        assert list(got[-1][1].k) == list(live.info['cam2'][-1][1].k)
        assert got[-1][1].header.frame_id == 'cam2_color_optical_frame'
    finally:
        client.node.destroy_subscription(sub)


def test_files_name_the_images_frames_and_go_where_drivers_look(live):
    from armcal_ros.io.calib_files import read_extrinsics
    from armcal_ros.io.results_files import DRIVER_FILE_MARK
    _, poses = read_extrinsics(os.path.join(live.out, 'extrinsics.yaml'))
    assert {c: poses[c][2] for c in CAMS} == {c: FRAME.format(camera=c) for c in CAMS}
    for cam in CAMS:
        assert live.cam_diag[cam]['frame_id'] == FRAME.format(camera=cam)
    # camera_info_manager's default URL: file://${ROS_HOME}/camera_info/${NAME}.yaml
    for cam, name in zip(CAMS, DRIVER_NAMES):
        path = os.path.join(live.driver_dir, f'{name}.yaml')
        with open(path) as f:
            assert f.readline().rstrip('\n') == DRIVER_FILE_MARK
        back = read_camera_info(path)
        assert back.name == name
        np.testing.assert_allclose(back.K.ravel(), live.info[cam][-1][1].k)
        np.testing.assert_allclose(back.dist, live.info[cam][-1][1].d)
    with open(os.path.join(live.driver_dir, 'left_rgb.before_armcal.yaml')) as f:
        assert f.read() == FOREIGN_FILE
    assert 'kept as' in live.node.log()


def test_static_tf_to_the_images_frames(live, client):
    """/tf_static as tf2_ros' StaticTransformBroadcaster sends it: latched, the whole set."""
    TFMessage = pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs not built (Makefile)'
                                    ).TFMessage
    got, sub = client.record(TFMessage, '/tf_static')
    try:
        wait_until(lambda: got, 10, '/tf_static (transient local)')
    finally:
        client.node.destroy_subscription(sub)
    tfs = {t.child_frame_id: t for t in got[-1][1].transforms}
    assert set(tfs) == {FRAME.format(camera=c) for c in CAMS}
    for cam in CAMS:
        t = tfs[FRAME.format(camera=cam)]
        p = live.pose[cam][-1][1].pose.pose
        assert t.header.frame_id == 'base_link'
        np.testing.assert_allclose(
            [t.transform.translation.x, t.transform.translation.y, t.transform.translation.z],
            [p.position.x, p.position.y, p.position.z], atol=1e-9)


def test_calibration_committed_to_drivers_with_their_answers_logged(live):
    for cam in CAMS:
        wait_until(lambda: live.commits.get(cam), 10, f'a SetCameraInfo call for {cam}')
        assert list(live.commits[cam][-1].k) == list(live.info[cam][-1][1].k)
    log = wait_until(lambda: 'driver refused' in live.node.log() and live.node.log(), 10,
                     'the refusal in the log')
    assert "cam3: driver refused the calibration via /cam3/set_camera_info: 'flash is " \
           "read-only'" in log
    assert 'cam1: driver accepted the calibration' in log


def test_runtime_parameter_sets_are_validated(live, client):
    bad = client.set_parameters(pixel_sigma=-1.0)[0]
    assert not bad.successful and 'pixel_sigma' in bad.reason
    bad = client.set_parameters(noise_model='gaussian')[0]
    assert not bad.successful and 'noise_model' in bad.reason
    ro = client.set_parameters(image_topics=['/a', '/b', '/c'])[0]
    assert not ro.successful and 'image_topics' in ro.reason
    ok = client.set_parameters(pixel_sigma=0.4)[0]
    assert ok.successful, ok.reason
    assert "pixel_sigma=0.4" in wait_until(
        lambda: 'parameters changed' in live.node.log() and live.node.log(), 10, 'the log line')
    assert live.node.alive()


def test_save_service_writes_the_files(live, client):
    res = client.trigger('save')
    assert res.success, res.message
    for name in ('cam1.yaml', 'cam2.yaml', 'cam3.yaml', 'extrinsics.yaml', 'samples.npz',
                 'calibration.json'):
        assert os.path.exists(os.path.join(live.out, name)), name
    saved = read_camera_info(os.path.join(live.out, 'cam1.yaml'))
    np.testing.assert_allclose(saved.K.ravel(), live.info['cam1'][-1][1].k)


def test_restart_republishes_the_saved_calibration(live, client, ros_env):
    n_before = int(live.main_diag['samples'])
    assert live.node.stop() == 0, live.node.log()[-2000:]
    assert 'saved' in live.node.log()
    got, sub = client.record(CameraInfo, '/armcal/cam1/camera_info')
    try:
        t_start = time.monotonic()
        # As a shell script's `node &` starts it: SIGINT ignored, inherited.
        live.node = start_node(ros_env, live.params, live.root / 'node_b.log',
                               ignore_sigint=True)
        live.procs.append(live.node)
        wait_until(lambda: [m for t, m in got if t > t_start], 30,
                   'CameraInfo from the restarted node')
        msg = [m for t, m in got if t > t_start][-1]
        assert list(msg.k) == list(live.info['cam1'][-1][1].k)
        values = wait_until(lambda: diag_values(live.diag, 'armcal: calibration', t_start), 20,
                            'diagnostics of the restarted node')
        assert f'restored {n_before} samples' in values['restored'], values
        assert values['state'] == 'calibrated'
    finally:
        client.node.destroy_subscription(sub)


def test_bad_inputs_are_counted_and_the_node_keeps_running(live, client, sim):
    pub_js = client.node.create_publisher(JointState, '/joint_states', 50)
    pub_img = {c: client.node.create_publisher(Image, f'/{c}/image_raw', 5) for c in CAMS}
    wait_until(lambda: pub_js.get_subscription_count() > 0
               and all(p.get_subscription_count() > 0 for p in pub_img.values()), 15,
               'the node subscribing')
    names = [str(n) for n in sim.markers['joint_names']]
    q = [float(v) for v in sim.markers['dwell_q'][0]]
    t0 = 5_000_000_000_000

    def joints(k, names=names, q=q, t=None):
        m = JointState(name=names, position=q)
        m.header.stamp = conv.time_msg(t0 + k * 5_000_000 if t is None else t)
        pub_js.publish(m)
        time.sleep(0.002)

    def image(cam, encoding, width, height, step, nbytes):
        m = Image(encoding=encoding, width=width, height=height, step=step)
        image.k += 1
        m.header.stamp = conv.time_msg(t0 + 100_000_000 + image.k * 20_000_000)
        m.data = bytes(nbytes)
        pub_img[cam].publish(m)

    image.k = 0
    before = diag_values(live.diag, 'armcal: calibration') or {}

    def count(v, key):
        return int(v.get(f'input_{key}', 0))
    for k in range(40):
        joints(k)
    for _ in range(2):   # twice: best-effort delivery is not guaranteed
        image('cam1', 'mono8', 64, 48, 64, 100)            # truncated data
        image('cam2', 'weird_encoding', 64, 48, 64, 64 * 48)  # unknown encoding
        image('cam3', 'rgb8', 64, 48, 64, 64 * 48)           # says colour, sized mono
        image('cam2', 'mono8', 64, 48, 64, 64 * 48)          # not the camera's 640 x 480
        time.sleep(0.05)
    for k in range(40, 80):
        joints(k)
    nan_q = list(q)
    nan_q[2] = float('nan')
    joints(80, q=nan_q)                                       # a NaN joint
    joints(81, names=names + ['gripper_finger'], q=q + [0.01])   # an extra joint: fine
    # 8 MB on a VGA camera's topic: best-effort DDS usually drops so large a message on the
    # way (its fragments overflow the socket buffers); one that arrives is counted and skipped
    # (test_ros_node_parameters.py checks that in-process); the node must run on either way.
    image('cam1', 'mono8', 4000, 2000, 4000, 8_000_000)
    for k in range(82, 120):
        joints(k)
    joints(0, names=['no_such_joint'], q=[0.0], t=t0 + 121 * 5_000_000)
    joints(0, t=t0 - 60_000_000_000)                          # the clock jumps back a minute
    joints(0, t=t0 + 3_600_000_000_000)                       # and an hour forwards
    t_sent = time.monotonic()

    last = {}

    def counted():
        v = diag_values(live.diag, 'armcal: calibration', t_sent)
        if v is None:
            return None
        last.update(v)
        bad_images = sum(count(v, k) - count(before, k)
                         for k in ('image_decode_error', 'image_malformed'))
        ok = (bad_images >= 3 and count(v, 'joint_state_missing_joint') >= 1
              and count(v, 'time_jump') >= 1 and count(v, 'joint_state_non_finite') >= 1
              and count(v, 'image_size_changed') >= 1)
        return v if ok else None
    try:
        values = wait_until(counted, 20, 'the bad inputs in /diagnostics')
    except AssertionError as exc:
        raise AssertionError(f'{exc}; last counts: '
                             f'{ {k: v for k, v in last.items() if k.startswith("input_")} }')
    assert live.node.alive()
    assert client.trigger('save').success
    assert 'image cannot be decoded' in live.node.log()
    log = live.node.log()
    assert 'lacks joint(s) [' in log and 'no_such_joint' in log, 'the log names the joints'

    assert values['state'] == 'calibrated'
    for p in [pub_js, *pub_img.values()]:
        client.node.destroy_publisher(p)


@pytest.mark.parametrize('sig', ['SIGINT', 'SIGTERM'])
def test_a_signal_ends_the_node_within_2_s_with_its_samples_saved(live, client, ros_env, sig):
    """Node B was started with SIGINT ignored, as a background job of a script is."""
    import signal
    from armcal_ros.frontend.store import SampleStore
    values = wait_until(lambda: diag_values(live.diag, 'armcal: calibration'), 10, 'diag')
    n = int(values['samples'])
    samples = os.path.join(live.out, 'samples.npz')
    os.utime(samples, (0, 0))
    t0 = time.monotonic()
    live.node.p.send_signal(getattr(signal, sig))
    live.node.p.wait(30)
    elapsed = time.monotonic() - t0
    log = live.node.log()
    assert live.node.p.returncode == 0, log[-2000:]
    assert os.path.getmtime(samples) > 0, 'samples saved at shutdown'
    assert len(SampleStore.load(live.out)) >= n
    # The contract: within 2 s (measured 0.6-0.7 s here, the replay ended and no solve
    # running).
    assert elapsed < 2.0, (elapsed, log[-2000:])
    live.node = start_node(ros_env, live.params, live.root / f'node_after_{sig}.log')
    live.procs.append(live.node)
    t = time.monotonic()
    wait_until(lambda: diag_values(live.diag, 'armcal: calibration', t), 30,
               'the node back after the signal')


def test_reset_forgets_the_samples(live, client):
    res = client.trigger('reset')
    assert res.success and res.message.startswith('forgetting '), res.message
    t = time.monotonic()
    values = wait_until(lambda: (lambda v: v if v and v['samples'] == '0' else None)(
        diag_values(live.diag, 'armcal: calibration', t)), 10, 'no samples after the reset')
    assert values['state'] == 'calibrated', 'the calibration stays published'
    assert live.node.stop() == 0


@pytest.mark.parametrize('extra, words', [
    (dict(pixel_sigma=-1.0), ['pixel_sigma', 'out of range']),
    (dict(noise_model='gaussian'), ['noise_model', 'must be one of']),
    (dict(camera_names=['cam1', 'cam2']), ['camera_names', 'image_topics']),
    (dict(pixel_sgima=1.0), ['unknown parameter', 'pixel_sgima']),
])
def test_bad_parameters_stop_the_start_with_the_reason(ros_env, tmp_path, extra, words):
    params = write_params(tmp_path / 'bad.yaml', NODE_PARAMS, output_dir=str(tmp_path / 'out'),
                          **extra)
    log = refused_start(ros_env, params, tmp_path / 'node.log')
    for w in words:
        assert w in log, log


def test_replay_starts_once_the_subscriber_has_matched(ros_env, client, tmp_path):
    """The first message reaches a subscriber that is up, without sleeping out ``--delay``."""
    from armcal_ros.io.bag import BagWriter
    bag = tmp_path / 'short'
    with BagWriter(bag) as w:
        for k in range(5):
            w.write_joint_state('/match_test/joint_states', 1_000_000_000 + k * 10_000_000,
                                ['a'], [0.01 * (k + 1)])
    got, sub = client.record(JointState, '/match_test/joint_states',
                             QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
    # The bound is far above anything discovery takes on one host; a replay that slept it out
    # would not have ended within the wait below.
    proc = start_replay(ros_env, bag, 1, tmp_path / 'replay.log', delay=120)
    try:
        wait_until(lambda: proc.p.poll() is not None, 60, 'the replay to end')
    finally:
        proc.kill()
        client.node.destroy_subscription(sub)
    assert proc.p.returncode == 0, proc.log()
    assert 's of discovery first' in proc.log()
    wait_until(lambda: len(got) == 5, 10, 'all five messages')
    assert [m.position[0] for _, m in got] == pytest.approx([0.01, 0.02, 0.03, 0.04, 0.05])


def test_replay_loops_and_stops_cleanly_on_sigint(ros_env, client, tmp_path):
    from armcal_ros.io.bag import BagWriter
    bag = tmp_path / 'small'
    with BagWriter(bag) as w:
        for k in range(40):
            w.write_joint_state('/loop_test/joint_states', 1_000_000_000 + k * 10_000_000,
                                ['a'], [0.01 * k])
    got, sub = client.record(JointState, '/loop_test/joint_states',
                             QoSProfile(depth=100, reliability=ReliabilityPolicy.BEST_EFFORT))
    proc = start_replay(ros_env, bag, 2, tmp_path / 'replay.log', '--loop')
    try:
        wait_until(lambda: len(got) >= 100, 30, 'more messages than one pass of the bag')
        assert proc.stop() == 0, proc.log()
    finally:
        proc.kill()
        client.node.destroy_subscription(sub)
    assert 'loop(s)' in proc.log()
    positions = [m.position[0] for _, m in got]
    assert positions.count(0.0) >= 2, 'the bag started again from its first message'
