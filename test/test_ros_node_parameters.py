"""
The node's parameters on a real rclpy node without DDS traffic: descriptors, checks, TF.

The node is built in the test's process with parameter overrides, in the module's own ROS
environment (the ``ros_env`` fixture of conftest.py).
"""
import pytest

from armcal_ros.params import BY_NAME, PARAMS
from armcal_ros.ros import conversions as conv
from helpers.cameras import camera
from helpers.params_files import PUMA_URDF

pytestmark = pytest.mark.timeout(60)


@pytest.fixture
def ros_context(ros_env):
    import rclpy
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    ctx.try_shutdown()


def _overrides(tmp_path, **extra):
    from rclpy.parameter import Parameter
    values = dict(robot_description_file=PUMA_URDF, marker_link='marker',
                  output_dir=str(tmp_path / 'out'), resume=False)
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
    (dict(pixel_sigma='one'), ['pixel_sigma', 'double']),
    (dict(output_dir='/proc/armcal_out'), ['output_dir', '/proc/armcal_out']),
    (dict(pixel_sigma=1e300), ['pixel_sigma', '50']),
    (dict(point_sigma=float('nan')), ['point_sigma', 'nan']),
    (dict(marker_offset=[0.0, float('inf'), 0.0]), ['marker_offset', 'finite']),
    (dict(pose_topic='/flange_pose', noise_model='kinematic'), ['noise_model', 'pose_topic']),
    (dict(intrinsics_mode=['prior'], intrinsics_files=['a.yaml'] * 3),
     ['intrinsics_mode', 'intrinsics_sigma_px']),
    (dict(intrinsics_mode=['fixed'], intrinsics_files=['/nope.yaml'] * 3),
     ['intrinsics_files', 'camera cam1', '/nope.yaml']),
])
def test_bad_parameters_refuse_the_start(ros_context, tmp_path, extra, words):
    from armcal_ros.ros.node import CalibratorNode, ParameterError
    with pytest.raises(ParameterError) as err:
        CalibratorNode(context=ros_context, parameter_overrides=_overrides(tmp_path, **extra))
    for w in words:
        assert w in str(err.value)


def test_an_integer_is_a_valid_double_at_start_and_at_runtime(ros_context, tmp_path):
    """One rule with the offline CLI, which reads `pixel_sigma: 1` as 1.0."""
    from rclpy.parameter import Parameter

    from armcal_ros.ros.node import CalibratorNode
    from armcal_ros.settings import settings_from_values
    node = CalibratorNode(context=ros_context, parameter_overrides=_overrides(
        tmp_path, pixel_sigma=1, marker_offset=[0, 0, 1]))
    try:
        assert node.engine.settings.solver.pixel_sigma == 1.0
        assert isinstance(node.values['pixel_sigma'], float)
        assert node.values['marker_offset'] == [0.0, 0.0, 1.0]
        r = node.set_parameters([Parameter('point_sigma', value=1)])[0]
        assert r.successful, r.reason
        assert node.values['point_sigma'] == 1.0
        r = node.set_parameters([Parameter('point_sigma', value='x')])[0]
        assert not r.successful and 'point_sigma' in r.reason and 'double' in r.reason
        # The same values through the CLI's path give the same settings.
        assert settings_from_values(dict(node.values)).solver.pixel_sigma == 1.0
    finally:
        node.close(solve_timeout=1.0)
        node.destroy_node()


def test_an_absurdly_large_image_is_counted_and_never_queued(ros_context, tmp_path):
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Image

    from armcal_ros.ros.node import CalibratorNode
    node = CalibratorNode(context=ros_context, parameter_overrides=_overrides(tmp_path))

    def raw(w, h):
        return serialize_message(Image(width=w, height=h, step=w, encoding='mono8',
                                       data=bytes(w * h)))
    try:
        node.queue.close()          # nothing is taken out: the queue shows what was put in
        callback = node._image_callback('cam1', Image)
        sizes = []
        node.queue.put = lambda kind, item, **_: sizes.append(len(item[1]._raw))
        callback(raw(640, 480))
        callback(raw(4000, 2000))       # 8 MB after 0.3 MB frames
        callback(raw(640, 480))
        assert sizes == [len(raw(640, 480))] * 2
        assert node.node_state().input_counts['image_oversize'] == 1
    finally:
        node.close(solve_timeout=1.0)
        node.destroy_node()


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


def test_static_tf_as_tf2_msgs_and_one_warning_without_it(ros_context, tmp_path, monkeypatch):
    import sys
    from types import SimpleNamespace

    from armcal_ros.ros.node import CalibratorNode
    node = CalibratorNode(context=ros_context, parameter_overrides=_overrides(tmp_path))
    sent = []
    monkeypatch.setattr(node, '_publish', lambda pub, msg: sent.append((pub, msg)))
    cal = SimpleNamespace(cameras={'cam1': SimpleNamespace(camera=camera())})
    try:
        monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', None)      # import fails: one warning
        node._publish_tf(cal, conv.time_msg(0))
        node._publish_tf(cal, conv.time_msg(0))
        assert node._tf_warned and not sent
        monkeypatch.delitem(sys.modules, 'tf2_msgs.msg')
        pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs not built (Makefile)')
        node.engine.frame_ids['cam1'] = 'cam1_color_optical_frame'
        node._publish_tf(cal, conv.time_msg(0))
        (pub, msg), = sent
        assert pub.topic_name == '/tf_static'
        assert type(msg).__module__.startswith('tf2_msgs.msg')
        assert [(t.header.frame_id, t.child_frame_id) for t in msg.transforms] == \
            [('base_link', 'cam1_color_optical_frame')]
        assert msg.transforms[0].transform.translation.x == pytest.approx(camera().center[0])
    finally:
        node.close(solve_timeout=1.0)
        node.destroy_node()


def test_given_intrinsics_reach_the_engine(ros_context, tmp_path):
    from armcal_ros.core.camera import Camera
    from armcal_ros.io.calib_files import write_camera_info
    from armcal_ros.ros.node import CalibratorNode
    files = []
    for k in range(3):
        f = tmp_path / f'cam{k + 1}.yaml'
        write_camera_info(str(f), Camera(f'cam{k + 1}', 640, 480, 800.0 + k, 800.0, 320, 240))
        files.append(str(f))
    node = CalibratorNode(context=ros_context, parameter_overrides=_overrides(
        tmp_path, intrinsics_mode=['fixed', 'estimate', 'prior'], intrinsics_files=files,
        intrinsics_sigma_px=2.0))
    try:
        given = node.engine.settings.solver.intrinsics
        assert sorted(given) == ['cam1', 'cam3']
        assert given['cam1'].mode == 'fixed' and given['cam3'].sigma == (2.0,) * 4
        assert given['cam3'].intrinsics[0] == 802.0
    finally:
        node.close(solve_timeout=1.0)
        node.destroy_node()
