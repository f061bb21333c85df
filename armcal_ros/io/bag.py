"""
A thin layer over ``rosbags`` (0.11) for writing rosbag2 bags without ROS, and the reading API.

Writing: :class:`BagWriter` writes real rosbag2 bags (metadata version 9, CDR) in ``mcap`` (the
default) or ``sqlite3`` storage, with message definitions from the Jazzy typestore
(``Stores.ROS2_JAZZY``), so ``ros2 bag`` and rclpy read them.  It knows the three message types the
calibrator consumes: ``sensor_msgs/msg/JointState``, ``sensor_msgs/msg/Image`` and
``sensor_msgs/msg/CompressedImage``, each with a proper ``std_msgs/Header``.  It checksums what it
writes (each mcap chunk's CRC, a CRC per sqlite3 message), so a reader can tell a corrupted
message from a good one.

Compression: rosbags 0.11 supports zstd only.  For mcap it offers chunk compression
(``CompressionMode.STORAGE``: each ~1 MiB chunk is zstd-compressed inside the .mcap file, which is
what ``ros2 bag record --storage-preset-profile zstd_fast`` produces and what every mcap reader
decodes); ``MESSAGE`` (per message) and ``FILE`` (whole file) modes exist too but are deprecated in
rosbag2 itself.  ``compress=True`` selects chunk compression for mcap and is ignored for sqlite3.

Reading (:func:`iter_raw`, :func:`iter_messages`, :func:`bag_topics`, with every lost message
of a corrupt bag counted) lives in :mod:`armcal_ros.io.bag_reading` and is re-exported here.
"""

from pathlib import Path
import struct
import zlib

import cv2
import numpy as np
from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from scipy.spatial.transform import Rotation

from armcal_ros.io.bag_reading import (  # noqa: F401 - the reading API, re-exported
    _message_crc, _U64, bag_topics, BagLosses, BagLossWarning, BagReadError, CRC_TABLE,
    DeserializationError, iter_messages, iter_raw, jazzy_typestore, RawMessage, STORAGES)

JOINT_STATE = 'sensor_msgs/msg/JointState'
IMAGE = 'sensor_msgs/msg/Image'
COMPRESSED_IMAGE = 'sensor_msgs/msg/CompressedImage'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
TRANSFORM_STAMPED = 'geometry_msgs/msg/TransformStamped'

IMAGE_ENCODINGS = ('mono8', 'rgb8', 'bgr8')
COMPRESSED_FORMATS = ('png', 'jpeg')


def split_stamp(t_ns):
    """Split integer nanoseconds into (sec, nanosec) as builtin_interfaces/Time wants."""
    t_ns = int(t_ns)
    if t_ns < 0:
        raise ValueError(f't_ns must be >= 0, got {t_ns}')
    return t_ns // 1_000_000_000, t_ns % 1_000_000_000


