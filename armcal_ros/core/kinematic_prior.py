"""
The ``kinematic`` prior: the covariance the arm's own error sources imply.

X_i = X^_i + J_p(q_i) dp + e_i with dp ~ N(0, S_p), S_p = diag(sigma_p^2), and e_i ~ N(0, s_n^2 I).
J_p (N, 3, P) is the derivative of each measured marker position with respect to the kinematic
error parameters (per joint: angle offset and joint-origin translation/rotation errors; the
marker mount), evaluated at the nominal robot - :meth:`KinematicChain.jacobian_errors` computes
it.  Core stays robot-agnostic: it takes J_p, the parameter names and sigma_p.

dp enters the adjustment as explicit global parameters, whitened (dp = sigma_p * g, g ~ N(0, I)),
next to the cameras in the reduced system; the points stay 3x3 blocks eliminated by the Schur
complement, so an iteration costs O(N P^2).

Observability: the parameter set is complete but not minimal (a revolute joint's rz equals its
offset; the base joint's origin errors are a rigid motion of everything, which the images cannot
see; link errors along parallel axes trade off).  The Gaussian prior makes the normal matrix
positive definite and leaves every direction the data cannot see at its prior mean (zero) with
its prior spread: nothing wanders and nothing is singular.  Redundant pairs share the correction
in proportion to their prior variances; only their sum matters for the points.

J_p is not re-linearised at the estimate: dp is of the order of 1e-3 (rad or m), so the neglected
second-order term is of the order of |dp|^2 x reach ~ 1 um, far below the pixel noise.

Default scales (:data:`DEFAULT_KINEMATIC_SCALES`, standard deviations) are typical before-
calibration errors of a mid-size industrial arm (Mooring, Roth and Driels, "Fundamentals of
Manipulator Calibration", 1991; ISO 9283 accuracy of about a millimetre against a repeatability
of a few hundredths): joint zero offsets 0.1 deg (encoder zeroing), joint-origin translations
0.5 mm (machining and assembly tolerances of link lengths and offsets), joint-origin rotations
0.05 deg (axis twist and parallelism), and the marker mount 1 mm per axis and 0.5 deg (a hand-
fitted adapter).  They are deliberately about twice the simulator's drawn magnitudes: a prior
should be wide enough for a real arm; ``auto`` tunes a common multiplier by evidence.

Gauge (:func:`base_motion_gauge`).  Some error directions move the marker, for every joint
configuration, by one and the same rigid motion of the base frame (the base joint's origin
errors and offset; on a PUMA also joint 2's origin translation along, and rotation about, the
base axis), and others do not move it at all (the redundancies above).  The cameras are fixed in
the world, not in the base frame, so such an error is indistinguishable from moving every camera
by the inverse motion: the images and joint readings are identical.  These directions form the
subspace U; two arms whose errors differ by a member of U produce the same data, and no
estimator can tell them apart.  ``BaseMotionGauge.canonical`` picks from that class the member
with the smallest prior norm, which is what an accuracy benchmark can fairly compare against.
"""

from dataclasses import dataclass
from typing import Dict, Optional, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from armcal_ros.core.geometry import skew

DEG = np.pi / 180.0

#: Standard deviations by parameter kind (radians and metres); see the module docstring.
DEFAULT_KINEMATIC_SCALES: Dict[str, float] = {
    'offset': 0.1 * DEG,
    'prismatic_offset': 0.5e-3,
    'translation': 0.5e-3,
    'rotation': 0.05 * DEG,
    'tip_translation': 1.0e-3,
    'tip_rotation': 0.5 * DEG,
}


def kinematic_sigmas(error_names: Sequence[str], scales: Optional[Dict[str, float]] = None,
                     prismatic: Sequence[str] = ()) -> np.ndarray:
    """
    Prior standard deviations (P,) for parameters named like ``KinematicChain.error_names``.

    Names are ``<joint>/<field>`` with field offset, tx, ty, tz, rx, ry, rz, and
    ``tip/<field>`` for the marker mount.  ``scales`` overrides entries of
    :data:`DEFAULT_KINEMATIC_SCALES`; ``prismatic`` names joints whose offset is a length.
    """
    s = dict(DEFAULT_KINEMATIC_SCALES)
    if scales:
        unknown = set(scales) - set(s)
        if unknown:
            raise ValueError(f'kinematic scales has unknown keys {sorted(unknown)}; '
                             f'allowed: {sorted(s)}')
        s.update(scales)
    out = np.empty(len(error_names))
    for i, name in enumerate(error_names):
        if '/' not in name:
            raise ValueError(f'error name {name!r} is not <joint>/<field>')
        joint, fld = name.rsplit('/', 1)
        tip = joint == 'tip'
        if fld == 'offset':
            out[i] = s['prismatic_offset'] if joint in prismatic else s['offset']
        elif fld in ('tx', 'ty', 'tz'):
            out[i] = s['tip_translation'] if tip else s['translation']
        elif fld in ('rx', 'ry', 'rz'):
            out[i] = s['tip_rotation'] if tip else s['rotation']
        else:
            raise ValueError(f'error name {name!r} has unknown field {fld!r}')
    return out


