"""
Whether a camera kept its lens, or its pose, through a change: what its two epochs may share.

A camera that changed has views from before the change.  Solved as a camera of their own
beside the rest (its *earlier self*), they keep tying the other cameras and the arm's model
to the images, which retiring them loses.  What the two epochs still have in common ties them
closer, and that is where most of the gain is:

- a camera that moved (a knock) keeps its lens: shared across the epochs, the earlier views
  pin the intrinsics that the camera's few new views alone determine poorly;
- a camera whose lens changed (a refocus, a zoom) keeps its pose: shared, the earlier views
  pin the pose, and with it the arm's model and the other cameras, as before the change.

Sharing a part that changed bends both epochs to one wrong lens or pose, which is far worse
than not sharing (docs/BENCHMARKS.md, *changes*).  So the adjustment first solves the two
epochs with everything their own, and these tests decide from that solve.

With a the shared part's parameters and C the adjustment's covariance of the camera
parameters, d = a_old - a_new and D = C_oo + C_nn - C_on - C_no, Wald's test of d = 0 is
W = d^T D^-1 d, chi^2 with k = dim(a) degrees of freedom under one lens (or pose).

- The lens, a = (fx, fy, cx, cy, the free distortion terms), with a focused test of the focal
  length, which a refocus or a zoom moves first: with f the mean of fx and fy,
  z = (f_old - f_new) / sd, standard normal under one lens.  Over k = 8 parameters Wald's test
  spreads its power; a 0.5 % refocus showed as |z| of 2-7 where W was 16-51 (99 % point 20.1).
- The pose, a = (w, t): the rotation difference log(R_old R_new^T) (the solver's rotation
  increments, R <- exp(w) R, are taken on the same side) and t_old - t_new, k = 6.

A part is shared when no test rejects at ``alpha`` each (0.01: one lens judged two in about
2 % of cases, whose epochs are then solved apart, the safe side).  The covariance is the
adjustment's own, at the image noise it estimated; if it understates the errors, the tests
reject more often, which again errs on the safe side.
"""

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2, norm

from armcal_ros.core.camera import DISTORTION_NAMES, INTRINSIC_NAMES

#: Significance of each of the two tests.
ALPHA = 0.01


@dataclass
class LensTest:
    """The verdict on two cameras' lenses (``same``) and the statistics behind it."""

    same: bool
    wald: float
    dof: int
    wald_limit: float
    focal_z: float
    focal_limit: float
    message: str


def lens_test(adjustment, old: str, new: str, alpha: float = ALPHA) -> LensTest:
    """
    Test whether cameras ``old`` and ``new`` of ``adjustment`` have the same lens.

    ``adjustment`` is an :class:`~armcal_ros.core.adjustment.AdjustmentResult` that solved
    both with lenses of their own (no shared lens between them).  Raises ValueError if either
    camera's intrinsics are not among its parameters.
    """
    names = _check(adjustment, alpha)
    head = [p for p in INTRINSIC_NAMES + tuple(DISTORTION_NAMES) if f'{old}/{p}' in names]
    if len(head) < 4 or any(f'{new}/{p}' not in names for p in head):
        raise ValueError(f'cameras {old!r} and {new!r} must both have their intrinsics among '
                         'the adjustment\'s parameters')
    a_old, a_new = (_head(adjustment.cameras[n].camera, head) for n in (old, new))
    d = a_old - a_new
    D, wald = _wald(adjustment, names, old, new, head, d)
    k = len(head)
    wald_limit, focal_limit = float(chi2.ppf(1.0 - alpha, k)), float(norm.ppf(1.0 - alpha / 2))
    var_f = 0.25 * (D[0, 0] + D[1, 1] + 2.0 * D[0, 1])
    z = float(0.5 * (d[0] + d[1]) / np.sqrt(var_f)) if var_f > 0 else float('nan')
    same = bool(np.isfinite(wald) and np.isfinite(z) and wald <= wald_limit and
                abs(z) <= focal_limit)
    message = (f'Wald {wald:.1f} (limit {wald_limit:.1f}, {k} dof), focal z {z:+.2f} '
               f'(limit {focal_limit:.2f}): {"one lens" if same else "two lenses"}')
    return LensTest(same, wald, k, wald_limit, z, focal_limit, message)


def _check(adjustment, alpha):
    """Return the adjustment's parameter names once ``alpha`` is known to be a probability."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f'alpha must be in (0, 1), got {alpha}')
    return list(adjustment.parameter_names or [])


def _wald(adjustment, names, old, new, head, d):
    """Return (D, W = d^T D^-1 d) over parameters ``head`` of cameras ``old`` and ``new``."""
    io = [names.index(f'{old}/{p}') for p in head]
    i_n = [names.index(f'{new}/{p}') for p in head]
    C = np.asarray(adjustment.covariance, float)
    D = C[np.ix_(io, io)] + C[np.ix_(i_n, i_n)] - C[np.ix_(io, i_n)] - C[np.ix_(i_n, io)]
    try:
        return D, float(d @ np.linalg.solve(D, d))
    except np.linalg.LinAlgError:
        return D, float('nan')


def _head(camera, head):
    values = dict(zip(INTRINSIC_NAMES, camera.intrinsics()))
    values.update(zip(DISTORTION_NAMES, camera.dist))
    return np.array([values[p] for p in head], float)


@dataclass
class PoseTest:
    """The verdict on two cameras' poses (``same``) and the statistics behind it."""

    same: bool
    wald: float
    dof: int
    wald_limit: float
    rotation_deg: float
    translation_m: float
    message: str


def pose_test(adjustment, old: str, new: str, alpha: float = ALPHA) -> PoseTest:
    """
    Test whether cameras ``old`` and ``new`` of ``adjustment`` have the same pose.

    ``adjustment`` is an :class:`~armcal_ros.core.adjustment.AdjustmentResult` that solved
    both with poses of their own (no shared pose between them).  Raises ValueError if either
    camera's pose is not among its parameters.
    """
    names = _check(adjustment, alpha)
    head = ['wx', 'wy', 'wz', 'tx', 'ty', 'tz']
    if any(f'{n}/{p}' not in names for n in (old, new) for p in head):
        raise ValueError(f'cameras {old!r} and {new!r} must both have their poses among '
                         'the adjustment\'s parameters')
    a, b = adjustment.cameras[old].camera, adjustment.cameras[new].camera
    d = np.concatenate([Rotation.from_matrix(a.rotation @ b.rotation.T).as_rotvec(),
                        a.translation - b.translation])
    _, wald = _wald(adjustment, names, old, new, head, d)
    k = len(head)
    wald_limit = float(chi2.ppf(1.0 - alpha, k))
    same = bool(np.isfinite(wald) and wald <= wald_limit)
    rot = float(np.degrees(np.linalg.norm(d[:3])))
    shift = float(np.linalg.norm(a.center - b.center))
    message = (f'Wald {wald:.1f} (limit {wald_limit:.1f}, {k} dof; {rot:.3f} deg, '
               f'{1e3 * shift:.1f} mm apart): {"one pose" if same else "two poses"}')
    return PoseTest(same, wald, k, wald_limit, rot, shift, message)
