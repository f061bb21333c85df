"""
ChArUco board targets: the board's corner points in its own frame, and a detector for them.

A ChArUco board is a chessboard of ``rows`` x ``cols`` squares of side ``square_size`` with an
ArUco marker of side ``marker_size`` in every white square.  Its targets are the
(rows - 1) x (cols - 1) inner chessboard corners; the markers only identify them, so a partial
view still gives corners with their ids.  ``cv2.aruco.CharucoDetector`` finds the markers,
interpolates the corners from them by local homographies and refines them with cornerSubPix.

Conventions (the target frame that T_link_target refers to):

- ``opencv`` numbering (OpenCV >= 4.6): origin at the board's top-left outer corner, x along the
  columns, y down the rows, z into the board; corner id j = r (cols - 1) + c sits at
  ((c + 1) s, (r + 1) s, 0).
- ``legacy`` numbering (boards and libraries from OpenCV < 4.6, e.g. robot_cal_tools): origin
  at the bottom-left outer corner, y up, z out of the board, and the corner rows numbered from
  the bottom, so new id j is legacy id (rows - 2 - j // (cols - 1)) (cols - 1) + j % (cols - 1)
  at the same physical place.  The two frames differ by a half turn about x (a proper rigid
  motion), so either fits equally well; legacy ids are needed to reuse a pose of the board
  (T_link_target) measured by such a tool.  Older OpenCV also started the square pattern
  differently on boards with an even row count (``setLegacyPattern``); the legacy option sets
  both.
"""

from dataclasses import dataclass

import numpy as np

import cv2

from armcal_ros.frontend.detectors.base import (aruco_dictionary, Detection, Detector, to_gray,
                                                white_level)


def _dictionary_name(dictionary):
    """Return an ArUco dictionary name from a name or its OpenCV integer code."""
    if isinstance(dictionary, (int, np.integer)) and not isinstance(dictionary, bool):
        for k in dir(cv2.aruco):
            if k.startswith('DICT_') and getattr(cv2.aruco, k) == int(dictionary):
                return k
        raise ValueError(f'dictionary code {dictionary} is not an OpenCV ArUco dictionary')
    return str(dictionary)


