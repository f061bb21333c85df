"""Fields of ROS messages read by duck typing: rosbags' dataclasses and rclpy's messages alike."""

import numpy as np

from armcal_ros.core.camera import Camera
from armcal_ros.io.calib_files import camera_from_info_file, CameraInfoFile

#: What to do about a CameraInfo whose distortion model armcal cannot use.
MESSAGE_ADVICE = ('armcal fits plumb_bob (k1, k2, p1, p2, k3): calibrate the lens with a '
                  'plumb_bob model, or set intrinsics_mode to estimate for this camera and let '
                  'armcal estimate its intrinsics')


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

    Any distortion model is read, and used by the rule of a calibration file
    (:func:`armcal_ros.io.calib_files.camera_from_info_file`): plumb_bob, or a model whose
    coefficients beyond plumb_bob's five are zero (rational_polynomial with k4-k6 zero; with
    all of them zero every model is the pinhole: rectified images).  Raises ValueError for an
    uncalibrated message (K[0] == 0), and for a model armcal cannot use, naming it and its
    non-zero coefficients.
    """
    K = np.asarray(msg.k, dtype=float).reshape(3, 3)
    r, p = getattr(msg, 'r', None), getattr(msg, 'p', None)
    info = CameraInfoFile(
        camera_name=name, width=int(msg.width), height=int(msg.height), K=K,
        distortion_model=str(msg.distortion_model),
        D=np.asarray(msg.d, dtype=float).reshape(-1),
        R=np.eye(3) if r is None or len(r) != 9 else np.asarray(r, dtype=float).reshape(3, 3),
        P=(np.hstack([K, np.zeros((3, 1))]) if p is None or len(p) != 12
           else np.asarray(p, dtype=float).reshape(3, 4)),
        source=f'camera_info of {name}')
    return camera_from_info_file(info, name, advice=MESSAGE_ADVICE)


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
