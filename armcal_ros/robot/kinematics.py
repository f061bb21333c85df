"""
Forward kinematics of a serial URDF chain, its Jacobians, and kinematic error parameters.

Chain
-----
Between ``base_frame`` and ``tip_link`` the URDF gives a list of joints, each with an origin
O (pose of the joint frame in the parent link) and, if movable, a motion about or along a unit
axis a.  Fixed joints are folded into the origin of the next movable joint, and the fixed
joints after the last movable joint into a tail transform O_tail, so that with n movable
joints::

    T_base_tip(q) = O_1 D_1 M_1(q_1 + o_1)  O_2 D_2 M_2(q_2 + o_2) ... O_n D_n M_n(q_n + o_n)
                    O_tail D_tip

where M_k(v) = [Rot(a_k, v) | 0] for revolute and continuous joints and [I | a_k v] for
prismatic ones.  The nominal robot has every o_k = 0 and every D = I.

Error parameters
----------------
Per movable joint k, seven numbers, named ``<joint>/offset``, ``<joint>/tx``, ``/ty``,
``/tz``, ``/rx``, ``/ry``, ``/rz``:

- o_k: offset added to the joint value (radians; metres for a prismatic joint);
- t_k, r_k: translation (metres) and rotation vector (radians) of the error transform
  D_k = [Exp(r_k) | t_k], applied on the right of the joint origin, O_k <- O_k D_k; that is,
  t_k and r_k are expressed in the nominal joint frame (parent-side, before the motion).
  Exp is the SO(3) exponential (Rodrigues); r_k is meant to be small but any value is exact.

With ``tip_errors=True`` (the default) six more, ``tip/tx`` ... ``tip/rz``, give
D_tip = [Exp(r) | t] at the tip link frame: T_base_tip <- T_base_tip D_tip.  Its translation
is the error of the marker mount (for a point on the tip link it is exactly a shift of that
point), its rotation turns the point about the tip origin.

The vector is joint-major in chain order, tip block last: length 7 n (+ 6).  It is complete
to first order - an error in any fixed joint of the chain is equivalent to one in the next
movable joint's D or in D_tip - but not minimal: for a revolute joint r_k along a_k is exactly
the offset o_k, and link errors along parallel axes trade off.  A prior on the parameters
(and a solver that tolerates rank deficiency) handles that.

Jacobians
---------
With F_k = the world pose of the joint frame after D_k (rotation R_k, origin p_k), the point
x and d = x - p_k::

    dx/dq_k  = (R_k a_k) x d                (revolute/continuous)      R_k a_k   (prismatic)
    dx/do_k  = dx/dq_k
    dx/dt_k  = R_k Exp(r_k)^T                (the nominal joint frame's rotation)
    dx/dr_k  = -[d]x R_k J_r(r_k)            (J_r the right Jacobian of SO(3); I at r = 0)

and likewise for the tip block with F = the tip frame after D_tip.

Everything is vectorised over M configurations: arrays of shape (M, ...) with loops only over
the joints.
"""

from dataclasses import dataclass
from typing import List, Optional, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from armcal_ros.core.geometry import skew
from .urdf import load_urdf, parse_urdf, UrdfModel

ERROR_FIELDS = ('offset', 'tx', 'ty', 'tz', 'rx', 'ry', 'rz')
TIP_ERROR_FIELDS = ('tx', 'ty', 'tz', 'rx', 'ry', 'rz')
TIP_ERROR_PREFIX = 'tip'


def so3_exp(r):
    """Rotation matrix Exp(r) of a rotation vector r (3,)."""
    return Rotation.from_rotvec(np.asarray(r, float)).as_matrix()


def so3_right_jacobian(r):
    """
    Right Jacobian J_r(r) of SO(3), so that Exp(r + dr) = Exp(r) Exp(J_r(r) dr) + O(dr^2).

    J_r = I - (1 - cos t) / t^2 [r]x + (t - sin t) / t^3 [r]x^2,  t = |r|.
    """
    r = np.asarray(r, float)
    t2 = float(r @ r)
    K = skew(r)
    if t2 < 1e-8:
        a = 0.5 - t2 / 24.0
        b = 1.0 / 6.0 - t2 / 120.0
    else:
        t = np.sqrt(t2)
        a = (1.0 - np.cos(t)) / t2
        b = (t - np.sin(t)) / (t2 * t)
    return np.eye(3) - a * K + b * (K @ K)


