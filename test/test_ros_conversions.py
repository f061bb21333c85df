"""Messages the node publishes: CameraInfo, poses, TF and markers (no DDS traffic)."""
import cv2
import numpy as np
import pytest

from armcal_ros.io.message_fields import camera_from_camera_info
from armcal_ros.ros import conversions as conv
from helpers.cameras import camera, points

pytestmark = pytest.mark.timeout(60)


def test_camera_info_follows_the_conventions():
    cam = camera()
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
    X = points()
    uv, _ = cv2.projectPoints(X, cam.rvec, cam.translation, K, np.asarray(msg.d))
    np.testing.assert_allclose(uv.reshape(-1, 2), cam.project(X), atol=1e-9)
    back = camera_from_camera_info(msg, 'cam1')
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.dist, cam.dist)


def test_camera_from_camera_info_refuses_uncalibrated_and_other_models():
    msg = conv.camera_info_msg(camera(), conv.time_msg(0))
    msg.distortion_model = 'equidistant'
    with pytest.raises(ValueError, match='plumb_bob'):
        camera_from_camera_info(msg)
    # Rectified images: any model with zero coefficients is the pinhole.
    msg.d = [0.0] * 4
    assert np.all(camera_from_camera_info(msg).dist == 0)
    msg.k = [0.0] * 9
    with pytest.raises(ValueError, match='uncalibrated'):
        camera_from_camera_info(msg)


def test_pose_and_transform_are_T_base_camera():
    cam = camera()
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


def test_marker_array_has_samples_bias_and_frusta():
    cam = camera()
    nominal = points(10)
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
