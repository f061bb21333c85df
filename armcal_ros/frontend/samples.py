"""
The data a calibration is made from: per-camera observations of one 3D point (a sample).

A sample is one place where the arm dwelt: the nominal 3D position of the target from forward
kinematics (``point_nominal``, metres, base frame), the joint angles it came from (``q``) or a
target pose (``pose``, for pose-input data), and per camera the pooled image position(s) of
the target.  A sphere or a single tag gives one point per camera (K = 1); board targets will
give K corners with their ids.
"""

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Observation:
    """
    One camera's pooled view of a sample's target.

    ``uv`` (K, 2) pixels (OpenCV convention), ``ids`` (K,) target point ids (0 for a sphere),
    ``n_frames`` the frames pooled, ``spread_px`` the RMS distance of the pooled detections
    from ``uv`` (a per-observation noise estimate; 0 for a single frame), ``stamp_ns`` the
    median image stamp.
    """

    uv: np.ndarray
    ids: np.ndarray
    n_frames: int = 1
    spread_px: float = 0.0
    stamp_ns: int = 0

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

    def better_than(self, other):
        """Return True if this observation is the more trustworthy (more frames, less spread)."""
        return (self.n_frames, -self.spread_px) > (other.n_frames, -other.spread_px)


@dataclass
class Sample:
    """
    One 3D point seen by one or more cameras.

    ``point_nominal`` (3,) the target position from the robot model (metres, base frame);
    ``observations`` camera name -> :class:`Observation`; ``stamp_ns`` a representative time;
    ``q`` (n,) joint angles in chain order (or None); ``pose`` (4, 4) target pose (or None);
    ``id`` assigned by the :class:`~armcal_ros.frontend.store.SampleStore` (-1 before).
    """

    point_nominal: np.ndarray
    observations: dict = field(default_factory=dict)
    stamp_ns: int = 0
    q: np.ndarray = None
    pose: np.ndarray = None
    id: int = -1

    def __post_init__(self):
        self.point_nominal = np.asarray(self.point_nominal, dtype=float).reshape(-1)
        if self.point_nominal.shape != (3,) or not np.all(np.isfinite(self.point_nominal)):
            raise ValueError(f'point_nominal must be 3 finite numbers, got {self.point_nominal}')
        if self.q is not None:
            self.q = np.asarray(self.q, dtype=float).reshape(-1)
        if self.pose is not None:
            self.pose = np.asarray(self.pose, dtype=float)
            if self.pose.shape != (4, 4):
                raise ValueError(f'pose must have shape (4, 4), got {self.pose.shape}')
        for name, obs in self.observations.items():
            if not isinstance(obs, Observation):
                raise ValueError(f'observations[{name!r}] must be an Observation, '
                                 f'got {type(obs).__name__}')
        self.stamp_ns = int(self.stamp_ns)
        self.id = int(self.id)

    @property
    def n_cameras(self):
        """Return the number of cameras that saw this sample."""
        return len(self.observations)

    def rank(self):
        """Sort key: more cameras, then more pooled frames, then less spread is better."""
        frames = sum(o.n_frames for o in self.observations.values())
        spread = sum(o.spread_px for o in self.observations.values()) / max(1, self.n_cameras)
        return (self.n_cameras, frames, -spread)
