"""
Pose input: a measured link pose (T_base_link) at any image stamp, and whether it was still.

Robots that report a flange pose (a geometry_msgs PoseStamped / TransformStamped stream)
instead of joint angles give samples directly: the link pose at an image's stamp is interpolated
between the bracketing pose messages - the translation linearly, the rotation by spherical
linear interpolation - and refused when the stamp is outside the history or the bracketing gap is
longer than ``max_gap_s``.  Stillness is judged as for joint input: the speed of a point at
``radius`` from the link origin (the target's extent) must be below ``max_speed``
(|v| + |omega| radius, from the bracketing messages).
"""

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


@dataclass
class PoseAt:
    """An interpolated pose (4, 4), the point speed there (m/s), and a status string."""

    pose: np.ndarray
    speed: float
    status: str


class PoseTrack:
    """A time-ordered history of link poses; :meth:`at` interpolates."""

    def __init__(self, max_gap_s=0.1):
        if not max_gap_s > 0:
            raise ValueError(f'max_gap_s must be > 0, got {max_gap_s}')
        self.max_gap_ns = int(max_gap_s * 1e9)
        self._t = []
        self._p = []
        self._q = []
        self._sorted = True

    def __len__(self):
        return len(self._t)

    def add(self, stamp_ns, translation, quat_xyzw):
        """Add one pose; non-finite or non-unit quaternions are refused with ValueError."""
        t = np.asarray(translation, float).reshape(3)
        q = np.asarray(quat_xyzw, float).reshape(4)
        n = np.linalg.norm(q)
        if not (np.all(np.isfinite(t)) and np.isfinite(n) and abs(n - 1.0) < 1e-3):
            raise ValueError('pose must have a finite translation and a unit quaternion')
        if self._t and int(stamp_ns) < self._t[-1]:
            self._sorted = False
        self._t.append(int(stamp_ns))
        self._p.append(t)
        self._q.append(q / n)

    def _sort(self):
        if not self._sorted:
            order = np.argsort(self._t, kind='stable')
            self._t = [self._t[i] for i in order]
            self._p = [self._p[i] for i in order]
            self._q = [self._q[i] for i in order]
            self._sorted = True

    def at(self, stamp_ns, radius=0.0) -> PoseAt:
        """Return the pose at ``stamp_ns`` ('ok', 'outside' or 'gap' in ``status``)."""
        self._sort()
        t = np.asarray(self._t)
        if len(t) < 2 or stamp_ns < t[0] or stamp_ns > t[-1]:
            return PoseAt(None, float('nan'), 'outside')
        k = int(np.searchsorted(t, stamp_ns, side='right'))
        k = min(max(k, 1), len(t) - 1)
        t0, t1 = t[k - 1], t[k]
        if t1 - t0 > self.max_gap_ns or t1 == t0:
            return PoseAt(None, float('nan'), 'gap')
        a = (stamp_ns - t0) / (t1 - t0)
        rots = Rotation.from_quat([self._q[k - 1], self._q[k]])
        R = Slerp([0.0, 1.0], rots)([a])[0]
        T = np.eye(4)
        T[:3, :3] = R.as_matrix()
        T[:3, 3] = (1 - a) * self._p[k - 1] + a * self._p[k]
        dt = (t1 - t0) * 1e-9
        v = np.linalg.norm(self._p[k] - self._p[k - 1]) / dt
        w = (rots[0].inv() * rots[1]).magnitude() / dt
        return PoseAt(T, float(v + w * radius), 'ok')