def _z_to_axis(axis):
    """Return a rotation P with P e_z = ``axis`` (unit); the identity when the axis is +z."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, axis)
    sin_angle = np.linalg.norm(v)
    if sin_angle < 1e-15:
        return np.eye(3) if axis[2] > 0 else np.diag([1.0, -1.0, -1.0])
    return so3_exp(v / sin_angle * np.arctan2(sin_angle, axis[2]))


def _turn_about_z(R, angles):
    """R Rz(angles) for R (M or 1, 3, 3) and angles (M,): only two columns change."""
    c = np.cos(angles)[:, None]
    s = np.sin(angles)[:, None]
    out = np.empty((angles.shape[0], 3, 3))
    out[:, :, 0] = c * R[:, :, 0] + s * R[:, :, 1]
    out[:, :, 1] = c * R[:, :, 1] - s * R[:, :, 0]
    out[:, :, 2] = R[:, :, 2]
    return out


def _apply(R, p, v):
    """Transform point(s) v by frames (R (M,3,3), p (M,3)); v is (3,) or (M, 3)."""
    if v.ndim == 1:
        return p + R @ v
    return p + np.einsum('mij,mj->mi', R, v)


def _unturn(R, P):
    """R P^T, skipping the product when P is the identity."""
    return R if P is None else R @ P.T


def _homogeneous(R, p):
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = p
    T[..., 3, 3] = 1.0
    return T


@dataclass(frozen=True)
class _Segment:
    """One movable joint with the fixed transforms before it folded into its origin."""

    name: str
    type: str
    axis: np.ndarray
    R0: np.ndarray
    p0: np.ndarray
    P: np.ndarray

    @property
    def Pturn(self):
        """P, or None when it is the identity."""
        return None if np.array_equal(self.P, np.eye(3)) else self.P


class KinematicChain:
    """
    The serial chain of a URDF from ``base_frame`` to ``tip_link``.

    Attributes: ``joint_names`` (movable joints, chain order), ``n_joints``, ``joint_types``,
    ``joint_axes`` (n, 3; in each joint's frame), ``lower``/``upper`` (n,) position limits
    (radians or metres; -inf/+inf for continuous joints), ``velocity_limits`` and
    ``effort_limits`` (n,; inf where the URDF gives none),
    ``error_names``/``n_errors`` (see the module docstring), ``chain_links`` (the child link
    of each movable joint), ``link_masses`` (n,) and ``link_coms`` (n, 3): the mass and
    centre of mass (in the ``chain_links`` frame) of everything rigidly attached to that link
    through fixed joints, including off-chain links; links fixed to the base carry no joint
    load and are left out.
    """

    def __init__(self, model: UrdfModel, base_frame: str = 'base_link',
                 tip_link: str = 'tool0', tip_errors: bool = True):
        if not isinstance(model, UrdfModel):
            raise ValueError(f'model must be a UrdfModel, got {type(model).__name__}')
        joints = model.chain(base_frame, tip_link)
        self.model = model
        self.base_frame = base_frame
        self.tip_link = tip_link
        self.tip_errors = bool(tip_errors)
        segments: List[_Segment] = []
        T = np.eye(4)
        for joint in joints:
            T = T @ joint.origin
            if joint.movable:
                segments.append(_Segment(joint.name, joint.type, joint.axis.copy(),
                                         T[:3, :3].copy(), T[:3, 3].copy(),
                                         _z_to_axis(joint.axis)))
                T = np.eye(4)
        if not segments:
            raise ValueError(f'the chain from {base_frame!r} to {tip_link!r} has no movable '
                             'joint')
        self._segments = segments
        self._R_tail = T[:3, :3].copy()
        self._p_tail = T[:3, 3].copy()
        movable = [j for j in joints if j.movable]
        self.joint_names = [j.name for j in movable]
        self.n_joints = len(movable)
        self.joint_types = [j.type for j in movable]
        self.joint_axes = np.array([j.axis for j in movable])
        self.lower = np.array([j.lower for j in movable], float)
        self.upper = np.array([j.upper for j in movable], float)
        self.velocity_limits = np.array([j.velocity for j in movable], float)
        self.effort_limits = np.array([j.effort for j in movable], float)
        self.chain_links = [j.child for j in movable]
        self._revolute = np.array([t != 'prismatic' for t in self.joint_types])
        names = [f'{j}/{f}' for j in self.joint_names for f in ERROR_FIELDS]
        if self.tip_errors:
            names += [f'{TIP_ERROR_PREFIX}/{f}' for f in TIP_ERROR_FIELDS]
        self.error_names = names
        self.n_errors = len(names)
        masses, coms = [], []
        for link in self.chain_links:
            m, c = self._rigid_mass(link)
            masses.append(m)
            coms.append(c)
        self.link_masses = np.array(masses)
        self.link_coms = np.array(coms).reshape(-1, 3)

    @classmethod
    def from_urdf(cls, text: str, base_frame: str = 'base_link', tip_link: str = 'tool0',
                  tip_errors: bool = True) -> 'KinematicChain':
        """Build the chain from URDF XML text (see ``parse_urdf``)."""
        return cls(parse_urdf(text), base_frame, tip_link, tip_errors)

    @classmethod
    def from_file(cls, path, base_frame: str = 'base_link', tip_link: str = 'tool0',
                  tip_errors: bool = True) -> 'KinematicChain':
        """Build the chain from a URDF file."""
        return cls(load_urdf(path), base_frame, tip_link, tip_errors)

    def _rigid_mass(self, link):
        """Mass and centre of mass (in ``link``'s frame) of the rigid body holding ``link``."""
        total, moment = 0.0, np.zeros(3)
        stack = [(link, np.eye(4))]
        while stack:
            name, T = stack.pop()
            body = self.model.links[name]
            total += body.mass
            moment += body.mass * (T[:3, :3] @ body.com + T[:3, 3])
            for joint in self.model.child_joints(name):
                if joint.type == 'fixed':
                    stack.append((joint.child, T @ joint.origin))
        com = moment / total if total > 0 else np.zeros(3)
        return total, com

    # ---- argument checks ---------------------------------------------------------------

    def _check_q(self, q):
        q = np.asarray(q, dtype=float)
        if q.ndim == 1:
            q = q[None, :]
        if q.ndim != 2 or q.shape[1] != self.n_joints:
            raise ValueError(f'q must have shape ({self.n_joints},) or (M, {self.n_joints}) '
                             f'for joints {self.joint_names}, got {np.shape(q)}')
        return q

    def _check_errors(self, errors):
        if errors is None:
            return None
        e = np.asarray(errors, dtype=float)
        if e.shape != (self.n_errors,):
            raise ValueError(f'errors must have shape ({self.n_errors},), got {e.shape}')
        if not np.all(np.isfinite(e)):
            raise ValueError('errors must be finite')
        return e

    def _check_point(self, point, M):
        p = np.asarray(point, dtype=float)
        if p.shape != (3,) and p.shape != (M, 3):
            raise ValueError(f'point must have shape (3,) or ({M}, 3), got {p.shape}')
        return p

    # ---- joint-name mapping ----------------------------------------------------------

    def index_map(self, names: Sequence[str]) -> np.ndarray:
        """
        Return the index into ``names`` of each chain joint: ``q = positions[..., idx]``.

        ``names`` may list the joints in any order and carry extra joints (ignored).  Raises
        ValueError naming any chain joint that is missing or listed more than once.
        """
        if isinstance(names, str):
            raise ValueError('names must be a sequence of joint names, not a single string')
        names = list(names)
        where = {}
        for i, name in enumerate(names):
            where.setdefault(name, []).append(i)
        missing = [j for j in self.joint_names if j not in where]
        if missing:
            raise ValueError(f'joint(s) {", ".join(missing)} of the chain {self.base_frame!r} '
                             f'-> {self.tip_link!r} missing from joint names {names}')
        repeated = [j for j in self.joint_names if len(where[j]) > 1]
        if repeated:
            raise ValueError(f'joint(s) {", ".join(repeated)} listed more than once in joint '
                             f'names {names}')
        return np.array([where[j][0] for j in self.joint_names], dtype=int)

    def error_vector(self, offset: float = 0.0, translation: float = 0.0,
                     rotation: float = 0.0, prismatic_offset: Optional[float] = None,
                     tip_translation: Optional[float] = None,
                     tip_rotation: Optional[float] = None) -> np.ndarray:
        """
        Return an (n_errors,) vector holding one value per kind of error parameter.

        Handy for prior standard deviations or for scaling random draws: ``offset`` for the
        revolute offsets (rad), ``prismatic_offset`` (m, default ``translation``),
        ``translation`` (m) and ``rotation`` (rad) for the joint origins, and
        ``tip_translation``/``tip_rotation`` for the tip block (default: the joint values).
        """
        prismatic_offset = translation if prismatic_offset is None else prismatic_offset
        block = np.empty((self.n_joints, 7))
        block[:, 0] = np.where(self._revolute, offset, prismatic_offset)
        block[:, 1:4] = translation
        block[:, 4:7] = rotation
        out = [block.ravel()]
        if self.tip_errors:
            tt = translation if tip_translation is None else tip_translation
            tr = rotation if tip_rotation is None else tip_rotation
            out.append(np.array([tt, tt, tt, tr, tr, tr], float))
        return np.concatenate(out)

    def sample_configurations(self, m: int, rng=None) -> np.ndarray:
        """
        Return ``m`` joint configurations (m, n) drawn uniformly within the URDF limits.

        Continuous joints (infinite limits) are drawn over [-pi, pi].
        """
        if int(m) != m or m < 1:
            raise ValueError(f'm must be a positive integer, got {m}')
        rng = rng if rng is not None else np.random.default_rng(0)
        lo = np.where(np.isfinite(self.lower), self.lower, -np.pi)
        hi = np.where(np.isfinite(self.upper), self.upper, np.pi)
        return rng.uniform(lo, hi, (int(m), self.n_joints))

    # ---- forward kinematics ----------------------------------------------------------

    def _forward(self, q, errors, keep_joint_frames=False, keep_link_frames=False):
        """
        Propagate world frames along the chain.

        Returns (R_tip, p_tip, R_tip_nominal, joint_frames, link_frames): the tip frame after
        D_tip, the tip frame before D_tip, per movable joint the frame F_k after D_k (before
        the motion), and per movable joint the child link frame (after the motion).  R arrays
        have shape (M, 3, 3) or (1, 3, 3) when nothing depends on q; p arrays (M, 3).
        """
        # Internally each joint frame is turned by P (P e_z = axis) so that every motion is
        # about or along z: R Rz(v) changes two columns only.  R here is the true frame times
        # P of the last joint passed; ``Pt`` (P^T) undoes that in the next origin.
        M = q.shape[0]
        R = np.eye(3)[None]
        p = np.zeros((1, 3))
        Pt = np.eye(3)
        joint_frames, link_frames = [], []
        for k, seg in enumerate(self._segments):
            R0, p0 = seg.R0, seg.p0
            value = q[:, k]
            if errors is not None:
                e = errors[7 * k:7 * k + 7]
                p0 = p0 + R0 @ e[1:4]
                R0 = R0 @ so3_exp(e[4:7])
                value = value + e[0]
            p = p + R @ (Pt @ p0)
            R = R @ (Pt @ R0 @ seg.P)
            if keep_joint_frames:
                joint_frames.append((_unturn(R, seg.Pturn), np.broadcast_to(p, (M, 3))))
            if seg.type == 'prismatic':
                p = p + R[:, :, 2] * value[:, None]
            else:
                R = _turn_about_z(R, value)
            if keep_link_frames:
                link_frames.append((np.broadcast_to(_unturn(R, seg.Pturn), (M, 3, 3)),
                                    np.broadcast_to(p, (M, 3))))
            Pt = seg.P.T
        p = p + R @ (Pt @ self._p_tail)
        R = R @ (Pt @ self._R_tail)
        R_nominal = R
        if self.tip_errors and errors is not None:
            e = errors[-6:]
            p = p + R @ e[:3]
            R = R @ so3_exp(e[3:])
        p = np.broadcast_to(p, (M, 3))
        return R, p, R_nominal, joint_frames, link_frames

    def fk_pose(self, q, errors=None) -> np.ndarray:
        """Pose of the tip link in the base frame, (M, 4, 4), for q of shape (n,) or (M, n)."""
        q = self._check_q(q)
        R, p, _, _, _ = self._forward(q, self._check_errors(errors))
        return _homogeneous(np.broadcast_to(R, (q.shape[0], 3, 3)), p)

    def fk(self, q, point=(0.0, 0.0, 0.0), errors=None) -> np.ndarray:
        """
        Position in the base frame of ``point`` (3,) or (M, 3), given in the tip link frame.

        ``errors`` is an optional (n_errors,) error-parameter vector; None is the nominal
        robot (identical to zeros).  Returns (M, 3).
        """
        q = self._check_q(q)
        point = self._check_point(point, q.shape[0])
        R, p, _, _, _ = self._forward(q, self._check_errors(errors))
        return _apply(R, p, point)

    def link_frames(self, q, errors=None) -> np.ndarray:
        """World poses (M, n, 4, 4) of each ``chain_links`` frame (movable joint's child)."""
        q = self._check_q(q)
        _, _, _, _, links = self._forward(q, self._check_errors(errors),
                                          keep_link_frames=True)
        R = np.stack([r for r, _ in links], axis=1)
        p = np.stack([t for _, t in links], axis=1)
        return _homogeneous(R, p)

    # ---- Jacobians ---------------------------------------------------------------------

    def _joint_columns(self, x, joint_frames):
        """Return dx/dq_k for every movable joint: (M, 3, n)."""
        cols = []
        for seg, (R, p) in zip(self._segments, joint_frames):
            z = np.broadcast_to(R @ seg.axis, x.shape)
            cols.append(z if seg.type == 'prismatic' else np.cross(z, x - p))
        return np.stack(cols, axis=2)

    def jacobian_q(self, q, point=(0.0, 0.0, 0.0), errors=None) -> np.ndarray:
        """Analytic d fk / d q, shape (M, 3, n), at the (optionally erroneous) robot."""
        q = self._check_q(q)
        point = self._check_point(point, q.shape[0])
        R, p, _, frames, _ = self._forward(q, self._check_errors(errors),
                                           keep_joint_frames=True)
        x = _apply(R, p, point)
        return self._joint_columns(x, frames)

    def jacobian_errors(self, q, point=(0.0, 0.0, 0.0), errors=None) -> np.ndarray:
        """
        Analytic d fk / d errors, shape (M, 3, n_errors), evaluated at ``errors``.

        Column order follows ``error_names``.  See the module docstring for the formulas.
        """
        q = self._check_q(q)
        M = q.shape[0]
        point = self._check_point(point, M)
        e = self._check_errors(errors)
        e0 = np.zeros(self.n_errors) if e is None else e
        R, p, R_nom, frames, _ = self._forward(q, e, keep_joint_frames=True)
        x = _apply(R, p, point)
        J = np.empty((M, 3, self.n_errors))
        J[:, :, 0:7 * self.n_joints:7] = self._joint_columns(x, frames)
        for k, (Rk, pk) in enumerate(frames):
            r = e0[7 * k + 4:7 * k + 7]
            J[:, :, 7 * k + 1:7 * k + 4] = Rk @ so3_exp(r).T
            J[:, :, 7 * k + 4:7 * k + 7] = -skew(x - pk) @ (Rk @ so3_right_jacobian(r))
        if self.tip_errors:
            r = e0[-3:]
            J[:, :, -6:-3] = R_nom
            J[:, :, -3:] = -skew(x - p) @ (R @ so3_right_jacobian(r))
        return J

    # ---- gravity -----------------------------------------------------------------------

    def gravity_torques(self, q, gravity=(0.0, 0.0, -9.81), errors=None) -> np.ndarray:
        """
        Generalised gravity force on each movable joint, (M, n), in N m (N for prismatic).

        tau_k = -dV/dq_k with V = -sum_i m_i g . c_i (c_i the world centre of mass of chain
        body i); so tau_k = (R_k a_k) . sum_{i >= k} m_i (c_i - p_k) x g for a revolute joint
        and (R_k a_k) . g sum_{i >= k} m_i for a prismatic one.  It is the torque gravity
        applies to the joint (the drive holds -tau); a joint of stiffness K deflects by
        tau / K.  ``gravity`` is in the base frame (m/s^2).
        """
        q = self._check_q(q)
        g = np.asarray(gravity, dtype=float)
        if g.shape != (3,):
            raise ValueError(f'gravity must have shape (3,), got {g.shape}')
        _, _, _, frames, links = self._forward(q, self._check_errors(errors),
                                               keep_joint_frames=True, keep_link_frames=True)
        M = q.shape[0]
        # moments m_i c_i and masses of bodies i >= k, accumulated from the tip down
        moment = np.zeros((M, 3))
        mass = 0.0
        tau = np.empty((M, self.n_joints))
        for k in range(self.n_joints - 1, -1, -1):
            Rl, pl = links[k]
            m = self.link_masses[k]
            moment = moment + m * _apply(Rl, pl, self.link_coms[k])
            mass += m
            Rk, pk = frames[k]
            z = np.broadcast_to(Rk @ self._segments[k].axis, (M, 3))
            if self._segments[k].type == 'prismatic':
                tau[:, k] = mass * (z @ g)
            else:
                tau[:, k] = np.einsum('mi,mi->m', z, np.cross(moment - mass * pk, g))
        return tau
