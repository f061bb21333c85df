"""
Between the package's dataclasses and ROS 2 messages: CameraInfo, poses, TF, diagnostics, markers.

Conventions (those of camera drivers and image_geometry, so that every CameraInfo consumer
reads the output as a driver's):

- CameraInfo of a monocular camera: ``distortion_model`` ``plumb_bob`` with
  D = (k1, k2, p1, p2, k3) as OpenCV orders them, K row-major, R = identity, P = [K | 0];
  ``header.frame_id`` is the camera's optical frame (REP 103: x right, y down, z forward): the
  frame_id its images carry, ``<camera>_optical_frame`` when none is known.
- Poses are T_base_camera: the optical frame's origin and orientation in ``base_frame``, with
  the 6x6 covariance over (x, y, z, rotation about X, Y, Z) of the parent frame, row-major.
"""

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PointStamped, PoseWithCovarianceStamped, TransformStamped
from sensor_msgs.msg import CameraInfo
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from armcal_ros.core.camera import Camera
from armcal_ros.ros.status import bias_vectors, frustum_segments, Status

_LEVELS = {0: DiagnosticStatus.OK, 1: DiagnosticStatus.WARN, 2: DiagnosticStatus.ERROR}


def optical_frame(camera_name):
    """Return the optical frame id of a camera (REP 103 suffix)."""
    return f'{camera_name}_optical_frame'


def time_msg(t_ns):
    """Convert integer nanoseconds to builtin_interfaces/Time."""
    t_ns = int(t_ns)
    if t_ns < 0:
        raise ValueError(f't_ns must be >= 0, got {t_ns}')
    return Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)


def camera_info_msg(cam: Camera, stamp: Time, frame_id=None) -> CameraInfo:
    """Return the CameraInfo of a calibrated monocular camera (R = I, P = [K | 0], plumb_bob)."""
    K = cam.K
    msg = CameraInfo()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id or optical_frame(cam.name)
    msg.width = int(cam.width)
    msg.height = int(cam.height)
    msg.distortion_model = 'plumb_bob'
    msg.d = [float(v) for v in cam.dist]
    msg.k = [float(v) for v in K.ravel()]
    msg.r = [float(v) for v in np.eye(3).ravel()]
    msg.p = [float(v) for v in np.hstack([K, np.zeros((3, 1))]).ravel()]
    return msg


def uncalibrated_camera_info_msg(name, width, height, stamp: Time,
                                 frame_id=None) -> CameraInfo:
    """
    Return the CameraInfo of a camera with no calibration: D, K, R, P zero.

    sensor_msgs/CameraInfo: "If the camera is uncalibrated, the matrices D, K, R, P should be
    left zeroed out"; image_geometry and image_proc then treat the camera as uncalibrated.
    """
    msg = CameraInfo()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id or optical_frame(name)
    msg.width = int(width)
    msg.height = int(height)
    msg.distortion_model = 'plumb_bob'
    msg.d = [0.0] * 5
    msg.k = [0.0] * 9
    msg.r = [0.0] * 9
    msg.p = [0.0] * 12
    return msg


def pose_msg(cam: Camera, covariance, base_frame, stamp: Time) -> PoseWithCovarianceStamped:
    """Return T_base_camera of ``cam`` with its 6x6 covariance."""
    t, q = cam.pose_in_world()
    cov = np.asarray(covariance, float)
    if cov.shape != (6, 6):
        raise ValueError(f'covariance must be 6x6, got {cov.shape}')
    msg = PoseWithCovarianceStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = base_frame
    p = msg.pose.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in t)
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (float(v) for v in q)
    msg.pose.covariance = [float(v) for v in cov.ravel()]
    return msg


def camera_from_pose(intrinsics: Camera, msg) -> Camera:
    """Combine a Camera's intrinsics with the pose of a PoseWithCovarianceStamped (T_base_cam)."""
    p = msg.pose.pose
    t = [p.position.x, p.position.y, p.position.z]
    q = [p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w]
    return Camera.from_pose_in_world(intrinsics.name, intrinsics.width, intrinsics.height,
                                     intrinsics.K, intrinsics.dist, t, q)


