"""
The data a calibration is made from: per-camera observations of a target at one pose (a sample).

A sample is one place where the arm dwelt: the nominal 3D position of the target from forward
kinematics or a measured link pose (``point_nominal``, metres, base frame), the joint angles it
came from (``q``) and/or the link pose (``pose``, T_base_link: measured with pose input, from
forward kinematics for a board), and per camera the pooled image position(s) of the target.  A
sphere or a single tag gives one point per camera (K = 1, one 3-D point per sample); a board
(:class:`BoardTarget`) gives K corners with their ids, each corner its own 3-D point
T_base_link T_link_target p_k.
"""

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

#: Half-side (m) of the square that stands for a one-point target's extent: the reach of a
#: guess of a marker's place on a tool (a few centimetres), so that a wrist turn that moves the
#: true marker by a millimetre is seen as motion and as another place.
POINT_REFERENCE_RADIUS = 0.05


@dataclass
class Observation:
    """
    One camera's pooled view of a sample's target.

    ``uv`` (K, 2) pixels (OpenCV convention), ``ids`` (K,) target point ids (0 for a sphere),
    ``n_frames`` the frames pooled, ``spread_px`` the RMS distance of the pooled detections
    from ``uv`` (a per-observation noise estimate; 0 for a single frame), ``stamp_ns`` the
    median image stamp.  When ``uv`` is a fitted centre (a shaded sphere), ``centroid_uv``
    (K, 2) is the same frames' mean intensity centroid and ``centroid_spread_px`` its spread
    (None and 0 otherwise).
    """

    uv: np.ndarray
    ids: np.ndarray
    n_frames: int = 1
    spread_px: float = 0.0
    stamp_ns: int = 0
    centroid_uv: Optional[np.ndarray] = None
    centroid_spread_px: float = 0.0

    def __post_init__(self):
        self.uv = np.asarray(self.uv, dtype=float).reshape(-1, 2)
        self.ids = np.asarray(self.ids, dtype=np.int64).reshape(-1)
        if self.ids.shape[0] != self.uv.shape[0]:
            raise ValueError(f'ids must have shape ({self.uv.shape[0]},) to match uv '
                             f'{self.uv.shape}, got {self.ids.shape}')
        if not np.all(np.isfinite(self.uv)):
            raise ValueError('uv must be finite')
        self.n_frames = int(self.n_frames)
        if self.n_frames < 1:
            raise ValueError(f'n_frames must be >= 1, got {self.n_frames}')
        self.spread_px = float(self.spread_px)
        self.stamp_ns = int(self.stamp_ns)
        if self.centroid_uv is not None:
            self.centroid_uv = np.asarray(self.centroid_uv, dtype=float).reshape(-1, 2)
            if self.centroid_uv.shape != self.uv.shape or \
                    not np.all(np.isfinite(self.centroid_uv)):
                raise ValueError(f'centroid_uv must be finite with the shape of uv '
                                 f'{self.uv.shape}, got {self.centroid_uv.shape}')
        self.centroid_spread_px = float(self.centroid_spread_px)

    def better_than(self, other):
        """Return True if this observation is the more trustworthy (more frames, less spread)."""
        return (self.n_frames, -self.spread_px) > (other.n_frames, -other.spread_px)


