"""Messages the node publishes, its event queue and its parameter handling (no DDS traffic)."""
import os
import threading

import cv2
import numpy as np
import pytest

from armcal_ros.core.camera import Camera
from armcal_ros.params import BY_NAME, PARAMS
from armcal_ros.ros import conversions as conv
from armcal_ros.ros.event_queue import EventQueue
from armcal_ros.ros.status import bias_vectors, diagnostic_statuses, frustum_segments, NodeState

pytestmark = pytest.mark.timeout(60)


def _camera():
    return Camera.look_at('cam1', 640, 480, 810.0, 790.0, 330.0, 235.0,
                          [-0.17, 0.06, 0.001, -0.002, 0.01], eye=[1.2, -1.0, 0.9],
                          target=[0.5, 0.0, 0.0])


def _points(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform([0.3, -0.3, -0.2], [0.8, 0.3, 0.3], (n, 3))


def test_camera_info_follows_the_conventions():
    cam = _camera()
    msg = conv.camera_info_msg(cam, conv.time_msg(1_500_000_000))
    assert msg.header.frame_id == 'cam1_optical_frame'
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (1, 500_000_000)
    assert (msg.width, msg.height) == (640, 480)
    assert msg.distortion_model == 'plumb_bob'
    K = np.asarray(msg.k).reshape(3, 3)
    np.testing.assert_allclose(K, cam.K)
    np.testing.assert_allclose(np.asarray(msg.r).reshape(3, 3), np.eye(3))
    np.testing.assert_allclose(np.asarray(msg.p).reshape(3, 4), np.hstack([cam.K, np.zeros(
        (3, 1))]))
    # D in OpenCV's order: a consumer projecting with (K, D) gets the camera's own projection.
    X = _points()
    uv, _ = cv2.projectPoints(X, cam.rvec, cam.translation, K, np.asarray(msg.d))
    np.testing.assert_allclose(uv.reshape(-1, 2), cam.project(X), atol=1e-9)
    back = conv.camera_from_camera_info(msg, 'cam1')
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.dist, cam.dist)


def test_camera_from_camera_info_refuses_uncalibrated_and_other_models():
    msg = conv.camera_info_msg(_camera(), conv.time_msg(0))
    msg.distortion_model = 'equidistant'
    with pytest.raises(ValueError, match='plumb_bob'):
        conv.camera_from_camera_info(msg)
    msg.k = [0.0] * 9
    with pytest.raises(ValueError, match='uncalibrated'):
        conv.camera_from_camera_info(msg)


def test_pose_and_transform_are_T_base_camera():
    cam = _camera()
    cov = np.diag([1e-6, 2e-6, 3e-6, 1e-5, 2e-5, 3e-5])
    cov[0, 4] = cov[4, 0] = 5e-7
    msg = conv.pose_msg(cam, cov, 'base_link', conv.time_msg(0))
    assert msg.header.frame_id == 'base_link'
    p = msg.pose.pose.position
    np.testing.assert_allclose([p.x, p.y, p.z], cam.center)
    np.testing.assert_allclose(np.asarray(msg.pose.covariance).reshape(6, 6), cov)
    again = conv.camera_from_pose(cam, msg)
    np.testing.assert_allclose(again.rotation, cam.rotation, atol=1e-12)
    np.testing.assert_allclose(again.translation, cam.translation, atol=1e-12)
    # The optical axis (z) in the base frame points from the camera to its target.
    o = msg.pose.pose.orientation
    from scipy.spatial.transform import Rotation
    z = Rotation.from_quat([o.x, o.y, o.z, o.w]).apply([0, 0, 1])
    to_target = np.array([0.5, 0.0, 0.0]) - cam.center
    assert np.dot(z, to_target / np.linalg.norm(to_target)) > 0.999
    tf = conv.transform_msg(cam, 'base_link', conv.time_msg(0))
    assert (tf.header.frame_id, tf.child_frame_id) == ('base_link', 'cam1_optical_frame')
    assert tf.transform.rotation.w == pytest.approx(o.w)
    with pytest.raises(ValueError, match='6x6'):
        conv.pose_msg(cam, np.eye(3), 'base_link', conv.time_msg(0))


def test_time_msg_refuses_negative():
    with pytest.raises(ValueError, match='t_ns'):
        conv.time_msg(-1)


def test_frustum_far_corners_project_to_the_image_corners():
    cam = _camera()
    cam.dist = np.zeros(5)
    segs = frustum_segments(cam, depth=0.3)
    assert segs.shape == (8, 2, 3)
    np.testing.assert_allclose(segs[:4, 0], np.tile(cam.center, (4, 1)))
    uv = cam.project(segs[:4, 1])
    np.testing.assert_allclose(uv, [[0, 0], [640, 0], [640, 480], [0, 480]], atol=1e-9)
    np.testing.assert_allclose(cam.to_camera(segs[:4, 1])[:, 2], 0.3)
    with pytest.raises(ValueError, match='depth'):
        frustum_segments(cam, 0.0)


