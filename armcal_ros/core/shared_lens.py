"""
Whether a camera kept its lens through a change, so that its two epochs may share one lens.

A camera that moved has views from before the move.  Solved as a camera of their own beside
the rest (their own pose: the camera as it was), they keep tying the other cameras and the
arm's model to the images, which retiring them loses; with the lens shared across the two
epochs they also pin the moved camera's intrinsics, which its few new views alone determine
poorly.  Sharing a lens that changed (a refocus, a zoom, or a knock that turned a loose focus
ring) bends both epochs' poses to one wrong lens, which is far worse than not sharing
(docs/BENCHMARKS.md, *changes*).  So the adjustment first solves the two epochs with lenses
of their own, and this test decides from that solve.

With a = (fx, fy, cx, cy, the free distortion terms) and C the adjustment's covariance of
the camera parameters, d = a_old - a_new and D = C_oo + C_nn - C_on - C_no:

- Wald's test of d = 0: W = d^T D^-1 d, chi^2 with k = dim(a) degrees of freedom under one
  lens;
- a focused test of the focal length, which a refocus or a zoom moves first: with f the mean
  of fx and fy, z = (f_old - f_new) / sd, standard normal under one lens.  Over k = 8
  parameters Wald's test spreads its power; a 0.5 % refocus showed as |z| of 2-7 where W was
  16-51 (99 % point 20.1).

The lens is shared when neither test rejects at ``alpha`` each (0.01: one lens judged two in
about 2 % of cases, whose epochs are then solved apart, the safe side).  The covariance is
the adjustment's own, at the image noise it estimated; if it understates the errors, the
tests reject more often, which again errs on the safe side.
"""

from dataclasses import dataclass

import numpy as np
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
    if not 0.0 < alpha < 1.0:
        raise ValueError(f'alpha must be in (0, 1), got {alpha}')
    names = list(adjustment.parameter_names or [])
    head = [p for p in INTRINSIC_NAMES + tuple(DISTORTION_NAMES) if f'{old}/{p}' in names]
    if len(head) < 4 or any(f'{new}/{p}' not in names for p in head):
        raise ValueError(f'cameras {old!r} and {new!r} must both have their intrinsics among '
                         'the adjustment\'s parameters')
    io = [names.index(f'{old}/{p}') for p in head]
    i_n = [names.index(f'{new}/{p}') for p in head]
    C = np.asarray(adjustment.covariance, float)
    D = C[np.ix_(io, io)] + C[np.ix_(i_n, i_n)] - C[np.ix_(io, i_n)] - C[np.ix_(i_n, io)]
    a_old, a_new = (_head(adjustment.cameras[n].camera, head) for n in (old, new))
    d = a_old - a_new
    k = len(head)
    wald_limit, focal_limit = float(chi2.ppf(1.0 - alpha, k)), float(norm.ppf(1.0 - alpha / 2))
    try:
        wald = float(d @ np.linalg.solve(D, d))
    except np.linalg.LinAlgError:
        wald = float('nan')
    var_f = 0.25 * (D[0, 0] + D[1, 1] + 2.0 * D[0, 1])
    z = float(0.5 * (d[0] + d[1]) / np.sqrt(var_f)) if var_f > 0 else float('nan')
    same = bool(np.isfinite(wald) and np.isfinite(z) and wald <= wald_limit and
                abs(z) <= focal_limit)
    message = (f'Wald {wald:.1f} (limit {wald_limit:.1f}, {k} dof), focal z {z:+.2f} '
               f'(limit {focal_limit:.2f}): {"one lens" if same else "two lenses"}')
    return LensTest(same, wald, k, wald_limit, z, focal_limit, message)


def _head(camera, head):
    values = dict(zip(INTRINSIC_NAMES, camera.intrinsics()))
    values.update(zip(DISTORTION_NAMES, camera.dist))
    return np.array([values[p] for p in head], float)