@dataclass
class KinematicData:
    """
    What the ``kinematic`` and ``hybrid`` priors need per measured point.

    ``jacobian`` (N, 3, P): d X^_i / d dp at the nominal robot; ``names`` (P,) parameter names;
    ``sigma`` (P,) prior standard deviations (default from :func:`kinematic_sigmas`).
    """

    jacobian: np.ndarray
    names: Sequence[str]
    sigma: Optional[np.ndarray] = None

    def __post_init__(self):
        self.jacobian = np.asarray(self.jacobian, float)
        if self.jacobian.ndim != 3 or self.jacobian.shape[1] != 3:
            raise ValueError(f'kinematics.jacobian must have shape (N, 3, P), '
                             f'got {self.jacobian.shape}')
        if not np.all(np.isfinite(self.jacobian)):
            raise ValueError('kinematics.jacobian contains NaN or inf')
        self.names = list(self.names)
        p = self.jacobian.shape[2]
        if len(self.names) != p:
            raise ValueError(f'kinematics.names has {len(self.names)} entries for {p} '
                             'jacobian columns')
        if self.sigma is None:
            self.sigma = kinematic_sigmas(self.names)
        self.sigma = np.asarray(self.sigma, float).reshape(-1)
        if self.sigma.shape != (p,) or np.any(self.sigma < 0) or \
                not np.all(np.isfinite(self.sigma)):
            raise ValueError(f'kinematics.sigma must be ({p},) finite and >= 0, '
                             f'got shape {self.sigma.shape}')

    @property
    def n(self):
        """Return the number of points."""
        return self.jacobian.shape[0]

    def subset(self, index):
        """Return the same data for a subset of the points."""
        return KinematicData(self.jacobian[index], self.names, self.sigma)

    def scaled(self, factor):
        """Return the same data with every prior sigma multiplied by ``factor``."""
        return KinematicData(self.jacobian, self.names, self.sigma * float(factor))

    def whitened_design(self, scale=1.0):
        """J_p diag(scale * sigma_p), (N, 3, P): the design of the whitened parameters."""
        return self.jacobian * (self.sigma * scale)[None, None, :]


def rigid_motion_jacobian(points) -> np.ndarray:
    """
    Return the derivative (M, 3, 6) of points (M, 3) under a small rigid motion of their frame.

    x -> Exp(w) x + t, so dx/d(w, t) = [-[x]x | I] at w = t = 0 (rotation first).
    """
    x = np.asarray(points, float)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f'points must have shape (M, 3), got {x.shape}')
    G = np.zeros((x.shape[0], 3, 6))
    G[:, :, :3] = -skew(x)
    G[:, :, 3:] = np.eye(3)
    return G


@dataclass
class BaseMotionGauge:
    """
    The error directions the data cannot see, U, and the canonical representative of a truth.

    ``basis`` (P, k) is an orthonormal basis of U in whitened coordinates z = dp / sigma, so
    that Z Z^T is the orthogonal projection in the metric of the prior N(0, diag(sigma^2)).
    ``singular_values`` (descending, metres RMS per unit z) are those of the whitened Jacobian
    with the rigid motions projected out; ``n_observable`` of them are kept as non-zero.
    """

    basis: np.ndarray
    sigma: np.ndarray
    singular_values: np.ndarray
    n_observable: int

    def _check(self, errors):
        e = np.asarray(errors, float)
        if e.shape != self.sigma.shape:
            raise ValueError(f'errors must have shape {self.sigma.shape}, got {e.shape}')
        return e

    def unobservable_part(self, errors) -> np.ndarray:
        """Return the prior-metric projection of ``errors`` (P,) onto U."""
        z = self._check(errors) / self.sigma
        return self.sigma * (self.basis @ (self.basis.T @ z))

    def canonical(self, errors) -> np.ndarray:
        """
        Return the member of ``errors + U`` with the smallest prior norm, (P,).

        argmin_{u in U} (e - u)^T diag(sigma)^-2 (e - u) = e - sigma Z Z^T (e / sigma):
        every error vector that gives the same data maps to the same canonical vector.
        """
        return self._check(errors) - self.unobservable_part(errors)


