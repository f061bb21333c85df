"""
Marker detectors: an image in, zero or more 2D points with ids and a quality out.

All image coordinates use the OpenCV / ``cv2.projectPoints`` convention: the centre of the
top-left pixel is (0, 0), u to the right, v down.

A detector instance may keep state between frames (the sphere detector tracks its last
position), so the caller keeps one instance per camera.

This module holds what every detector shares: :class:`Detection`, the :class:`Detector`
interface, image helpers and the checks of constructor parameters.
"""

from dataclasses import dataclass
import math
from typing import Optional

import numpy as np

import cv2


@dataclass(frozen=True)
class Detection:
    """
    One detected point.

    ``uv`` (2,) pixel position, ``id`` marker id (0 for a sphere, the tag id for ArUco),
    ``quality`` in [0, 1] (detector specific, higher is better; see each detector),
    ``radius_px`` the apparent size (sphere radius, half the tag diagonal), for a tag
    ``corners`` (4, 2) its refined corners and, when ``uv`` is a model fit's centre (the
    shaded sphere), ``centroid`` (2,) the blob's intensity centroid: less noisy than the fit,
    biased by the light, so that pooling their differences over many views
    (:mod:`armcal_ros.core.light_pooling`) gets the best of both.
    """

    uv: np.ndarray
    id: int
    quality: float
    radius_px: float
    corners: Optional[np.ndarray] = None
    centroid: Optional[np.ndarray] = None


class Detector:
    """Interface of every detector: ``detect(image) -> list[Detection]``."""

    #: why the last call to :meth:`detect` returned what it did (for diagnostics and counters)
    last_status = 'none'

    def detect(self, image):
        """Return the detections in ``image`` ((H, W) mono or (H, W, 3) BGR, 8 or 16 bit)."""
        raise NotImplementedError

    def reset(self):
        """Forget any state carried between frames (e.g. after a time jump)."""


def to_gray(image):
    """Return a single-channel view/copy of ``image`` ((H, W), (H, W, 3) BGR or (H, W, 4) BGRA)."""
    image = np.asarray(image)
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if image.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(np.ascontiguousarray(image), code)
    raise ValueError(f'image must have shape (H, W), (H, W, 3) or (H, W, 4), got {image.shape}')


def white_level(dtype):
    """Return the full-scale value of an image of ``dtype`` (uint8 255, uint16 65535, float 1)."""
    if dtype == np.uint8:
        return 255.0
    if dtype == np.uint16:
        return 65535.0
    if np.issubdtype(dtype, np.floating):
        return 1.0
    raise ValueError(f'image dtype must be uint8, uint16 or float, got {dtype}')


def check_positive(name, value, allow_zero=False):
    """Return ``value`` as a float > 0 (>= 0 with ``allow_zero``); ValueError naming ``name``."""
    try:
        value = float(value)
    except (TypeError, ValueError) as exc:
        raise ValueError(f'{name} must be a number, got {value!r}') from exc
    if not math.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f'{name} must be {"non-negative" if allow_zero else "positive"}, '
                         f'got {value}')
    return value


def check_fraction(name, value):
    """Return ``value`` as a float in [0, 1]; ValueError naming ``name``."""
    value = check_positive(name, value, allow_zero=True)
    if value > 1:
        raise ValueError(f'{name} must be in [0, 1], got {value}')
    return value


_ARUCO_PREFIX = 'DICT_'


def aruco_dictionary(name):
    """Return the predefined OpenCV ArUco dictionary ``name`` ('DICT_' may be left out)."""
    key = str(name).strip().upper()
    if not key.startswith(_ARUCO_PREFIX):
        key = _ARUCO_PREFIX + key
    value = getattr(cv2.aruco, key, None)
    if not isinstance(value, int):
        known = sorted(k for k in dir(cv2.aruco) if k.startswith(_ARUCO_PREFIX))
        raise ValueError(f'dictionary {name!r} is not an OpenCV ArUco dictionary '
                         f'(one of {", ".join(known)})')
    return cv2.aruco.getPredefinedDictionary(value)