def test_bias_vectors_pair_each_estimate_with_its_own_sample():
    nominal = _points(40, seed=3)
    rng = np.random.default_rng(4)
    estimated = nominal + rng.normal(0, 0.0007, nominal.shape)
    order = rng.permutation(40)
    segs = bias_vectors(nominal, estimated[order])
    assert segs.shape == (40, 2, 3)
    np.testing.assert_allclose(segs[:, 0], nominal[order])
    np.testing.assert_allclose(segs[:, 1], estimated[order])
    far = estimated.copy()
    far[0] += 0.05
    assert len(bias_vectors(nominal, far)) == 39


def test_marker_array_has_samples_bias_and_frusta():
    cam = _camera()
    nominal = _points(10)
    msg = conv.marker_array_msg('base_link', conv.time_msg(0), nominal, [cam],
                                nominal + 0.001, bias_scale=50.0)
    by_ns = {m.ns: m for m in msg.markers}
    assert len(by_ns['samples'].points) == 10
    bias = by_ns['bias_x50']
    assert len(bias.points) == 20
    d = np.array([[p.x, p.y, p.z] for p in bias.points]).reshape(-1, 2, 3)
    np.testing.assert_allclose(d[:, 1] - d[:, 0], 0.05, atol=1e-9)
    assert len(by_ns['frusta'].points) == 16
    assert by_ns['camera_names'].text == 'cam1'
    empty = conv.marker_array_msg('base_link', conv.time_msg(0), np.zeros((0, 3)))
    from visualization_msgs.msg import Marker
    assert all(m.action == Marker.DELETE for m in empty.markers)


def _state(**kw):
    base = dict(camera_names=['cam1', 'cam2'], n_samples=3, min_samples=20,
                samples_per_camera={'cam1': 3, 'cam2': 1}, image_sizes={'cam1': (640, 480)},
                solving=False, n_solves=0, n_rejected=0,
                input_counts={'time_jump': 2, 'image_decode_error': 1},
                queue_dropped={'image': 0, 'joint': 0}, queue_depth={'image': 1, 'joint': 0})
    base.update(kw)
    return NodeState(**base)


def test_diagnostics_before_a_calibration():
    st = diagnostic_statuses(_state())
    assert [s.name for s in st] == ['armcal: calibration', 'armcal: cam1', 'armcal: cam2']
    main = st[0]
    assert main.level == 1 and main.message.startswith('collecting samples (3 of 20)')
    assert main.values['input_time_jump'] == '2'
    assert main.values['input_image_decode_error'] == '1'
    assert main.values['samples_cam2'] == '1'
    assert st[1].values['image_size'] == '640x480' and st[2].values['image_size'] == 'no image yet'
    msg = conv.diagnostic_array_msg(st, conv.time_msg(0))
    from diagnostic_msgs.msg import DiagnosticStatus
    assert msg.status[0].level == DiagnosticStatus.WARN
    assert conv.diagnostic_values(msg, 'armcal: calibration')['samples'] == '3'
    assert conv.diagnostic_values(msg, 'nope') is None
    dropped = diagnostic_statuses(_state(queue_dropped={'image': 4}))[0]
    assert 'dropped' in dropped.message and dropped.values['queue_dropped_image'] == '4'


def test_event_queue_keeps_order_and_drops_oldest_per_lane():
    q = EventQueue({'joint': 5, 'image': 2, 'control': None})
    assert q.put('joint', 'j0') and q.put('image', 'i0') and q.put('joint', 'j1')
    assert q.put('image', 'i1')
    assert not q.put('image', 'i2'), 'the image lane is full: i0 is pushed out'
    q.put('control', 'c0')
    assert q.dropped['image'] == 1 and q.dropped['joint'] == 0
    assert q.depth() == {'joint': 2, 'image': 2, 'control': 1}
    got = q.get_batch(timeout=0.1)
    assert [item for _, item in got] == ['j0', 'j1', 'i1', 'i2', 'c0']
    assert q.get_batch(timeout=0.01) == []
    with pytest.raises(ValueError, match='kind'):
        q.put('bogus', 1)
    with pytest.raises(ValueError, match='bounds'):
        EventQueue({'joint': 0})


def test_event_queue_wakes_the_worker_and_closes():
    q = EventQueue({'joint': 10})
    got = []

    def worker():
        while True:
            batch = q.get_batch(timeout=5.0)
            if not batch and q.closed:
                return
            got.extend(batch)
    t = threading.Thread(target=worker)
    t.start()
    for i in range(5):
        q.put('joint', i)
    q.close()
    t.join(5.0)
    assert not t.is_alive() and [i for _, i in got] == list(range(5))
    assert not q.put('joint', 99)


# -- parameters on a real rclpy node (no traffic) ---------------------------------------

