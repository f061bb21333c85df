"""The ArUco / AprilTag detector: one point per tag, its centre, with the tag id."""

import numpy as np

import cv2

from armcal_ros.frontend.detectors.base import (aruco_dictionary, check_positive, Detection,
                                                Detector, to_gray, white_level)


def diagonal_intersection(corners):
    """
    Return the intersection (2,) of the diagonals 0-2 and 1-3 of a quadrilateral (4, 2).

    Under perspective the image of a square's centre is where its diagonals cross, not the
    mean of its corners (perspective does not preserve ratios of lengths, the corner mean is
    off by up to a pixel on a tilted tag; it does preserve incidence).
    """
    c = np.asarray(corners, dtype=float).reshape(4, 2)
    d1, d2 = c[2] - c[0], c[3] - c[1]
    a = np.column_stack([d1, -d2])
    if abs(np.linalg.det(a)) < 1e-9 * max(1.0, float(np.dot(d1, d1) + np.dot(d2, d2))):
        return None
    s, _ = np.linalg.solve(a, c[1] - c[0])
    return c[0] + s * d1


class ArucoDetector(Detector):
    """
    An ArUco / AprilTag tag's centre, by ``cv2.aruco.ArucoDetector`` with sub-pixel corners.

    The point is the intersection of the refined corners' diagonals (see
    :func:`diagonal_intersection`).  ``marker_id`` None returns every tag of the dictionary,
    otherwise only that id.  ``minMarkerDistanceRate`` is 0 because the default missed
    strongly tilted tags under noise.  ``quality`` is the shortest side in pixels over 32,
    capped at 1 (corner accuracy degrades on small tags).

    ``corners`` True returns the tag's four refined corners instead, as detections with ids
    0-3 in OpenCV's order (top-left, top-right, bottom-right, bottom-left of the tag as printed):
    the tag as a rigid four-point target (:func:`tag_corner_points`).  Corners of two tags
    would share those ids, so this needs ``marker_id``.
    """

    def __init__(self, dictionary='DICT_4X4_50', marker_id=None, corner_refine_win_size=5,
                 min_marker_distance_rate=0.0, corners=False):
        self.dictionary_name = str(dictionary)
        self._dictionary = aruco_dictionary(dictionary)
        n_ids = int(self._dictionary.bytesList.shape[0])
        if marker_id is not None:
            if int(marker_id) != marker_id or not 0 <= int(marker_id) < n_ids:
                raise ValueError(f'marker_id must be None or an integer in [0, {n_ids}) for '
                                 f'{dictionary}, got {marker_id!r}')
            marker_id = int(marker_id)
        self.marker_id = marker_id
        self.corners = bool(corners)
        if self.corners and marker_id is None:
            raise ValueError('corners mode needs a marker_id (the corners of two tags would '
                             'share their ids)')
        if int(corner_refine_win_size) != corner_refine_win_size or corner_refine_win_size < 1:
            raise ValueError(f'corner_refine_win_size must be a positive integer, got '
                             f'{corner_refine_win_size!r}')
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        params.cornerRefinementWinSize = int(corner_refine_win_size)
        # The defaults (30 iterations, stop at 0.1 px) leave the corners 0.1-0.4 px short of
        # convergence on rendered tags; refining to 0.001 px costs little (4 corners).  The
        # window is also capped at relativeCornerRefinmentWinSize * module size.
        params.cornerRefinementMaxIterations = 100
        params.cornerRefinementMinAccuracy = 0.001
        params.relativeCornerRefinmentWinSize = 0.6
        params.minMarkerDistanceRate = check_positive(
            'min_marker_distance_rate', min_marker_distance_rate, allow_zero=True)
        self._detector = cv2.aruco.ArucoDetector(self._dictionary, params)
        self.last_status = 'none'

    def detect(self, image):
        """Return one :class:`Detection` per tag found (sorted by id)."""
        gray = to_gray(image)
        if gray.dtype != np.uint8:
            scale = 255.0 / white_level(gray.dtype)
            gray = cv2.convertScaleAbs(gray, alpha=scale)
        corners, ids, _ = self._detector.detectMarkers(np.ascontiguousarray(gray))
        out = []
        if ids is not None:
            for quad, tag in zip(corners, ids.reshape(-1)):
                if self.marker_id is not None and int(tag) != self.marker_id:
                    continue
                quad = quad.reshape(4, 2).astype(float)
                centre = diagonal_intersection(quad)
                if centre is None:
                    continue
                sides = np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)
                diag = 0.25 * (np.linalg.norm(quad[2] - quad[0])
                               + np.linalg.norm(quad[3] - quad[1]))
                out.append(Detection(uv=centre, id=int(tag),
                                     quality=float(min(1.0, sides.min() / 32.0)),
                                     radius_px=float(diag), corners=quad))
        out = self._merge_duplicates(out)
        self.last_status = 'ok' if out else 'none'
        if self.corners:
            return [Detection(uv=uv, id=k, quality=d.quality, radius_px=d.radius_px)
                    for d in out[:1] for k, uv in enumerate(d.corners)]
        return out

    @staticmethod
    def _merge_duplicates(dets):
        # With minMarkerDistanceRate = 0 OpenCV no longer removes the duplicate candidates it
        # finds at several adaptive thresholds: the same tag comes back 2-3 times with corners
        # refined to within ~0.01 px.  Same id and centres within half a tag radius -> one
        # detection at the mean centre.  Two real tags with one id stay apart.
        out = []
        for det in sorted(dets, key=lambda d: d.id):
            group = next((g for g in out if g[0].id == det.id and np.linalg.norm(
                g[0].uv - det.uv) < 0.5 * det.radius_px), None)
            if group is None:
                out.append([det])
            else:
                group.append(det)
        return [g[0] if len(g) == 1 else Detection(
            uv=np.mean([d.uv for d in g], axis=0), id=g[0].id,
            quality=max(d.quality for d in g), radius_px=float(np.mean([d.radius_px for d in g])),
            corners=np.mean([d.corners for d in g], axis=0))
            for g in out]


def tag_corner_points(size):
    """
    Return (4, 3): a square tag's corners in its own frame, in OpenCV's corner order.

    Origin at the centre, x to the right and y up as printed, z out of the tag: the object
    points of ``cv2.SOLVEPNP_IPPE_SQUARE``.
    """
    h = 0.5 * float(size)
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