def stamp_to_ns(stamp):
    """builtin_interfaces/Time (anything with sec and nanosec) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def encode_compressed(image, fmt='png', encoding='mono8', jpeg_quality=90, png_level=3):
    """
    Encode an image array as image_transport's ``compressed`` plugin does.

    Returns (format string, bytes).  The format string follows compressed_image_transport:
    ``'<encoding>; <png|jpeg> compressed <target>'`` where the target is ``bgr8`` for colour
    (OpenCV writes BGR files) and empty for mono.
    """
    if fmt not in COMPRESSED_FORMATS:
        raise ValueError(f'fmt must be one of {COMPRESSED_FORMATS}, got {fmt!r}')
    image = _check_image(image, encoding)
    target = ''
    if encoding == 'rgb8':
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
        target = 'bgr8'
    elif encoding == 'bgr8':
        target = 'bgr8'
    if fmt == 'png':
        ok, buf = cv2.imencode('.png', image, [cv2.IMWRITE_PNG_COMPRESSION, int(png_level)])
    else:
        ok, buf = cv2.imencode('.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:
        raise ValueError(f'cv2 could not encode a {image.shape} image as {fmt}')
    return f'{encoding}; {fmt} compressed {target}', buf.tobytes()


def _check_image(image, encoding):
    image = np.asarray(image)
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f'encoding must be one of {IMAGE_ENCODINGS}, got {encoding!r}')
    if image.dtype != np.uint8:
        raise ValueError(f'image must be uint8, got {image.dtype}')
    if encoding == 'mono8' and image.ndim != 2:
        raise ValueError(f'a mono8 image must have shape (H, W), got {image.shape}')
    if encoding != 'mono8' and (image.ndim != 3 or image.shape[2] != 3):
        raise ValueError(f'a {encoding} image must have shape (H, W, 3), got {image.shape}')
    return np.ascontiguousarray(image)


class BagWriter:
    """
    Write a rosbag2 bag with rosbags; use as a context manager.

    ``path`` is the bag directory (it must not exist).  ``storage`` is ``'mcap'`` or
    ``'sqlite3'``; ``compress`` enables zstd chunk compression for mcap.  Each ``write_*`` takes
    the header stamp ``stamp_ns`` and, optionally, the bag (receive) time ``log_ns``, which
    defaults to the stamp.
    """

    def __init__(self, path, storage='mcap', compress=True, typestore=None):
        if storage not in STORAGES:
            raise ValueError(f'storage must be one of {STORAGES}, got {storage!r}')
        self.path = Path(path)
        self.storage = storage
        self.typestore = typestore or jazzy_typestore()
        plugin = StoragePlugin.MCAP if storage == 'mcap' else StoragePlugin.SQLITE3
        self._writer = Writer(self.path, version=9, storage_plugin=plugin)
        if compress and storage == 'mcap':
            self._writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
        self._connections = {}
        self._types = self.typestore.types
        self.counts = {}

    def __enter__(self):
        """Open the bag."""
        self._writer.open()
        self._finish = _add_checksums(self._writer.storage)
        return self

    def __exit__(self, exc_type, exc, tb):
        """Close the bag (writing its index and metadata), or abort it on an exception."""
        result = self._writer.__exit__(exc_type, exc, tb)
        if exc_type is None and self._finish is not None:
            self._finish()
        return result

    def connection(self, topic, msgtype):
        """Return (creating once) the connection for ``topic`` with ``msgtype``."""
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=self.typestore)
            self._connections[topic] = conn
            self.counts[topic] = 0
        elif conn.msgtype != msgtype:
            raise ValueError(f'topic {topic!r} already carries {conn.msgtype}, not {msgtype}')
        return conn

    def header(self, stamp_ns, frame_id=''):
        """Build a std_msgs/Header."""
        sec, nsec = split_stamp(stamp_ns)
        t = self._types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec)
        return self._types['std_msgs/msg/Header'](stamp=t, frame_id=frame_id)

    def write_message(self, topic, msgtype, log_ns, msg):
        """Serialise a rosbags message object and write it at bag time ``log_ns``."""
        conn = self.connection(topic, msgtype)
        self._writer.write(conn, int(log_ns), self.typestore.serialize_cdr(msg, msgtype))
        self.counts[topic] += 1

    def write_raw(self, topic, msgtype, log_ns, data):
        """Write already serialised CDR bytes (e.g. to copy or to corrupt a message in a test)."""
        conn = self.connection(topic, msgtype)
        self._writer.write(conn, int(log_ns), bytes(data))
        self.counts[topic] += 1

    def write_joint_state(self, topic, stamp_ns, names, positions, velocities=None,
                          efforts=None, log_ns=None, frame_id=''):
        """Write a sensor_msgs/JointState (velocity and effort empty unless given)."""
        names = [str(n) for n in names]
        pos = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1)
        if pos.size != len(names):
            raise ValueError(f'positions has {pos.size} values for {len(names)} names')
        vel = np.zeros(0) if velocities is None else np.ascontiguousarray(velocities, np.float64)
        eff = np.zeros(0) if efforts is None else np.ascontiguousarray(efforts, np.float64)
        for label, arr in (('velocities', vel), ('efforts', eff)):
            if arr.size not in (0, len(names)):
                raise ValueError(f'{label} must be empty or have {len(names)} values')
        msg = self._types[JOINT_STATE](header=self.header(stamp_ns, frame_id), name=names,
                                       position=pos, velocity=vel.reshape(-1),
                                       effort=eff.reshape(-1))
        self.write_message(topic, JOINT_STATE, stamp_ns if log_ns is None else log_ns, msg)

    def write_image(self, topic, stamp_ns, image, encoding='mono8', frame_id='', log_ns=None):
        """Write a sensor_msgs/Image from a uint8 array (H, W) mono8 or (H, W, 3) rgb8/bgr8."""
        image = _check_image(image, encoding)
        h, w = image.shape[:2]
        channels = 1 if image.ndim == 2 else 3
        msg = self._types[IMAGE](header=self.header(stamp_ns, frame_id), height=h, width=w,
                                 encoding=encoding, is_bigendian=0, step=w * channels,
                                 data=image.reshape(-1))
        self.write_message(topic, IMAGE, stamp_ns if log_ns is None else log_ns, msg)

    def write_pose(self, topic, msgtype, stamp_ns, T, frame_id, child_frame_id='',
                   log_ns=None):
        """
        Write a 4x4 pose as geometry_msgs/PoseStamped or TransformStamped (``msgtype``).

        ``frame_id`` is the parent frame; ``child_frame_id`` the moving one (TransformStamped).
        """
        types = self._types
        T = np.asarray(T, float)
        t = T[:3, 3]
        q = Rotation.from_matrix(T[:3, :3]).as_quat()
        quat = types['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3])
        header = self.header(stamp_ns, frame_id)
        if msgtype == POSE_STAMPED:
            msg = types[msgtype](header=header, pose=types['geometry_msgs/msg/Pose'](
                position=types['geometry_msgs/msg/Point'](x=t[0], y=t[1], z=t[2]),
                orientation=quat))
        elif msgtype == TRANSFORM_STAMPED:
            msg = types[msgtype](header=header, child_frame_id=child_frame_id,
                                 transform=types['geometry_msgs/msg/Transform'](
                                     translation=types['geometry_msgs/msg/Vector3'](
                                         x=t[0], y=t[1], z=t[2]), rotation=quat))
        else:
            raise ValueError(f'msgtype must be {POSE_STAMPED} or {TRANSFORM_STAMPED}, '
                             f'got {msgtype!r}')
        self.write_message(topic, msgtype, stamp_ns if log_ns is None else log_ns, msg)

    def write_encoded_image(self, topic, stamp_ns, data, fmt, frame_id='', log_ns=None):
        """Write already encoded bytes (a JPEG or PNG file's) as a sensor_msgs/CompressedImage."""
        msg = self._types[COMPRESSED_IMAGE](header=self.header(stamp_ns, frame_id), format=fmt,
                                            data=np.frombuffer(bytes(data), np.uint8))
        self.write_message(topic, COMPRESSED_IMAGE, stamp_ns if log_ns is None else log_ns, msg)

    def write_camera_info(self, topic, stamp_ns, K, dist, width, height, frame_id='',
                          log_ns=None):
        """Write a monocular plumb_bob sensor_msgs/CameraInfo (R = I, P = [K | 0])."""
        types = self._types
        K = np.asarray(K, float).reshape(3, 3)
        P = np.hstack([K, np.zeros((3, 1))])
        msg = types[CAMERA_INFO](
            header=self.header(stamp_ns, frame_id), height=int(height), width=int(width),
            distortion_model='plumb_bob', d=np.asarray(dist, float).reshape(-1),
            k=K.reshape(-1), r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0,
            binning_y=0, roi=types['sensor_msgs/msg/RegionOfInterest'](
                x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))
        self.write_message(topic, CAMERA_INFO, stamp_ns if log_ns is None else log_ns, msg)

    def write_compressed_image(self, topic, stamp_ns, image, fmt='png', encoding='mono8',
                               frame_id='', log_ns=None, jpeg_quality=90):
        """Encode ``image`` (png or jpeg) and write a sensor_msgs/CompressedImage."""
        format_string, data = encode_compressed(image, fmt, encoding, jpeg_quality)
        msg = self._types[COMPRESSED_IMAGE](header=self.header(stamp_ns, frame_id),
                                            format=format_string,
                                            data=np.frombuffer(data, np.uint8))
        self.write_message(topic, COMPRESSED_IMAGE, stamp_ns if log_ns is None else log_ns, msg)


def _add_checksums(storage):
    """
    Make a rosbags storage writer checksum what it writes; return what to run once it is closed.

    mcap: each chunk's ``uncompressed_crc`` (rosbags writes 0, "not computed") becomes the CRC-32
    of its records, as the mcap C++ writer behind ``ros2 bag record`` writes it.  sqlite3: a
    :data:`CRC_TABLE` row per message.  A rosbags writer unlike 0.11's gets no checksums.
    """
    if hasattr(storage, 'compressor') and hasattr(storage, 'chunks'):
        compress, crcs = storage.compressor, []

        def compressor(data):
            crcs.append(zlib.crc32(data))
            return compress(data)

        def patch():
            if len(crcs) != len(storage.chunks):
                return
            with open(storage.path, 'r+b') as f:
                for index, crc in zip(storage.chunks, crcs):
                    f.seek(_U64.unpack_from(index.getvalue(), 16)[0] + 33)
                    f.write(struct.pack('<I', crc))
        storage.compressor = compressor
        return patch
    if hasattr(storage, 'cursor') and hasattr(storage, 'conn') and hasattr(storage, 'write'):
        storage.conn.execute(f'CREATE TABLE {CRC_TABLE}(id INTEGER PRIMARY KEY, '
                             'crc INTEGER NOT NULL)')
        write, cursor = storage.write, storage.cursor

        def write_with_crc(connection, timestamp, data):
            write(connection, timestamp, data)
            cursor.execute(f'INSERT INTO {CRC_TABLE} VALUES(?, ?)',
                           (cursor.lastrowid, _message_crc(connection.id, timestamp, data)))
        storage.write = write_with_crc
    return None


def image_to_array(msgtype, msg):
    """
    Decode an Image or CompressedImage message to (uint8 array, encoding).

    Mono images come back (H, W) ``mono8``; colour images (H, W, 3) in ``bgr8`` or ``rgb8`` as
    their message says (compressed colour images decode to ``bgr8``).
    """
    if msgtype == IMAGE:
        enc = msg.encoding
        if enc not in IMAGE_ENCODINGS:
            raise ValueError(f'unsupported image encoding {enc!r}')
        ch = 1 if enc == 'mono8' else 3
        data = np.asarray(msg.data, np.uint8)
        rows = data[:msg.height * msg.step].reshape(msg.height, msg.step)
        img = rows[:, :msg.width * ch]
        return (img if ch == 1 else img.reshape(msg.height, msg.width, 3)), enc
    if msgtype == COMPRESSED_IMAGE:
        buf = np.asarray(msg.data, np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f'cannot decode compressed image with format {msg.format!r}')
        if img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        return img, ('mono8' if img.ndim == 2 else 'bgr8')
    raise ValueError(f'msgtype must be {IMAGE} or {COMPRESSED_IMAGE}, got {msgtype!r}')
