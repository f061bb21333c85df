"""Bags written by armcal_ros.io.bag: rosbags reads them back, rclpy deserialises them."""

import numpy as np
import pytest

from rosbags.rosbag2 import Writer
from rosbags.rosbag2.enums import CompressionFormat, CompressionMode, StoragePlugin
from rosbags.typesys import get_types_from_msg, get_typestore, Stores

from armcal_ros.io.bag import (
    BagLosses, BagWriter, bag_topics, COMPRESSED_IMAGE, DeserializationError, IMAGE,
    image_to_array, iter_messages, iter_raw, JOINT_STATE,
)


def _image(channels=1):
    img = np.full((48, 64), 3, np.uint8)
    img[10:14, 20:25] = 200
    img[30, 40] = 77
    return img if channels == 1 else np.dstack([img, img // 2, img // 3])


def _write(path, storage='mcap', corrupt=False):
    with BagWriter(path, storage=storage) as w:
        for i in range(10):
            w.write_joint_state('/joint_states', 5 * 10**9 + i * 5_000_000, ['j2', 'j1', 'grip'],
                                [0.1 * i, -0.2, 0.01], velocities=[1.0, 0.0, 0.0])
        w.write_image('/cam1/image_raw', 5 * 10**9 + 1234, _image(), frame_id='cam1_optical_frame',
                      log_ns=5 * 10**9 + 9_000_000)
        w.write_image('/cam2/image_raw', 5 * 10**9 + 2000, _image(3), encoding='rgb8')
        w.write_compressed_image('/cam3/image_raw/compressed', 5 * 10**9 + 3000, _image(),
                                 fmt='png')
        w.write_compressed_image('/cam4/image_raw/compressed', 5 * 10**9 + 4000, _image(3),
                                 fmt='jpeg', encoding='bgr8', jpeg_quality=95)
        if corrupt:
            w.write_raw('/joint_states', JOINT_STATE, 6 * 10**9, b'\x00\x01\x00\x00\xff\xff')


@pytest.mark.parametrize('storage', ['mcap', 'sqlite3'])
def test_round_trip(tmp_path, storage):
    path = tmp_path / 'bag'
    _write(path, storage)
    assert (path / 'metadata.yaml').exists()
    topics = bag_topics(path)
    assert topics['/joint_states'] == (JOINT_STATE, 10)
    assert topics['/cam1/image_raw'] == (IMAGE, 1)
    assert topics['/cam3/image_raw/compressed'] == (COMPRESSED_IMAGE, 1)
    msgs = list(iter_messages(path))
    assert len(msgs) == 14
    js = [m for t, _, _, m in msgs if t == '/joint_states']
    assert list(js[3].name) == ['j2', 'j1', 'grip']
    np.testing.assert_allclose(js[3].position, [0.3, -0.2, 0.01])
    assert js[3].header.stamp.sec == 5 and js[3].header.stamp.nanosec == 15_000_000
    by_topic = {t: (mt, ts, m) for t, mt, ts, m in msgs}
    mt, ts, m = by_topic['/cam1/image_raw']
    assert ts == 5 * 10**9 + 9_000_000 and m.header.stamp.nanosec == 1234
    assert m.header.frame_id == 'cam1_optical_frame' and m.encoding == 'mono8'
    img, enc = image_to_array(mt, m)
    np.testing.assert_array_equal(img, _image())
    img, enc = image_to_array(*by_topic['/cam2/image_raw'][::2])
    assert enc == 'rgb8'
    np.testing.assert_array_equal(img, _image(3))
    mt, _, m = by_topic['/cam3/image_raw/compressed']
    assert m.format.startswith('mono8; png compressed')
    img, enc = image_to_array(mt, m)
    np.testing.assert_array_equal(img, _image())       # png is lossless
    mt, _, m = by_topic['/cam4/image_raw/compressed']
    assert m.format == 'bgr8; jpeg compressed bgr8'
    img, enc = image_to_array(mt, m)
    assert enc == 'bgr8' and img.shape == (48, 64, 3)
    assert np.abs(img.astype(int) - _image(3)).mean() < 6.0


def test_topic_filter_and_corrupt_messages_are_skippable(tmp_path):
    path = tmp_path / 'bag'
    _write(path, corrupt=True)
    raws = list(iter_raw(path, topics=['/joint_states']))
    assert len(raws) == 11 and {r.topic for r in raws} == {'/joint_states'}
    with pytest.raises(DeserializationError, match='/joint_states'):
        raws[-1].deserialize()
    errors = []
    good = list(iter_messages(path, topics=['/joint_states'], skip_errors=True,
                              on_error=errors.append))
    assert len(good) == 10 and len(errors) == 1
    with pytest.raises(DeserializationError):
        list(iter_messages(path, topics=['/joint_states']))


def test_writer_refuses_bad_input(tmp_path):
    with pytest.raises(ValueError, match='storage'):
        BagWriter(tmp_path / 'x', storage='rosbag1')
    with BagWriter(tmp_path / 'b') as w:
        with pytest.raises(ValueError, match='mono8'):
            w.write_image('/c', 1, np.zeros((4, 4, 3), np.uint8))
        with pytest.raises(ValueError, match='positions'):
            w.write_joint_state('/j', 1, ['a', 'b'], [0.0])
        w.write_joint_state('/j', 1, ['a'], [0.0])
        with pytest.raises(ValueError, match='already carries'):
            w.write_image('/j', 2, np.zeros((4, 4), np.uint8))


def test_rclpy_deserialises_the_raw_bytes(tmp_path, monkeypatch):
    monkeypatch.setenv('ROS_LOG_DIR', str(tmp_path / 'log'))
    serialization = pytest.importorskip('rclpy.serialization')
    from sensor_msgs.msg import CompressedImage, Image, JointState
    path = tmp_path / 'bag'
    _write(path)
    classes = {JOINT_STATE: JointState, IMAGE: Image, COMPRESSED_IMAGE: CompressedImage}
    seen = set()
    for raw in iter_raw(path):
        msg = serialization.deserialize_message(raw.rawdata, classes[raw.msgtype])
        seen.add(raw.msgtype)
        if raw.msgtype == IMAGE and msg.encoding == 'mono8':
            arr = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.height, msg.width)
            np.testing.assert_array_equal(arr, _image())
        if raw.msgtype == JOINT_STATE:
            assert list(msg.name) == ['j2', 'j1', 'grip']
    assert seen == set(classes)


@pytest.mark.parametrize('storage,mode', [('mcap', CompressionMode.NONE),
                                          ('mcap', CompressionMode.STORAGE),
                                          ('mcap', CompressionMode.MESSAGE),
                                          ('sqlite3', CompressionMode.NONE)])
def test_bags_rosbags_writes_read_alike(tmp_path, storage, mode):
    # rosbags' own writer: no checksums, and a message type Jazzy does not have (its definition
    # comes from the bag)
    ts = get_typestore(Stores.ROS2_JAZZY)
    ts.register(get_types_from_msg('int32 a\nstring b', 'my_msgs/msg/Thing'))
    thing = ts.types['my_msgs/msg/Thing']
    path = tmp_path / 'bag'
    writer = Writer(path, version=9, storage_plugin=(StoragePlugin.MCAP if storage == 'mcap'
                                                     else StoragePlugin.SQLITE3))
    writer.set_compression(mode, CompressionFormat.ZSTD)
    with writer as w:
        conn = w.add_connection('/thing', 'my_msgs/msg/Thing', typestore=ts)
        for i in range(5):
            w.write(conn, 100 - i, ts.serialize_cdr(thing(a=i, b=f'x{i}'), 'my_msgs/msg/Thing'))
    losses = BagLosses()
    msgs = list(iter_messages(path, losses=losses))
    assert [(t, m.a, m.b) for _, _, t, m in msgs] == [(100 - i, i, f'x{i}')
                                                      for i in reversed(range(5))]
    assert losses.complete and not losses.lost and bag_topics(path) == {
        '/thing': ('my_msgs/msg/Thing', 5)}
