"""Tests for sensor_msgs/Image and CompressedImage decoding."""

import array
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from armcal_ros.frontend.image_decode import (
    decode_compressed_image, decode_image_msg, decode_raw_image, encode_raw_image,
    ImageDecodeError)

H, W = 7, 10


@pytest.fixture
def rng():
    return np.random.default_rng(3)


def _decode(fields):
    return decode_raw_image(fields['encoding'], fields['height'], fields['width'],
                            fields['step'], fields['is_bigendian'], fields['data'])


@pytest.mark.parametrize('encoding', ['mono8', '8UC1'])
def test_mono8_round_trip_is_zero_copy(rng, encoding):
    img = rng.integers(0, 256, (H, W), dtype=np.uint8)
    fields = encode_raw_image(img, encoding)
    buf = bytearray(fields['data'])
    out = decode_raw_image(encoding, H, W, fields['step'], 0, buf)
    np.testing.assert_array_equal(out, img)
    assert out.dtype == np.uint8 and out.shape == (H, W)
    buf[0] = (int(buf[0]) + 1) % 256          # a view on the message buffer, not a copy
    assert out[0, 0] == buf[0]


@pytest.mark.parametrize('encoding', ['mono16', '16UC1'])
@pytest.mark.parametrize('big', [False, True])
def test_mono16_both_endiannesses(rng, encoding, big):
    img = rng.integers(0, 65536, (H, W), dtype=np.uint16)
    out = _decode(encode_raw_image(img, encoding, is_bigendian=big))
    assert out.dtype == np.uint16 and out.dtype.isnative
    np.testing.assert_array_equal(out, img)


def test_big_endian_bytes_are_read_big_endian():
    data = bytes([0x01, 0x02])
    assert decode_raw_image('mono16', 1, 1, 2, 1, data)[0, 0] == 0x0102
    assert decode_raw_image('mono16', 1, 1, 2, 0, data)[0, 0] == 0x0201


@pytest.mark.parametrize('encoding,to_bgr', [
    ('bgr8', lambda x: x), ('8UC3', lambda x: x), ('rgb8', lambda x: x[..., ::-1]),
    ('bgra8', lambda x: x[..., :3]), ('rgba8', lambda x: x[..., 2::-1]),
    ('8UC4', lambda x: x[..., :3])])
def test_colour_encodings_come_out_bgr(rng, encoding, to_bgr):
    channels = 4 if encoding in ('bgra8', 'rgba8', '8UC4') else 3
    img = rng.integers(0, 256, (H, W, channels), dtype=np.uint8)
    out = _decode(encode_raw_image(img, encoding))
    assert out.shape == (H, W, 3)
    np.testing.assert_array_equal(out, to_bgr(img))


def test_rgb16_big_endian(rng):
    img = rng.integers(0, 65536, (H, W, 3), dtype=np.uint16)
    out = _decode(encode_raw_image(img, 'rgb16', is_bigendian=True))
    np.testing.assert_array_equal(out, img[..., ::-1])


@pytest.mark.parametrize('encoding', ['mono8', 'bgr8', 'mono16', 'rgb8'])
def test_padded_step_is_skipped(rng, encoding):
    depth = 2 if '16' in encoding else 1
    shape = (H, W) if encoding.startswith('mono') else (H, W, 3)
    img = rng.integers(0, 2 ** (8 * depth), shape).astype(np.uint16 if depth == 2 else np.uint8)
    row = W * (1 if len(shape) == 2 else 3) * depth
    fields = encode_raw_image(img, encoding, step=row + 6)
    assert fields['step'] == row + 6
    out = _decode(fields)
    expected = img[..., ::-1] if encoding == 'rgb8' else img
    np.testing.assert_array_equal(out, expected)


@pytest.mark.parametrize('ros,bgr_index', [
    ('bayer_rggb8', {(0, 0): 2, (1, 1): 0}), ('bayer_bggr8', {(0, 0): 0, (1, 1): 2}),
    ('bayer_gbrg8', {(0, 1): 0, (1, 0): 2}), ('bayer_grbg8', {(0, 1): 2, (1, 0): 0})])
def test_bayer_patterns_demosaic_to_the_right_colour(ros, bgr_index):
    # A flat colour (B, G, R) = (30, 120, 220) sampled through each mosaic must come back.
    colour = np.array([30, 120, 220])
    mosaic = np.full((16, 16), colour[1], np.uint8)        # green everywhere else
    for (r, c), ch in bgr_index.items():
        mosaic[r::2, c::2] = colour[ch]
    out = _decode(encode_raw_image(mosaic, ros))
    assert out.shape == (16, 16, 3)
    np.testing.assert_allclose(out[4:-4, 4:-4].reshape(-1, 3).mean(axis=0), colour, atol=2)


