"""
Marker detectors: an image in, zero or more 2D points with ids and a quality out.

:func:`make_detector` builds one by marker type: ``sphere`` (:mod:`.sphere`), ``aruco``
(:mod:`.aruco`) or ``charuco`` (:mod:`.charuco`).  What they share (:class:`Detection`, the
:class:`Detector` interface, :func:`to_gray`, the image conventions) is in :mod:`.base`.
"""

import inspect

from armcal_ros.frontend.detectors.aruco import (ArucoDetector, diagonal_intersection,
                                                 tag_corner_points)
from armcal_ros.frontend.detectors.base import Detection, Detector, to_gray
from armcal_ros.frontend.detectors.charuco import CharucoBoard, CharucoDetector
from armcal_ros.frontend.detectors.sphere import SphereDetector

__all__ = ['ArucoDetector', 'CharucoBoard', 'CharucoDetector', 'Detection', 'Detector',
           'diagonal_intersection', 'make_detector', 'SphereDetector', 'tag_corner_points',
           'to_gray']


_DETECTORS = {'sphere': SphereDetector, 'aruco': ArucoDetector}


def make_detector(marker_type, **params):
    """
    Build the detector for ``marker_type`` ('sphere', 'aruco', 'charuco') with ``params``.

    Unknown marker types and parameter names raise ValueError naming them; values are checked
    by the detector's constructor (ValueError naming the parameter).
    """
    kind = str(marker_type).strip().lower()
    if kind == 'charuco':
        return _make_charuco(**params)
    cls = _DETECTORS.get(kind)
    if cls is None:
        raise ValueError(f'marker_type {marker_type!r} is not supported (one of '
                         f'{", ".join(sorted(_DETECTORS) + ["charuco"])})')
    accepted = set(inspect.signature(cls.__init__).parameters) - {'self'}
    unknown = sorted(set(params) - accepted)
    if unknown:
        raise ValueError(f'unknown {marker_type} detector parameter(s) {", ".join(unknown)} '
                         f'(accepted: {", ".join(sorted(accepted))})')
    return cls(**params)


def _make_charuco(rows=None, cols=None, square_size=None, marker_size=None,
                  dictionary='DICT_6X6_250', legacy=False, min_corners=4, **unknown):
    """Build a ChArUco detector from board and detector keywords (:mod:`.charuco`)."""
    if unknown:
        raise ValueError(f'unknown charuco detector parameter(s) {", ".join(sorted(unknown))} '
                         '(accepted: rows, cols, square_size, marker_size, dictionary, legacy, '
                         'min_corners)')
    missing = [k for k, v in (('rows', rows), ('cols', cols), ('square_size', square_size),
                              ('marker_size', marker_size)) if v is None]
    if missing:
        raise ValueError(f'charuco detector needs {", ".join(missing)}')
    board = CharucoBoard(rows, cols, square_size, marker_size, dictionary, legacy)
    return CharucoDetector(board, min_corners=min_corners)