def transform_msg(cam: Camera, base_frame, stamp: Time, child_frame_id=None) -> TransformStamped:
    """Return the static transform base_frame -> the camera's optical frame (T_base_camera)."""
    t, q = cam.pose_in_world()
    msg = TransformStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = base_frame
    msg.child_frame_id = child_frame_id or optical_frame(cam.name)
    tr = msg.transform
    tr.translation.x, tr.translation.y, tr.translation.z = (float(v) for v in t)
    tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w = (float(v) for v in q)
    return msg


def point_stamped_msg(point, frame_id, stamp: Time) -> PointStamped:
    """Return a PointStamped (published for each stored sample)."""
    msg = PointStamped()
    msg.header.stamp = stamp
    msg.header.frame_id = frame_id
    msg.point.x, msg.point.y, msg.point.z = (float(v) for v in np.asarray(point).reshape(3))
    return msg


def diagnostic_array_msg(statuses, stamp: Time) -> DiagnosticArray:
    """Build a DiagnosticArray from :class:`~armcal_ros.ros.status.Status` records."""
    msg = DiagnosticArray()
    msg.header.stamp = stamp
    for s in statuses:
        if not isinstance(s, Status):
            raise ValueError(f'statuses must hold Status records, got {type(s).__name__}')
        d = DiagnosticStatus(level=_LEVELS[s.level], name=s.name, message=s.message,
                             hardware_id=s.hardware_id)
        d.values = [KeyValue(key=str(k), value=str(v)) for k, v in s.values.items()]
        msg.status.append(d)
    return msg


def diagnostic_values(msg: DiagnosticArray, name):
    """Return {key: value} of the status called ``name`` in a DiagnosticArray (or None)."""
    for s in msg.status:
        if s.name == name:
            return {kv.key: kv.value for kv in s.values}
    return None


def _points(arr):
    return [Point(x=float(a), y=float(b), z=float(c))
            for a, b, c in np.asarray(arr, float).reshape(-1, 3)]


def _marker(ns, mid, mtype, frame, stamp, rgba, scale):
    m = Marker()
    m.header.frame_id = frame
    m.header.stamp = stamp
    m.ns, m.id, m.type, m.action = ns, mid, mtype, Marker.ADD
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = float(scale)
    m.color = ColorRGBA(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
    return m


def marker_array_msg(base_frame, stamp: Time, samples, cameras=(), estimated=None,
                     bias_scale=50.0, frustum_depth=0.15) -> MarkerArray:
    """
    Build the markers for RViz: samples, bias vectors and camera frusta in ``base_frame``.

    ``samples`` (N, 3) nominal sample positions; ``estimated`` (M, 3) the adjustment's
    estimated points (or None); each bias X_est - X_nominal is drawn from the nominal point
    magnified ``bias_scale`` times (it is about a millimetre), in namespace
    ``bias_x<scale>``.  Markers of a namespace with nothing to show are deleted.
    """
    out = MarkerArray()
    samples = np.asarray(samples, float).reshape(-1, 3)
    m = _marker('samples', 0, Marker.SPHERE_LIST, base_frame, stamp, (0.1, 0.6, 1.0, 0.9),
                0.006)
    m.points = _points(samples)
    if not len(samples):
        m.action = Marker.DELETE
    out.markers.append(m)
    ns = f'bias_x{bias_scale:g}'
    m = _marker(ns, 0, Marker.LINE_LIST, base_frame, stamp, (1.0, 0.3, 0.1, 1.0), 0.0015)
    if estimated is not None and len(samples):
        segs = bias_vectors(samples, estimated)
        if len(segs):
            segs = segs.copy()
            segs[:, 1] = segs[:, 0] + bias_scale * (segs[:, 1] - segs[:, 0])
            m.points = _points(segs)
    if not m.points:
        m.action = Marker.DELETE
    out.markers.append(m)
    for j, cam in enumerate(cameras):
        f = _marker('frusta', j, Marker.LINE_LIST, base_frame, stamp, (0.2, 0.9, 0.2, 1.0),
                    0.004)
        f.points = _points(frustum_segments(cam, frustum_depth))
        out.markers.append(f)
        t = _marker('camera_names', j, Marker.TEXT_VIEW_FACING, base_frame, stamp,
                    (1.0, 1.0, 1.0, 1.0), 0.05)
        c = cam.center
        pos = t.pose.position
        pos.x, pos.y, pos.z = float(c[0]), float(c[1]), float(c[2]) + 0.05
        t.text = cam.name
        out.markers.append(t)
    return out