@pytest.mark.parametrize('encoding', ['yuv422', 'yuv422_yuy2'])
def test_yuv422_flat_colour(encoding):
    bgr = np.zeros((4, 8, 3), np.uint8)
    bgr[:] = (40, 160, 90)
    yuv = np.zeros((4, 8, 2), np.uint8)
    # Build the 4:2:2 bytes by hand (BT.601 video range, as OpenCV decodes them):
    # U Y0 V Y1 (UYVY) or Y0 U Y1 V (YUYV).
    b, g, r = 40.0, 160.0, 90.0
    y = 16 + (65.481 * r + 128.553 * g + 24.966 * b) / 255
    u = 128 + (-37.797 * r - 74.203 * g + 112.0 * b) / 255
    v = 128 + (112.0 * r - 93.786 * g - 18.214 * b) / 255
    if encoding == 'yuv422':
        yuv[:, 0::2, 0], yuv[:, 0::2, 1], yuv[:, 1::2, 0], yuv[:, 1::2, 1] = u, y, v, y
    else:
        yuv[:, 0::2, 0], yuv[:, 0::2, 1], yuv[:, 1::2, 0], yuv[:, 1::2, 1] = y, u, y, v
    fields = dict(encoding=encoding, height=4, width=8, step=16, is_bigendian=0,
                  data=yuv.tobytes())
    out = _decode(fields)
    assert out.shape == (4, 8, 3)
    np.testing.assert_allclose(out.reshape(-1, 3).mean(axis=0), (b, g, r), atol=3)


def test_data_types_from_rclpy_and_rosbags(rng):
    img = rng.integers(0, 256, (H, W), dtype=np.uint8)
    as_array = array.array('B', img.tobytes())               # rclpy
    as_ndarray = np.frombuffer(img.tobytes(), np.uint8)      # rosbags
    for data in (as_array, as_ndarray, img.tobytes(), list(img.tobytes())):
        msg = SimpleNamespace(encoding='mono8', height=H, width=W, step=W, is_bigendian=0,
                              data=data)
        np.testing.assert_array_equal(decode_image_msg(msg), img)


@pytest.mark.parametrize('fields,match', [
    (dict(encoding='mono8', height=H, width=W, step=W, data=bytes(H * W - 1)), 'expected'),
    (dict(encoding='mono8', height=H, width=W, step=W, data=bytes(H * W + 3)), 'expected'),
    (dict(encoding='rgb8', height=H, width=W, step=W * 3 - 1, data=bytes(H * (W * 3 - 1))),
     'shorter'),
    (dict(encoding='mono16', height=H, width=W, step=2 * W + 1, data=bytes(H * (2 * W + 1))),
     'multiple'),
    (dict(encoding='32FC7', height=H, width=W, step=W, data=bytes(H * W)), 'unsupported'),
    (dict(encoding='mono8', height=0, width=W, step=W, data=b''), 'positive'),
])
def test_inconsistent_messages_raise_image_decode_error(fields, match):
    with pytest.raises(ImageDecodeError, match=match):
        decode_raw_image(fields['encoding'], fields['height'], fields['width'], fields['step'],
                         0, fields['data'])


def test_compressed_png_jpeg_and_16_bit(rng):
    img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    ok, png = cv2.imencode('.png', img)
    assert ok
    msg = SimpleNamespace(format='png', data=array.array('B', png.tobytes()))
    np.testing.assert_array_equal(decode_image_msg(msg), img)
    gray16 = rng.integers(0, 65536, (H, W), dtype=np.uint16)
    ok, png16 = cv2.imencode('.png', gray16)
    out = decode_compressed_image('16UC1; png compressed', png16)
    assert out.dtype == np.uint16
    np.testing.assert_array_equal(out, gray16)
    smooth = np.tile(np.linspace(0, 255, 64, dtype=np.uint8), (48, 1))
    ok, jpg = cv2.imencode('.jpg', smooth, [cv2.IMWRITE_JPEG_QUALITY, 95])
    out = decode_compressed_image('mono8; jpeg compressed mono8', jpg.tobytes())
    assert out.shape == (48, 64)
    assert np.abs(out.astype(int) - smooth).max() <= 4


def test_compressed_depth_header_is_skipped(rng):
    depth = rng.integers(0, 5000, (H, W), dtype=np.uint16)
    ok, png = cv2.imencode('.png', depth)
    data = bytes(12) + png.tobytes()
    out = decode_compressed_image('16UC1; compressedDepth png', data)
    np.testing.assert_array_equal(out, depth)


def test_corrupt_compressed_raises():
    with pytest.raises(ImageDecodeError, match='imdecode'):
        decode_compressed_image('jpeg', b'\xff\xd8 definitely not a jpeg')
    with pytest.raises(ImageDecodeError, match='no data'):
        decode_compressed_image('jpeg', b'')


def test_non_image_object_raises():
    with pytest.raises(ImageDecodeError, match='neither'):
        decode_image_msg(SimpleNamespace(height=1))