def base_motion_gauge(jacobian, points, sigma, rtol: float = 1e-8) -> BaseMotionGauge:
    """
    Find U, the error directions that move the marker only by one rigid base-frame motion.

    ``jacobian`` (M, 3, P) is d x / d dp at M joint configurations that should cover the arm's
    whole range (every configuration it may be measured in), ``points`` (M, 3) the marker
    positions there, ``sigma`` (P,) > 0 the prior standard deviations that define the metric.

    Method: dp is in U if and only if there is one small rigid motion v = (w, t) with
    J(q) dp = G(x(q)) v for every q, G = :func:`rigid_motion_jacobian`; that is, if the stacked
    J dp lies in the column space of the stacked G.  So with Q an orthonormal basis of the
    stacked G (3M x 6) and the whitened Jacobian A = J diag(sigma) (3M x P), U is the null space
    of (I - Q Q^T) A: the right singular vectors whose singular value is below ``rtol`` times
    the largest (the gap is many orders of magnitude: 1e-2 against 1e-15 mm on a PUMA 560).
    It includes the null space of J itself (the zero motion).  First order in dp: the
    neglected term is |dp|^2 x reach, a micrometre for millimetre errors.
    """
    J = np.asarray(jacobian, float)
    x = np.asarray(points, float)
    if J.ndim != 3 or J.shape[1] != 3:
        raise ValueError(f'jacobian must have shape (M, 3, P), got {J.shape}')
    m, _, p = J.shape
    if x.shape != (m, 3):
        raise ValueError(f'points must have shape ({m}, 3), got {x.shape}')
    sig = np.asarray(sigma, float).reshape(-1)
    if sig.shape != (p,) or not np.all(np.isfinite(sig)) or np.any(sig <= 0):
        raise ValueError(f'sigma must be ({p},) finite and > 0, got shape {sig.shape}')
    if m < 3:
        raise ValueError(f'need at least 3 configurations to separate rigid motions, got {m}')
    if not 0 < rtol < 1:
        raise ValueError(f'rtol must be in (0, 1), got {rtol}')
    Q, _ = np.linalg.qr(rigid_motion_jacobian(x).reshape(3 * m, 6))
    A = J.reshape(3 * m, p) * sig
    A = A - Q @ (Q.T @ A)
    _, sv, vt = np.linalg.svd(A, full_matrices=True)
    rank = int(np.count_nonzero(sv > rtol * sv[0])) if sv.size and sv[0] > 0 else 0
    return BaseMotionGauge(vt[rank:].T.copy(), sig, sv / np.sqrt(m), rank)


TIP_BLOCK = ('tip/tx', 'tip/ty', 'tip/tz', 'tip/rx', 'tip/ry', 'tip/rz')


def tip_place(result, guess):
    """
    Return (place (3,), std (3,)) of a point marker from an adjustment's tip errors, or None.

    With the marker's nominal points computed at ``guess`` m0 on the tip link, the tip error
    D_tip = [Exp(r) | t] moves it to p = Exp(r) m0 + t (module docstring of
    :mod:`armcal_ros.robot.kinematics`).  Its covariance is J S J^T with J = [I, -[p - t]x]
    and S the posterior covariance of (t, r): the whitened global block scaled by the prior
    standard deviations.  ``result`` is an adjustment result with a kinematic prior; None when
    it has no tip block (a chain built without tip errors) or no global covariance.
    """
    names = list(getattr(result.prior.kinematics, 'names', []) if result.prior is not None
                 and result.prior.kinematics is not None else [])
    if result.global_covariance is None or not all(n in names for n in TIP_BLOCK):
        return None
    m0 = np.asarray(guess, float).reshape(3)
    sl = result.prior.global_slices['kinematic']
    sig = result.prior.kinematics.sigma * result.prior_settings.kinematic_scale
    cols = [names.index(n) for n in TIP_BLOCK]
    dp = np.array([result.kinematic_errors[n] for n in TIP_BLOCK])
    cov_g = result.global_covariance[sl, sl][np.ix_(cols, cols)]
    S = cov_g * np.outer(sig[cols], sig[cols])
    rotated = Rotation.from_rotvec(dp[3:]).apply(m0)
    J = np.hstack([np.eye(3), -skew(rotated)])
    std = np.sqrt(np.maximum(np.diag(J @ S @ J.T), 0.0))
    return rotated + dp[:3], std
