"""
Pose input: a measured link pose (T_base_link) at any image stamp, and whether it was still.

Robots that report a flange pose (a geometry_msgs PoseStamped / TransformStamped stream)
instead of joint angles give samples directly: the link pose at an image's stamp is interpolated
between the bracketing pose messages - the translation linearly, the rotation by spherical
linear interpolation - and refused when the stamp is outside the history or the bracketing gap is
longer than ``max_gap_s``.

:class:`PoseHistory` is a bounded, time-ordered history with the interface of
:class:`~armcal_ros.frontend.pairing.JointHistory`, so that
:class:`~armcal_ros.frontend.pairing.FramePairer` pairs frames with poses exactly as with joint
states (same pending, batching, time-jump and stillness rules), live or from a recording.  Its
"configuration" is the pose vector c = (x, y, z, qx, qy, qz, qw); :func:`pose_points` maps it to
the target's reference points and :func:`mean_pose_vector` pools a dwell.
"""

import numpy as np
from scipy.spatial.transform import Rotation

from armcal_ros.frontend.pairing import JointStatus, PairStatus, StampedRing


def _check_pose(translation, quat_xyzw):
    t = np.asarray(translation, float).reshape(3)
    q = np.asarray(quat_xyzw, float).reshape(4)
    n = np.linalg.norm(q)
    if not (np.all(np.isfinite(t)) and np.isfinite(n) and abs(n - 1.0) < 1e-3):
        raise ValueError('pose must have a finite translation and a unit quaternion')
    return t, q / n


def pose_vector_matrix(c):
    """Return the (M, 4, 4) transforms of pose vectors c (M, 7) = (x, y, z, qx, qy, qz, qw)."""
    c = np.asarray(c, float).reshape(-1, 7)
    T = np.zeros((len(c), 4, 4))
    T[:, :3, :3] = Rotation.from_quat(c[:, 3:]).as_matrix()
    T[:, :3, 3] = c[:, :3]
    T[:, 3, 3] = 1.0
    return T


def pose_points(c, points_in_link):
    """
    Return the base-frame positions of link-frame points at pose vectors ``c`` (M, 7).

    ``points_in_link`` (R, 3); the result is (M, 3) for R = 1 (a point target) and (M, R, 3)
    otherwise - the shape :class:`~armcal_ros.frontend.pairing.FramePairer` expects of ``fk``.
    """
    T = pose_vector_matrix(c)
    p = np.asarray(points_in_link, float).reshape(-1, 3)
    X = np.einsum('mij,rj->mri', T[:, :3, :3], p) + T[:, None, :3, 3]
    return X[:, 0] if len(p) == 1 else X


def mean_pose_vector(C):
    """Pool a dwell's pose vectors (F, 7): mean translation, chordal L2 mean rotation."""
    C = np.asarray(C, float).reshape(-1, 7)
    q = Rotation.from_quat(C[:, 3:]).mean().as_quat()
    return np.concatenate([C[:, :3].mean(axis=0), q])


def _interpolate(t, p, q, stamps, max_gap_ns):
    """
    Interpolate sorted poses (t (N,), p (N, 3), q (N, 4)) at ``stamps`` (M,).

    Returns (statuses (M,) PairStatus, pose vectors (M, 7), NaN where not OK).
    """
    ts = np.asarray(stamps, np.int64).reshape(-1)
    out = np.full((len(ts), 7), np.nan)
    st = np.full(len(ts), PairStatus.OK, dtype=object)
    if len(t) == 0:
        st[:] = PairStatus.EMPTY
        return st, out
    hi = np.searchsorted(t, ts, side='left')
    exact = (hi < len(t)) & (t[np.minimum(hi, len(t) - 1)] == ts)
    before = (hi == 0) & ~exact
    after = hi == len(t)
    st[before] = PairStatus.BEFORE_HISTORY
    st[after] = PairStatus.AFTER_HISTORY
    out[exact, :3] = p[hi[exact]]
    out[exact, 3:] = q[hi[exact]]
    inner = ~(before | after | exact)
    if np.any(inner):
        h = hi[inner]
        lo = h - 1
        gap = t[h] - t[lo]
        a = (ts[inner] - t[lo]) / gap
        r0 = Rotation.from_quat(q[lo])
        rel = (r0.inv() * Rotation.from_quat(q[h])).as_rotvec()
        vals = np.empty((len(h), 7))
        vals[:, :3] = p[lo] + a[:, None] * (p[h] - p[lo])
        vals[:, 3:] = (r0 * Rotation.from_rotvec(a[:, None] * rel)).as_quat()
        bad = gap > max_gap_ns
        vals[bad] = np.nan
        out[inner] = vals
        s = st[inner]
        s[bad] = PairStatus.GAP
        st[inner] = s
    return st, out


class PoseHistory(StampedRing):
    """
    A bounded, time-ordered history of link poses with slerp interpolation (live pose input).

    The interface of :class:`~armcal_ros.frontend.pairing.JointHistory` and its timing rules
    (:class:`~armcal_ros.frontend.pairing.StampedRing`): :meth:`add` returns a
    :class:`~armcal_ros.frontend.pairing.JointStatus`, :meth:`lookup` returns statuses and pose
    vectors (translation, quaternion xyzw).
    """

    def __init__(self, capacity=4096, max_gap_ns=100_000_000, jump_threshold_ns=500_000_000):
        super().__init__(7, capacity, max_gap_ns, jump_threshold_ns)

    def add(self, stamp_ns, translation, quat_xyzw):
        """Add one pose; return a JointStatus (NON_FINITE for a bad translation/quaternion)."""
        try:
            t, q = _check_pose(translation, quat_xyzw)
        except ValueError:
            return JointStatus.NON_FINITE
        return self.push(stamp_ns, np.concatenate([t, q]))

    def lookup(self, stamps_ns):
        """Interpolate at several stamps: (statuses (M,) PairStatus, pose vectors (M, 7))."""
        rows = self.rows
        return _interpolate(self.stamps, rows[:, :3], rows[:, 3:], stamps_ns, self.max_gap_ns)
