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
"""

from dataclasses import dataclass
from typing import Dict, Optional, Sequence

import numpy as np

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