@dataclass(frozen=True)
class CharucoBoard:
    """
    A ChArUco board: ``rows`` x ``cols`` squares (metres), an ArUco ``dictionary``.

    ``legacy`` selects the pre-4.6 corner numbering, frame and square pattern (module docstring).
    """

    rows: int
    cols: int
    square_size: float
    marker_size: float
    dictionary: str = 'DICT_6X6_250'
    legacy: bool = False

    def __post_init__(self):
        object.__setattr__(self, 'dictionary', _dictionary_name(self.dictionary))
        for name in ('rows', 'cols'):
            v = getattr(self, name)
            if isinstance(v, bool) or int(v) != v or v < 2:
                raise ValueError(f'charuco {name} must be an integer >= 2, got {v!r}')
            object.__setattr__(self, name, int(v))
        if self.rows * self.cols < 5:
            raise ValueError(f'charuco board {self.rows}x{self.cols} is too small (needs at '
                             'least 2 inner corners)')
        if not (np.isfinite(self.square_size) and self.square_size > 0):
            raise ValueError(f'charuco square_size must be > 0 (metres), got {self.square_size}')
        if not (np.isfinite(self.marker_size) and 0 < self.marker_size < self.square_size):
            raise ValueError(f'charuco marker_size must be in (0, square_size={self.square_size})'
                             f' (metres), got {self.marker_size}')
        d = aruco_dictionary(self.dictionary)
        if d.bytesList.shape[0] < self.n_markers:
            raise ValueError(f'dictionary {self.dictionary} has {d.bytesList.shape[0]} markers, '
                             f'a {self.rows}x{self.cols} board needs {self.n_markers}')

    @property
    def n_corners(self):
        """Return the number of inner corners, (rows - 1) (cols - 1)."""
        return (self.rows - 1) * (self.cols - 1)

    @property
    def n_markers(self):
        """Return the number of ArUco markers on the board (one per white square)."""
        return (self.rows * self.cols) // 2

    def cv_board(self, board_markers_only=False):
        """
        Return the ``cv2.aruco.CharucoBoard`` (size given as (cols, rows)).

        ``board_markers_only`` gives it a dictionary cut to the board's own markers (ids
        0 .. n_markers - 1, the same codes): see :class:`CharucoDetector`.
        """
        d = aruco_dictionary(self.dictionary)
        if board_markers_only:
            d = cv2.aruco.Dictionary(np.ascontiguousarray(d.bytesList[:self.n_markers]),
                                     d.markerSize, d.maxCorrectionBits)
        board = cv2.aruco.CharucoBoard((self.cols, self.rows), float(self.square_size),
                                       float(self.marker_size), d)
        board.setLegacyPattern(bool(self.legacy))
        return board

    def points(self):
        """Return the corner positions (n_corners, 3) in the target frame, row = corner id."""
        n = self.n_corners
        j = np.arange(n)
        c = j % (self.cols - 1)
        r = j // (self.cols - 1)
        s = self.square_size
        # In either convention id j sits at ((c + 1) s, (r + 1) s, 0) of its own frame.
        return np.column_stack([(c + 1) * s, (r + 1) * s, np.zeros(n)])

    def ids_from_opencv(self, ids):
        """Map OpenCV (>= 4.6) corner ids to this board's ids (identity unless legacy)."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        if not self.legacy:
            return ids.copy()
        w = self.cols - 1
        return (self.rows - 2 - ids // w) * w + ids % w

    def render(self, px_per_square=60, margin_px=20):
        """Return an 8-bit image of the board (for tests and printing), opencv orientation."""
        w = self.cols * px_per_square + 2 * margin_px
        h = self.rows * px_per_square + 2 * margin_px
        return self.cv_board().generateImage((w, h), marginSize=margin_px, borderBits=1)


class CharucoDetector(Detector):
    """
    The inner corners of one ChArUco board, each with its corner id.

    Every detected corner becomes a :class:`Detection` (``id`` in the board's numbering,
    ``quality`` 1, ``radius_px`` half the median spacing of neighbouring detected corners,
    i.e. about half a square).  Fewer than ``min_corners`` corners return nothing.

    The marker search uses a dictionary cut to the board's own markers.  Matching every
    candidate quad against every code of the full dictionary was most of the detection time
    (DICT_6X6_250, a 7x5 board at 800x600: about 110 ms of CPU per image; cut to its 17 codes
    about 20 ms).  The board's markers are found the same: a candidate is accepted only within
    ``errorCorrectionRate`` x ``maxCorrectionBits`` bits of a code, less than half the
    dictionary's distance between codes, so a quad that matches a board code matches nothing
    else in the full dictionary, and markers of other ids were dropped by the board anyway.
    The corners are then the same, bit for bit; with a foreign marker of the dictionary in
    view (now an unidentified candidate) cv2's marker refinement can move them by < 0.01 px.
    """

    def __init__(self, board: CharucoBoard, min_corners=4, min_markers=1):
        if not isinstance(board, CharucoBoard):
            raise ValueError(f'board must be a CharucoBoard, got {type(board).__name__}')
        if int(min_corners) != min_corners or min_corners < 1:
            raise ValueError(f'min_corners must be a positive integer, got {min_corners!r}')
        self.board = board
        self.min_corners = int(min_corners)
        params = cv2.aruco.CharucoParameters()
        params.minMarkers = int(min_markers)
        # Refine the markers that the first pass missed from the board layout (partial views).
        params.tryRefineMarkers = True
        dparams = cv2.aruco.DetectorParameters()
        dparams.minMarkerDistanceRate = 0.0
        self._detector = cv2.aruco.CharucoDetector(board.cv_board(board_markers_only=True),
                                                   params, dparams)
        self.last_status = 'none'

    def detect_arrays(self, image):
        """Return (uv (K, 2), ids (K,)) sorted by id; K = 0 when nothing is usable."""
        gray = to_gray(image)
        if gray.dtype != np.uint8:
            gray = cv2.convertScaleAbs(gray, alpha=255.0 / white_level(gray.dtype))
        corners, ids, _, marker_ids = self._detector.detectBoard(np.ascontiguousarray(gray))
        if ids is None or len(ids) < self.min_corners:
            # No marker: None (OpenCV 4) or an empty array (OpenCV 5).
            seen = marker_ids is not None and len(marker_ids) > 0
            self.last_status = 'too_few_corners' if seen else 'none'
            return np.zeros((0, 2)), np.zeros(0, np.int64)
        uv = np.asarray(corners, float).reshape(-1, 2)
        bid = self.board.ids_from_opencv(ids)
        order = np.argsort(bid)
        self.last_status = 'ok'
        return uv[order], bid[order]

    def detect(self, image):
        """Return one :class:`Detection` per detected corner, sorted by id."""
        uv, ids = self.detect_arrays(image)
        if not len(ids):
            return []
        radius = 0.5 * _corner_spacing_px(uv, ids, self.board)
        return [Detection(uv=u, id=int(i), quality=1.0, radius_px=radius)
                for u, i in zip(uv, ids)]


def _corner_spacing_px(uv, ids, board):
    """
    Median image distance between detected corners that are board neighbours.

    Neighbours by id: j and j + 1 in one row, j and j + (cols - 1) in the next (either
    numbering), so this is linear in the corners found.
    """
    w = board.cols - 1
    pos = np.full(board.n_corners + w + 1, -1)
    pos[ids] = np.arange(len(ids))
    right = ids[ids % w != w - 1]
    pairs = [(pos[right], pos[right + 1]), (pos[ids], pos[ids + w])]
    d = [np.linalg.norm(uv[a[b >= 0]] - uv[b[b >= 0]], axis=1) for a, b in pairs]
    d = np.concatenate(d)
    return float(np.median(d)) if len(d) else 0.0