@dataclass
class Sample:
    """
    One 3D point seen by one or more cameras.

    ``point_nominal`` (3,) the target position from the robot model (metres, base frame);
    ``observations`` camera name -> :class:`Observation`; ``stamp_ns`` a representative time;
    ``q`` (n,) joint angles in chain order (or None); ``pose`` (4, 4) T_base_link, the
    marker link's pose (or None); ``id`` assigned by the
    :class:`~armcal_ros.frontend.store.SampleStore` (-1 before).  ``reference_points`` (R, 3)
    are the base-frame positions of R points fixed on an extended target (a board's outer
    corners): two poses of a board that differ only by a turn have the same centre but not the
    same reference points, so the store spaces samples by these (None: by ``point_nominal``).
    """

    point_nominal: np.ndarray
    observations: dict = field(default_factory=dict)
    stamp_ns: int = 0
    q: np.ndarray = None
    pose: np.ndarray = None
    id: int = -1
    reference_points: Optional[np.ndarray] = None

    def __post_init__(self):
        self.point_nominal = np.asarray(self.point_nominal, dtype=float).reshape(-1)
        if self.point_nominal.shape != (3,) or not np.all(np.isfinite(self.point_nominal)):
            raise ValueError(f'point_nominal must be 3 finite numbers, got {self.point_nominal}')
        if self.q is not None:
            self.q = np.asarray(self.q, dtype=float).reshape(-1)
        if self.pose is not None:
            self.pose = np.asarray(self.pose, dtype=float)
            if self.pose.shape != (4, 4) or not np.all(np.isfinite(self.pose)):
                raise ValueError(f'pose must be a finite (4, 4) transform, got shape '
                                 f'{self.pose.shape}')
        if self.reference_points is not None:
            r = np.asarray(self.reference_points, dtype=float)
            if r.ndim != 2 or r.shape[1] != 3 or not len(r) or not np.all(np.isfinite(r)):
                raise ValueError(f'reference_points must be finite with shape (R, 3), got '
                                 f'{r.shape}')
            self.reference_points = r
        for name, obs in self.observations.items():
            if not isinstance(obs, Observation):
                raise ValueError(f'observations[{name!r}] must be an Observation, '
                                 f'got {type(obs).__name__}')
        self.stamp_ns = int(self.stamp_ns)
        self.id = int(self.id)

    def key_points(self):
        """Return the (R, 3) points the store compares samples by (module docstring)."""
        if self.reference_points is not None:
            return self.reference_points
        return self.point_nominal[None, :]

    @property
    def n_cameras(self):
        """Return the number of cameras that saw this sample."""
        return len(self.observations)

    def rank(self):
        """Sort key: more cameras, then more pooled frames, then less spread is better."""
        frames = sum(o.n_frames for o in self.observations.values())
        spread = sum(o.spread_px for o in self.observations.values()) / max(1, self.n_cameras)
        return (self.n_cameras, frames, -spread)


@dataclass
class BoardTarget:
    """
    A rigid multi-point target (a ChArUco board) on the marker link.

    ``points`` (P, 3) the board's points in its own (target) frame, row = point id;
    ``T_link_target`` (4, 4) its pose on the link - the seed when ``estimate_mount`` is set,
    the fixed mount otherwise; None: unknown (then it must be estimated; the seed comes from
    hand-eye).
    """

    points: np.ndarray
    T_link_target: Optional[np.ndarray] = None
    estimate_mount: bool = False
    #: Estimate the factor of ``points`` too (a tag of unknown side, ``points`` at a guess).
    estimate_scale: bool = False

    def __post_init__(self):
        self.points = np.asarray(self.points, dtype=float)
        if self.points.ndim != 2 or self.points.shape[1] != 3 or len(self.points) < 1 or \
                not np.all(np.isfinite(self.points)):
            raise ValueError(f'target points must be finite with shape (P >= 1, 3), got '
                             f'{self.points.shape}')
        if self.T_link_target is not None:
            T = np.asarray(self.T_link_target, dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                raise ValueError(f'T_link_target must be a finite (4, 4) transform, got '
                                 f'{T.shape}')
            self.T_link_target = T
        elif not self.estimate_mount:
            raise ValueError('the board\'s pose on the link is unknown: set '
                             'estimate_marker_offset or target_pose_guess')
        self.estimate_mount = bool(self.estimate_mount)

    def mount_guess(self):
        """Return T_link_target, or the identity when it is unknown (seeded by hand-eye)."""
        return np.eye(4) if self.T_link_target is None else self.T_link_target

    def reference_points_in_link(self):
        """
        Return (4, 3): the corners of the board's bounding rectangle in the link frame.

        Under :meth:`mount_guess`.  Any fixed non-collinear set tells two link poses apart;
        the board's own extent makes "the same place" mean "every corner within the
        tolerance".  A one-point target (a point marker whose place on the link is estimated)
        has no extent: a square of half-side :data:`POINT_REFERENCE_RADIUS` around it stands
        in, so that views of the same marker position from another wrist orientation - what
        makes its place observable - count as other places, and a turn about the guessed
        point, which moves the true one, is not taken for stillness.
        """
        lo, hi = self.points.min(axis=0), self.points.max(axis=0)
        if np.all(hi - lo == 0):
            r = POINT_REFERENCE_RADIUS
            lo, hi = lo - [r, r, 0.0], hi + [r, r, 0.0]
        corners = np.array([[lo[0], lo[1], lo[2]], [hi[0], lo[1], lo[2]],
                            [hi[0], hi[1], hi[2]], [lo[0], hi[1], hi[2]]])
        T = self.mount_guess()
        return corners @ T[:3, :3].T + T[:3, 3]

    def centre_in_link(self):
        """Return the board's centroid (3,) in the link frame under :meth:`mount_guess`."""
        T = self.mount_guess()
        return T[:3, :3] @ self.points.mean(axis=0) + T[:3, 3]
