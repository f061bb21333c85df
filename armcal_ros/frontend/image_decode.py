"""
Decoding of ``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` payloads into numpy arrays.

This is the one place in the package that knows image encodings.  The functions take the plain
message fields, so they work with rclpy messages (``data`` is ``array.array('B')``), rosbags
dataclasses (``data`` is a uint8 ndarray) and bytes alike.

Output convention (what the detectors expect):

- single-channel encodings -> (H, W) array of the encoding's depth (uint8 or uint16, native
  byte order);
- colour encodings -> (H, W, 3) **BGR** (OpenCV order), alpha dropped, Bayer mosaics demosaiced,
  YUV 4:2:2 converted.

Raw images are read with ``np.frombuffer`` and row padding (``step``) is skipped with a strided
view, so mono and BGR images with native byte order are returned without copying.  The returned
array may therefore be read-only and non-contiguous; callers that write into it must copy.
"""

import numpy as np

import cv2


class ImageDecodeError(ValueError):
    """An image message cannot be decoded (unknown encoding, inconsistent size, corrupt data)."""


# encoding -> (channels, bytes per channel, conversion to the output convention or None)
_RAW_ENCODINGS = {
    'mono8': (1, 1, None),
    '8uc1': (1, 1, None),
    'mono16': (1, 2, None),
    '16uc1': (1, 2, None),
    'bgr8': (3, 1, None),
    '8uc3': (3, 1, None),
    'rgb8': (3, 1, cv2.COLOR_RGB2BGR),
    'bgra8': (4, 1, cv2.COLOR_BGRA2BGR),
    '8uc4': (4, 1, cv2.COLOR_BGRA2BGR),
    'rgba8': (4, 1, cv2.COLOR_RGBA2BGR),
    'bgr16': (3, 2, None),
    '16uc3': (3, 2, None),
    'rgb16': (3, 2, cv2.COLOR_RGB2BGR),
    'bgra16': (4, 2, cv2.COLOR_BGRA2BGR),
    'rgba16': (4, 2, cv2.COLOR_RGBA2BGR),
    # ROS names the Bayer pattern by its first row; OpenCV by the second row's last two pixels,
    # hence the apparent swap (the same table as cv_bridge).
    'bayer_rggb8': (1, 1, cv2.COLOR_BayerBG2BGR),
    'bayer_bggr8': (1, 1, cv2.COLOR_BayerRG2BGR),
    'bayer_gbrg8': (1, 1, cv2.COLOR_BayerGR2BGR),
    'bayer_grbg8': (1, 1, cv2.COLOR_BayerGB2BGR),
    'bayer_rggb16': (1, 2, cv2.COLOR_BayerBG2BGR),
    'bayer_bggr16': (1, 2, cv2.COLOR_BayerRG2BGR),
    'bayer_gbrg16': (1, 2, cv2.COLOR_BayerGR2BGR),
    'bayer_grbg16': (1, 2, cv2.COLOR_BayerGB2BGR),
    # 4:2:2, two bytes per pixel.  ROS 'yuv422' is UYVY byte order, 'yuv422_yuy2' is YUYV.
    'yuv422': (2, 1, cv2.COLOR_YUV2BGR_UYVY),
    'uyvy': (2, 1, cv2.COLOR_YUV2BGR_UYVY),
    'yuv422_yuy2': (2, 1, cv2.COLOR_YUV2BGR_YUYV),
    'yuyv': (2, 1, cv2.COLOR_YUV2BGR_YUYV),
}

SUPPORTED_ENCODINGS = tuple(sorted(_RAW_ENCODINGS))

# compressedDepth (image_transport plugin) prefixes the PNG with a 12-byte ConfigHeader
# (int32 format, float32 depthParam[2]).
_COMPRESSED_DEPTH_HEADER = 12


def _as_byte_buffer(data, what):
    """Return a zero-copy uint8 view of ``data`` (bytes, bytearray, array('B'), ndarray, list)."""
    if isinstance(data, np.ndarray):
        if data.dtype != np.uint8:
            raise ImageDecodeError(f'{what} must hold uint8 bytes, got dtype {data.dtype}')
        return data.reshape(-1)
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except TypeError:
        try:
            return np.asarray(data, dtype=np.uint8).reshape(-1)
        except (TypeError, ValueError) as exc:
            raise ImageDecodeError(f'{what} is not a byte buffer: {type(data).__name__}') from exc