@pytest.fixture
def ros_context(tmp_path, monkeypatch):
    rclpy = pytest.importorskip('rclpy')
    monkeypatch.setenv('ROS_LOG_DIR', str(tmp_path / 'log'))
    monkeypatch.setenv('ROS_DOMAIN_ID', str(1 + os.getpid() % 200))
    monkeypatch.setenv('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    ctx.try_shutdown()


def _overrides(tmp_path, **extra):
    from rclpy.parameter import Parameter
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    values = dict(robot_description_file=os.path.join(root, 'urdf', 'puma560.urdf'),
                  marker_link='marker', output_dir=str(tmp_path / 'out'), resume=False)
    values.update(extra)
    return [Parameter(k, value=v) for k, v in values.items()]


def test_descriptors_declare_types_ranges_and_read_only(ros_context, tmp_path):
    from rcl_interfaces.msg import ParameterType

    from armcal_ros.ros.node import CalibratorNode, RUNTIME_PARAMETERS
    node = CalibratorNode(context=ros_context, parameter_overrides=_overrides(tmp_path))
    try:
        for p in PARAMS:
            d = node.describe_parameter(p.name)
            assert d.description and d.read_only == (p.name not in RUNTIME_PARAMETERS)
        d = node.describe_parameter('pixel_sigma')
        assert d.type == ParameterType.PARAMETER_DOUBLE
        assert d.floating_point_range[0].from_value == BY_NAME['pixel_sigma'].minimum
        assert node.describe_parameter('min_samples').integer_range[0].from_value == 1
        assert node.get_parameter('set_camera_info_services').value == []
        assert node.describe_parameter('camera_names').read_only
        assert node.values['camera_names'] == ['cam1', 'cam2', 'cam3']
    finally:
        node.close(solve_timeout=1.0)
        node.destroy_node()


@pytest.mark.parametrize('extra, words', [
    (dict(pixel_sigma=-1.0), ['pixel_sigma']),
    (dict(noise_model='gaussian'), ['noise_model', 'must be one of']),
    (dict(camera_names=['cam1', 'cam2']), ['camera_names', 'image_topics', 'same length']),
    (dict(marker_link='no_such_link'), ['marker_link', 'no_such_link']),
    (dict(pixel_sigma=1), ['pixel_sigma', 'double']),
    (dict(pose_topic='/flange_pose', noise_model='kinematic'), ['noise_model', 'pose_topic']),
])
def test_bad_parameters_refuse_the_start(ros_context, tmp_path, extra, words):
    from armcal_ros.ros.node import CalibratorNode, ParameterError
    with pytest.raises(ParameterError) as err:
        CalibratorNode(context=ros_context, parameter_overrides=_overrides(tmp_path, **extra))
    for w in words:
        assert w in str(err.value)


def test_runtime_parameter_sets_are_checked(ros_context, tmp_path):
    from rclpy.parameter import Parameter

    from armcal_ros.ros.node import CalibratorNode
    node = CalibratorNode(context=ros_context, parameter_overrides=_overrides(tmp_path))
    try:
        r = node.set_parameters([Parameter('point_sigma', value=-0.1)])[0]
        assert not r.successful and 'point_sigma' in r.reason
        r = node.set_parameters([Parameter('kernel', value='gaussian')])[0]
        assert not r.successful and 'kernel' in r.reason and 'must be one of' in r.reason
        r = node.set_parameters([Parameter('set_camera_info_services', value=['/a'])])[0]
        assert not r.successful and 'set_camera_info_services' in r.reason
        r = node.set_parameters([Parameter('camera_names', value=['a', 'b', 'c'])])[0]
        assert not r.successful and 'camera_names' in r.reason
        assert node.engine.settings.solver.pixel_sigma == 0.5
        r = node.set_parameters([Parameter('pixel_sigma', value=0.3),
                                 Parameter('noise_model', value='independent')])[0]
        assert r.successful, r.reason
        assert node.engine.settings.solver.pixel_sigma == 0.3
        assert node.engine.settings.prior.model == 'independent'
        assert node.values['noise_model'] == 'independent'
    finally:
        node.close(solve_timeout=1.0)
        node.destroy_node()


def test_static_tf_through_tf2_ros_when_importable(ros_context, tmp_path, monkeypatch):
    import sys
    import types

    from armcal_ros.ros.node import CalibratorNode
    sent = []

    class Broadcaster:
        def __init__(self, node):
            self.node = node

        def sendTransform(self, transforms):
            sent.extend(transforms)
    node = CalibratorNode(context=ros_context, parameter_overrides=_overrides(tmp_path))
    try:
        monkeypatch.setitem(sys.modules, 'tf2_ros', None)      # import fails: one warning
        node._publish_tf([_camera()], conv.time_msg(0))
        node._publish_tf([_camera()], conv.time_msg(0))
        assert node._tf_warned and not sent
        monkeypatch.setitem(sys.modules, 'tf2_ros',
                            types.SimpleNamespace(StaticTransformBroadcaster=Broadcaster))
        node._publish_tf([_camera()], conv.time_msg(0))
        assert [(t.header.frame_id, t.child_frame_id) for t in sent] == \
            [('base_link', 'cam1_optical_frame')]
        assert sent[0].transform.translation.x == pytest.approx(_camera().center[0])
    finally:
        node.close(solve_timeout=1.0)
        node.destroy_node()
