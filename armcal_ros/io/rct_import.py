"""
Read an industrial_calibration / robot_cal_tools data folder (static camera, robot-held target).

Layout (as in ``rct_examples/data/test_set_*``)::

    cal_data.yaml        - list of {image: images/N.png, pose: poses/N.yaml}, paths relative
    poses/N.yaml         - link pose in the base frame: x, y, z (m), qx, qy, qz, qw
    target.yaml          - target_finder: {type, rows, cols, chessboard_dim, aruco_marker_dim,
                           dictionary (OpenCV code)} - only ChArUco boards are read here
    camera_intr.yaml     - optional intrinsics guess {intrinsics: {fx, fy, cx, cy}}
    pose_guesses.yaml    - optional {base_to_camera_guess, wrist_to_target_guess}: x..qw

The pose files give T_base_link for the link that holds the target (the flange, ``tool0``);
``base_to_camera_guess`` is T_base_camera (optical frame) and ``wrist_to_target_guess``
T_link_target.  Everything is returned as plain arrays; images are read only by
:func:`detect_views`.
"""

import os
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np
import yaml

from armcal_ros.core.board_calibration import BoardData
from armcal_ros.core.target import pose_matrix, pose_vector

CAL_DATA = 'cal_data.yaml'
TARGET = 'target.yaml'
INTRINSICS_GUESS = 'camera_intr.yaml'
POSE_GUESSES = 'pose_guesses.yaml'
CHARUCO_TYPES = ('CharucoGridTargetFinderPlugin', 'CharucoGridTargetFinder', 'charuco')


class RctFormatError(ValueError):
    """A file of the folder is missing or malformed; the message names it."""


def is_rct_folder(path):
    """Return True if ``path`` is a directory with a ``cal_data.yaml``."""
    return os.path.isdir(path) and os.path.isfile(os.path.join(path, CAL_DATA))


def _load(path):
    try:
        with open(path) as f:
            return yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as exc:
        raise RctFormatError(f'{path}: cannot read: {exc}') from exc


def read_pose(doc, where):
    """Return the 4x4 pose of a mapping with x, y, z, qx, qy, qz, qw (``where`` names it)."""
    try:
        t = [float(doc[k]) for k in ('x', 'y', 'z')]
        q = [float(doc[k]) for k in ('qx', 'qy', 'qz', 'qw')]
    except (KeyError, TypeError, ValueError) as exc:
        raise RctFormatError(f'{where}: a pose needs numbers x, y, z, qx, qy, qz, qw '
                             f'({exc})') from exc
    try:
        return pose_matrix(t, q)
    except ValueError as exc:
        raise RctFormatError(f'{where}: {exc}') from exc


@dataclass
class RctTarget:
    """
    The ChArUco board of ``target.yaml`` (sizes in metres, OpenCV dictionary code).

    robot_cal_tools' boards and mount guesses use the pre-4.6 OpenCV corner numbering and frame
    (``CharucoBoard(*target.board_args, legacy=True)``).
    """

    rows: int
    cols: int
    square_size: float
    marker_size: float
    dictionary: int

    @property
    def board_args(self):
        """Return (rows, cols, square_size, marker_size, dictionary) for a CharucoBoard."""
        return (self.rows, self.cols, self.square_size, self.marker_size, self.dictionary)


@dataclass
class RctDataSet:
    """
    A robot_cal_tools folder: image paths, link poses (V, 4, 4), the target and the guesses.

    ``intrinsics_guess`` {fx, fy, cx, cy} or None; ``camera_guess`` T_base_camera and
    ``target_guess`` T_link_target (4, 4) or None.
    """

    root: str
    image_paths: List[str]
    poses: np.ndarray
    target: RctTarget
    intrinsics_guess: Optional[Dict[str, float]] = None
    camera_guess: Optional[np.ndarray] = None
    target_guess: Optional[np.ndarray] = None
    names: List[str] = field(default_factory=list)


def read_target(path) -> RctTarget:
    """Read ``target.yaml``; raise RctFormatError unless it is a ChArUco board."""
    doc = _load(path)
    tf = doc.get('target_finder') if isinstance(doc, dict) else None
    if not isinstance(tf, dict):
        raise RctFormatError(f'{path}: expected a target_finder mapping')
    kind = str(tf.get('type', ''))
    if not any(kind.endswith(k) for k in CHARUCO_TYPES):
        raise RctFormatError(f'{path}: target type {kind!r} is not supported (only ChArUco '
                             'boards: CharucoGridTargetFinderPlugin)')
    try:
        return RctTarget(int(tf['rows']), int(tf['cols']), float(tf['chessboard_dim']),
                         float(tf['aruco_marker_dim']), int(tf['dictionary']))
    except (KeyError, TypeError, ValueError) as exc:
        raise RctFormatError(f'{path}: ChArUco target needs rows, cols, chessboard_dim, '
                             f'aruco_marker_dim, dictionary ({exc})') from exc


