"""Serialized images: the header stamp read from CDR bytes, and deserialization on demand."""

import numpy as np
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import CompressedImage, Image

from armcal_ros.frontend.image_decode import decode_image_msg
from armcal_ros.ros.raw_message import header_fields, header_stamp_ns, LazyMessage


def _image(sec, nanosec, frame_id='cam0_optical_frame'):
    msg = Image(height=2, width=3, encoding='mono8', step=3, data=bytes(range(6)))
    msg.header.stamp.sec, msg.header.stamp.nanosec = sec, nanosec
    msg.header.frame_id = frame_id
    return msg


@pytest.mark.parametrize('sec,nanosec', [(0, 0), (1, 999_999_999), (1_700_000_000, 123),
                                         (2 ** 31 - 1, 5)])
def test_stamp_from_bytes_equals_the_header(sec, nanosec):
    raw = serialize_message(_image(sec, nanosec))
    assert header_stamp_ns(raw) == sec * 1_000_000_000 + nanosec


@pytest.mark.parametrize('frame_id', ['', 'c', 'camera1_color_optical_frame', 'x' * 300,
                                      'kamera_\u00f6'])
@pytest.mark.parametrize('mtype', [Image, CompressedImage])
def test_header_fields_from_bytes_equal_the_header(frame_id, mtype):
    msg = mtype()
    msg.header.stamp.sec, msg.header.stamp.nanosec = 1_700_000_000, 123_456_789
    msg.header.frame_id = frame_id
    assert header_fields(serialize_message(msg)) == (1_700_000_000, 123_456_789, frame_id)


def test_header_fields_refuse_a_frame_id_that_overruns_the_bytes():
    raw = serialize_message(_image(1, 2, frame_id='cam1_optical_frame'))
    with pytest.raises(ValueError, match='overruns'):
        header_fields(raw[:20])


def test_compressed_image_stamp_and_lazy_fields():
    msg = CompressedImage(format='png', data=b'\x89PNG')
    msg.header.stamp.sec, msg.header.stamp.nanosec = 42, 7
    lazy = LazyMessage(serialize_message(msg), CompressedImage)
    assert lazy.stamp_ns() == 42_000_000_007
    assert lazy.format == 'png' and bytes(lazy.data) == b'\x89PNG'
    assert lazy.stamp_ns() == 42_000_000_007      # from the message once deserialized


def test_lazy_image_decodes_like_the_message():
    lazy = LazyMessage(serialize_message(_image(3, 4)), Image)
    assert lazy._msg is None                      # nothing deserialized yet
    assert lazy.stamp_ns() == 3_000_000_004
    assert lazy._msg is None
    np.testing.assert_array_equal(decode_image_msg(lazy), decode_image_msg(_image(3, 4)))


@pytest.mark.parametrize('raw,words', [(b'\x00\x01\x00\x00\x01', 'too short'),
                                       (b'\x07\x07\x00\x00' + bytes(12), 'encapsulation'),
                                       (b'\x00\x01\x00\x00' + b'\xff' * 12, 'not a valid')])
def test_bad_bytes_are_refused_with_the_reason(raw, words):
    with pytest.raises(ValueError, match=words):
        header_stamp_ns(raw)


def test_truncated_payload_fails_on_first_use_not_before():
    raw = serialize_message(_image(1, 2))[:30]
    lazy = LazyMessage(raw, Image)
    assert lazy.stamp_ns() == 1_000_000_002
    with pytest.raises(Exception):
        decode_image_msg(lazy)