def decode_raw_image(encoding, height, width, step, is_bigendian, data):
    """
    Decode the fields of a ``sensor_msgs/Image`` into an array (see the module convention).

    ``step`` is the row length in bytes (>= width * bytes per pixel; the rest of each row is
    padding and is skipped).  ``is_bigendian`` matters for 16-bit encodings only.  Raises
    :class:`ImageDecodeError` for an unknown encoding or when the sizes are inconsistent.
    """
    enc = str(encoding).strip().lower()
    if enc not in _RAW_ENCODINGS:
        raise ImageDecodeError(
            f'unsupported image encoding {encoding!r} '
            f'(supported: {", ".join(SUPPORTED_ENCODINGS)})')
    channels, depth, conversion = _RAW_ENCODINGS[enc]
    height, width, step = int(height), int(width), int(step)
    if height <= 0 or width <= 0:
        raise ImageDecodeError(f'image size must be positive, got {width}x{height}')
    row_bytes = width * channels * depth
    if step < row_bytes:
        raise ImageDecodeError(
            f'step {step} is shorter than a {width}-pixel {encoding} row ({row_bytes} bytes)')
    if depth > 1 and step % depth:
        raise ImageDecodeError(f'step {step} is not a multiple of the {depth}-byte channel size')
    if enc.startswith(('yuv', 'uyvy')) and width % 2:
        raise ImageDecodeError(f'{encoding} needs an even width, got {width}')
    buf = _as_byte_buffer(data, 'Image.data')
    if buf.size != height * step:
        raise ImageDecodeError(
            f'Image.data has {buf.size} bytes, expected height*step = {height}*{step} = '
            f'{height * step} for a {width}x{height} {encoding} image')

    rows = buf.reshape(height, step)[:, :row_bytes]
    if depth == 2:
        # A dtype view on rows with a contiguous last axis is allowed and copies nothing.
        rows = rows.view('>u2' if is_bigendian else '<u2')
        if not rows.dtype.isnative:
            rows = rows.astype(np.uint16)
    img = rows.reshape(height, width, channels) if channels > 1 else rows
    if conversion is None:
        return img
    return cv2.cvtColor(np.ascontiguousarray(img), conversion)


def decode_compressed_image(fmt, data):
    """
    Decode a ``sensor_msgs/CompressedImage`` (``format``, ``data``) with ``cv2.imdecode``.

    JPEG and PNG (8 or 16 bit) are handled, including image_transport's ``compressedDepth``
    PNG.  Colour comes out BGR with alpha dropped, mono as (H, W).
    """
    buf = _as_byte_buffer(data, 'CompressedImage.data')
    if 'compresseddepth' in str(fmt).lower().replace(' ', ''):
        buf = buf[_COMPRESSED_DEPTH_HEADER:]
    if buf.size == 0:
        raise ImageDecodeError(f'CompressedImage ({fmt!r}) has no data')
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageDecodeError(
            f'cv2.imdecode could not decode {buf.size} bytes of CompressedImage format {fmt!r}')
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    elif img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    return img


def decode_image_msg(msg):
    """
    Decode an Image or CompressedImage message object by duck typing.

    A message with a ``format`` attribute is a CompressedImage; otherwise the Image fields
    ``encoding``, ``height``, ``width``, ``step``, ``is_bigendian`` and ``data`` are read.
    """
    if hasattr(msg, 'format'):
        return decode_compressed_image(msg.format, msg.data)
    try:
        fields = (msg.encoding, msg.height, msg.width, msg.step, msg.is_bigendian, msg.data)
    except AttributeError as exc:
        raise ImageDecodeError(
            f'{type(msg).__name__} is neither a sensor_msgs/Image nor a CompressedImage') from exc
    return decode_raw_image(*fields)


def encode_raw_image(img, encoding, step=None, is_bigendian=False):
    """
    Inverse of :func:`decode_raw_image` for the non-converted layouts (tests, simulator).

    ``img`` must already be in the memory layout of ``encoding`` (e.g. RGB order for 'rgb8').
    Returns the dict of Image fields (``data`` as bytes), padding rows to ``step`` if given.
    """
    enc = str(encoding).strip().lower()
    if enc not in _RAW_ENCODINGS:
        raise ValueError(f'encoding {encoding!r} is not supported')
    channels, depth, _ = _RAW_ENCODINGS[enc]
    img = np.asarray(img)
    height, width = img.shape[:2]
    if depth == 2:
        img = img.astype('>u2' if is_bigendian else '<u2')
    else:
        img = img.astype(np.uint8)
    row = img.reshape(height, -1).view(np.uint8)
    if row.shape[1] != width * channels * depth:
        raise ValueError(f'img shape {img.shape} does not match encoding {encoding}')
    step = row.shape[1] if step is None else int(step)
    if step < row.shape[1]:
        raise ValueError(f'step {step} shorter than the row ({row.shape[1]} bytes)')
    out = np.zeros((height, step), np.uint8)
    out[:, :row.shape[1]] = row
    return dict(encoding=encoding, height=height, width=width, step=step,
                is_bigendian=int(bool(is_bigendian)), data=out.tobytes())