def load_rct_folder(path) -> RctDataSet:
    """Read the folder's cal_data.yaml, poses, target.yaml and optional guesses."""
    if not is_rct_folder(path):
        raise RctFormatError(f'{path}: not a robot_cal_tools folder (no {CAL_DATA})')
    entries = _load(os.path.join(path, CAL_DATA))
    if not isinstance(entries, list) or not entries:
        raise RctFormatError(f'{os.path.join(path, CAL_DATA)}: expected a list of '
                             '{image, pose} entries')
    images, poses, names = [], [], []
    for k, e in enumerate(entries):
        if not isinstance(e, dict) or 'image' not in e or 'pose' not in e:
            raise RctFormatError(f'{CAL_DATA} entry {k}: needs image and pose')
        img = os.path.join(path, str(e['image']))
        if not os.path.isfile(img):
            raise RctFormatError(f'{CAL_DATA} entry {k}: image {img} does not exist')
        pose_file = os.path.join(path, str(e['pose']))
        poses.append(read_pose(_load(pose_file), pose_file))
        images.append(img)
        names.append(os.path.splitext(os.path.basename(img))[0])
    target = read_target(os.path.join(path, TARGET))
    intr = None
    ipath = os.path.join(path, INTRINSICS_GUESS)
    if os.path.isfile(ipath):
        doc = _load(ipath) or {}
        try:
            intr = {k: float(doc['intrinsics'][k]) for k in ('fx', 'fy', 'cx', 'cy')}
        except (KeyError, TypeError, ValueError) as exc:
            raise RctFormatError(f'{ipath}: intrinsics needs fx, fy, cx, cy ({exc})') from exc
    cam_guess = tgt_guess = None
    gpath = os.path.join(path, POSE_GUESSES)
    if os.path.isfile(gpath):
        doc = _load(gpath) or {}
        if 'base_to_camera_guess' in doc:
            cam_guess = read_pose(doc['base_to_camera_guess'], gpath + ' base_to_camera_guess')
        if 'wrist_to_target_guess' in doc:
            tgt_guess = read_pose(doc['wrist_to_target_guess'], gpath + ' wrist_to_target_guess')
    return RctDataSet(os.path.abspath(path), images, np.array(poses), target, intr, cam_guess,
                      tgt_guess, names)


def detect_views(data: RctDataSet, detector):
    """
    Detect the board in every image; return (uv list, ids list, (width, height)).

    ``detector`` is a :class:`~armcal_ros.frontend.detectors.CharucoDetector`; an image without
    a usable detection gives empty arrays.
    """
    import cv2
    uvs, ids, size = [], [], None
    for p in data.image_paths:
        img = cv2.imread(p, cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise RctFormatError(f'{p}: cannot decode the image')
        h, w = img.shape[:2]
        if size is None:
            size = (w, h)
        elif size != (w, h):
            raise RctFormatError(f'{p}: image size {w}x{h} differs from {size[0]}x{size[1]}')
        uv, i = detector.detect_arrays(img)
        uvs.append(uv)
        ids.append(i)
    return uvs, ids, size


def save_views(path, data: RctDataSet, uvs, ids, size, extra=None, decimals=2):
    """
    Write detected corners with their link poses as compact JSON (a detection cache/fixture).

    ``uvs`` / ``ids`` per view as returned by :func:`detect_views`; pixels are rounded to
    ``decimals``.  ``extra`` adds top-level entries (e.g. provenance).
    """
    import json
    t = data.target
    doc = dict(extra or {})
    doc.update(
        image_size=list(size),
        target=dict(rows=t.rows, cols=t.cols, square_size=t.square_size,
                    marker_size=t.marker_size, dictionary=t.dictionary),
        camera_guess=None if data.camera_guess is None else
        [round(v, 9) for v in pose_vector(data.camera_guess)],
        target_guess=None if data.target_guess is None else
        [round(v, 9) for v in pose_vector(data.target_guess)],
        intrinsics_guess=data.intrinsics_guess,
        views=[dict(name=n, pose=[round(v, 10) for v in pose_vector(T)],
                    ids=[int(i) for i in idv],
                    uv=[round(float(x), decimals) for x in np.asarray(uv).reshape(-1)])
               for n, T, uv, idv in zip(data.names, data.poses, uvs, ids)])
    with open(path, 'w') as f:
        json.dump(doc, f, separators=(',', ':'))


def load_views(path):
    """
    Read a file written by :func:`save_views`.

    Returns (RctDataSet without images (``root`` = path), uvs, ids, (width, height), doc).
    """
    import json
    try:
        with open(path) as f:
            doc = json.load(f)
        t = doc['target']
        target = RctTarget(int(t['rows']), int(t['cols']), float(t['square_size']),
                           float(t['marker_size']), int(t['dictionary']))
        views = doc['views']
        poses = np.array([pose_matrix(v['pose'][:3], v['pose'][3:]) for v in views])
        uvs = [np.asarray(v['uv'], float).reshape(-1, 2) for v in views]
        ids = [np.asarray(v['ids'], np.int64) for v in views]
        names = [str(v['name']) for v in views]
        guess = {k: (None if doc.get(k) is None else pose_matrix(doc[k][:3], doc[k][3:]))
                 for k in ('camera_guess', 'target_guess')}
        size = tuple(int(x) for x in doc['image_size'])
    except (OSError, ValueError, KeyError, TypeError, IndexError) as exc:
        raise RctFormatError(f'{path}: not a corner file: {exc}') from exc
    for k, (uv, i) in enumerate(zip(uvs, ids)):
        if len(uv) != len(i):
            raise RctFormatError(f'{path}: view {k} has {len(uv)} points and {len(i)} ids')
    data = RctDataSet(path, [], poses, target, doc.get('intrinsics_guess'),
                      guess['camera_guess'], guess['target_guess'], names)
    return data, uvs, ids, size, doc


def board_data(poses, board_points, uvs, ids, camera=0):
    """Return :class:`~armcal_ros.core.board_calibration.BoardData` for one camera's views."""
    view = np.concatenate([np.full(len(i), v, np.int64) for v, i in enumerate(ids)] +
                          [np.zeros(0, np.int64)])
    uv = np.concatenate([np.asarray(u, float).reshape(-1, 2) for u in uvs] + [np.zeros((0, 2))])
    corner = np.concatenate([np.asarray(i, np.int64) for i in ids] + [np.zeros(0, np.int64)])
    return BoardData(poses, board_points, view, np.full(len(view), camera), corner, uv)
