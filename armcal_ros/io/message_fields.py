"""Fields of ROS messages read by duck typing: rosbags' dataclasses and rclpy's messages alike."""

import numpy as np

from armcal_ros.core.camera import Camera


def stamp_ns(header_stamp):
    """Return a builtin_interfaces/Time as integer nanoseconds."""
    return int(header_stamp.sec) * 1_000_000_000 + int(header_stamp.nanosec)


def pose_from_msg(msg):
    """Return (translation (3,), quaternion xyzw (4,)) of a PoseStamped or TransformStamped."""
    if hasattr(msg, 'pose'):
        p, o = msg.pose.position, msg.pose.orientation
    elif hasattr(msg, 'transform'):
        p, o = msg.transform.translation, msg.transform.rotation
    else:
        raise ValueError(f'{type(msg).__name__} is neither a PoseStamped nor a '
                         'TransformStamped')
    return (p.x, p.y, p.z), (o.x, o.y, o.z, o.w)


def camera_from_camera_info(msg, name='camera') -> Camera:
    """
    Read a sensor_msgs/CameraInfo into a :class:`Camera` (identity pose), as a consumer would.

    Raises ValueError for an uncalibrated message (K[0] == 0), or a distortion model other
    than plumb_bob with non-zero coefficients (with all of them zero every model is the
    pinhole: rectified images).
    """
    K = np.asarray(msg.k, float).reshape(3, 3)
    if K[0, 0] == 0:
        raise ValueError(f'camera_info of {name}: K[0] == 0 means uncalibrated')
    d_all = np.asarray(msg.d, float).reshape(-1)
    if msg.distortion_model != 'plumb_bob' and np.any(d_all != 0):
        raise ValueError(f'camera_info of {name}: distortion_model {msg.distortion_model!r} '
                         'is not plumb_bob and its coefficients are not zero')
    d = np.zeros(5)
    if msg.distortion_model == 'plumb_bob':
        d[:min(5, d_all.size)] = d_all[:5]
    return Camera(name, int(msg.width), int(msg.height), K[0, 0], K[1, 1], K[0, 2], K[1, 2], d)


def camera_info_topic(image_topic):
    """
    Return the CameraInfo topic beside an image topic (image_transport's convention).

    ``/ns/image_raw`` and ``/ns/image_raw/compressed`` -> ``/ns/camera_info``.
    """
    t = image_topic.rstrip('/')
    if t.endswith('/compressed'):
        t = t[:-len('/compressed')]
    base = t.rpartition('/')[0]
    return f'{base}/camera_info'
