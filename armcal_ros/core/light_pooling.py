"""
A lit ball's centre from its low-noise centroid and its light shift pooled over many views.

Two centres come out of the shaded-sphere detector for each view m of camera c: the intensity
centroid ``c_m`` (low noise, but pulled towards the lit side) and the fitted centre ``s_m``
(unbiased, about twice as noisy: the fit also estimates the light).  Their difference
``d_m = s_m - c_m`` is the light's shift of the centroid plus the fit's extra noise.  For
light that is fixed in the cell the shift is a smooth function of where the ball is: it
depends on the direction to the lamps seen from the camera and on the ball's image size,
both of which change slowly along the workspace.  So the shift can be pooled over the
camera's views at nearby places and the centre taken as

    u_m = c_m + f(X_m),    f = the local-linear smooth of the d's over the nominal points X,

which carries the centroid's noise plus the smooth's (small) instead of the fit's.

The smooth at X_m is a weighted least-squares plane through its k nearest views, tricube
weights over the k-th neighbour's distance (local-linear regression, Cleveland 1979): a plane
follows a shift that changes along the workspace without the flattening of a local mean.  k
is chosen per camera by leave-one-out prediction of the d's: the error it measures is the
smooth's variance plus its bias plus the d's own noise, so the k that minimises it balances
the first two on the data at hand - a lamp close to the ball (a shift that changes quickly)
gets a small k, an evenly lit ball (no shift) a large one; one plane and one constant through
all the camera's views are the smoothest candidates.  Of the k's whose error is within
one standard error of the least, the largest is taken (the one-standard-error rule, Hastie,
Tibshirani and Friedman, *The Elements of Statistical Learning*, 7.10).

Assumption: the light does not move with the marker.  An LED whose brightest side turns with
the tool shifts its centroid with the tool's orientation, which this smooth over positions
does not see: use the per-view fit (``sphere_centre: shaded``) there.  Given each shift's own
noise, such a light is caught: the smooth then predicts left-out views far worse than their
noise (:data:`MAX_NOISE_RATIO`), and the fitted centres are kept.

Which of the two centres is better is not settled by the shifts alone: the leave-one-out
residual d - f = (s - truth) - (c + f - truth) is the difference of the two centres' errors,
and says nothing of which is the larger.  A centroid over a textured background is off by
its own, unsmooth, amount that the pooled centre carries; a fit's cold start may land in a
wrong minimum that the pooled centre does not.  A calibration of the views is the yardstick
that tells: the views are solved with each kind, and :func:`compare_solves` weighs each
kind's image noise from its own solve's residuals.
"""

from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy.spatial import cKDTree

#: Neighbourhood sizes tried per camera (views); at most the camera's view count - 1.
K_GRID = (8, 12, 16, 24, 32, 48, 64, 96, 128, 192, 256)
#: Fewer views than this per camera: nothing to pool over, the fitted centres are kept.
MIN_VIEWS = 12
#: Views the leave-one-out choice of k is scored at, at most.
MAX_SCORED = 400
#: The smooth must predict left-out views within this many times their own noise (RMS);
#: beyond it the shift is not a function of the ball's place (module doc) and the fitted
#: centres are kept.  About 1 under a lamp or even light; about 10 for an LED (a shift that
#: follows the tool's turn) on the simulator's recordings.
MAX_NOISE_RATIO = 3.0


@dataclass
class PooledShift:
    """
    One camera's pooled light shift.

    ``shift`` (M, 2) the smooth of the d's at each view (px), ``variance`` (M,) its variance
    per axis (px^2: the squared weights of its equivalent kernel times the d's noise),
    ``k`` the neighbourhood chosen (M for one plane or constant through all views),
    ``loo_rms`` its leave-one-out RMS prediction error per axis
    (px), ``status`` 'ok' or 'too_few' (then ``shift`` is the d's themselves), ``message``,
    ``noise_var`` the d's own noise variance per axis (px^2: the leave-one-out error less the
    smooth's part of it).
    """

    shift: np.ndarray
    variance: np.ndarray
    k: int
    loo_rms: float
    status: str
    message: str
    #: What :meth:`at` needs: the views' points and shifts and the smooth's global degree
    #: (None: local planes through ``k`` views).
    points: Optional[np.ndarray] = None
    shifts: Optional[np.ndarray] = None
    degree: Optional[int] = None
    noise_var: float = float('nan')

    def at(self, points) -> np.ndarray:
        """
        Return the smooth's shift (N, 2) at new places ``points`` (N, 3), the same smooth.

        What a new view's centroid is moved by, so that it is compared with the calibration
        as the solve's views were.  Only for a pooled shift (``status`` 'ok').
        """
        if self.status != 'ok' or self.points is None:
            raise ValueError(f'a shift is predicted only from a pooled one, status '
                             f'{self.status!r}')
        q = np.asarray(points, float).reshape(-1, 3)
        if self.degree is not None:
            return _global_fit(self.points, self.shifts, self.degree, False, query=q)
        return _local_linear(self.points, self.shifts, cKDTree(self.points), self.k, False,
                             query=q)[0]


def _local_linear(points, values, tree, k, leave_out, global_degree=None, at=None,
                  query=None):
    """
    Return (fit (M, 2), kernel_sq (M,)): each view's smooth and its squared weights' sum.

    The local-linear smooth over the k nearest views with tricube weights; with
    ``global_degree`` 1 or 0 instead a plane or a constant through all views, equally
    weighted (:func:`_global_fit`).  ``leave_out`` fits each view without itself (the
    cross-validation); ``at`` (indices) fits those views only (default all); ``query``
    (M, 3) fits at those places instead (new views: local planes only, no leave-out).
    """
    at = np.arange(len(points)) if at is None else at
    if global_degree is not None:
        fit, kernel_sq = _global_fit(points, values, global_degree, leave_out)
        return fit[at], kernel_sq[at]
    centre = points[at] if query is None else np.asarray(query, float)
    m = len(centre)
    dist, idx = tree.query(centre, k=k + 1)
    if query is None and leave_out:
        dist, idx = dist[:, 1:], idx[:, 1:]
    h = np.maximum(dist[:, -1:] * 1.0001, 1e-12)
    w = (1.0 - (dist / h) ** 3) ** 3
    dx = points[idx] - centre[:, None, :]                         # (M, k, 3)
    A = np.concatenate([np.ones(idx.shape + (1,)), dx / h[:, :, None]], axis=2)
    Aw = A * w[:, :, None]
    N = np.einsum('mka,mkb->mab', Aw, A)
    # A small ridge on the slopes keeps neighbourhoods on a line or a plane solvable; the
    # slopes are in units of the neighbourhood's size, so 1e-6 is negligible otherwise.
    N[:, 1:, 1:] += 1e-6 * np.eye(3) * N[:, :1, :1]
    # The intercept's row of N^-1 A^T W: the equivalent kernel of the smooth at the view.
    e0 = np.zeros((m, 4, 1))
    e0[:, 0, 0] = 1.0
    row = np.linalg.solve(N, e0)[:, :, 0]                         # (M, 4)
    kernel = np.einsum('ma,mka->mk', row, Aw)                     # (M, k)
    fit = np.einsum('mk,mkc->mc', kernel, values[idx])
    return fit, np.sum(kernel ** 2, axis=1)


def _global_fit(points, values, degree, leave_out, query=None):
    """
    Return (fit, kernel_sq) of one plane (``degree`` 1) or one constant (0) through all views.

    By the hat matrix H = A (A^T A)^-1 A^T, whose diagonal h gives the fit's squared weights
    (H is idempotent) and the leave-one-out prediction without refitting:
    y_(-i) = (Hy_i - h_i y_i) / (1 - h_i), with squared weights h_i / (1 - h_i).  With
    ``query`` (N, 3): the fit (N, 2) at those places alone.
    """
    span = max(float(np.ptp(points, axis=0).max()), 1e-12)

    def design(x):
        x = np.asarray(x, float)
        if degree == 1:
            return np.column_stack([np.ones(len(x)), (x - points.mean(axis=0)) / span])
        return np.ones((len(x), 1))
    A = design(points)
    if query is not None:
        return design(query) @ np.linalg.lstsq(A, values, rcond=None)[0]
    Q, _ = np.linalg.qr(A)
    fit = Q @ (Q.T @ values)
    h = np.minimum(np.sum(Q * Q, axis=1), 1.0 - 1e-9)
    if not leave_out:
        return fit, h
    return (fit - h[:, None] * values) / (1.0 - h[:, None]), h / (1.0 - h)


def pool_light_shift(points, shifts, noise_var=None) -> PooledShift:
    """
    Pool one camera's light shifts over its views (module doc).

    ``points`` (M, 3) the views' nominal marker positions (m), ``shifts`` (M, 2) fitted centre
    minus centroid (px), ``noise_var`` (M,) optional: each shift's own noise variance per axis
    (px^2, from the scatter of its frames).  With it, a smooth whose leave-one-out error
    exceeds :data:`MAX_NOISE_RATIO` times that noise is refused (status 'not_smooth', the
    fitted centres kept): the light moves with the marker.
    """
    points = np.asarray(points, float)
    shifts = np.asarray(shifts, float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f'points must have shape (M, 3), got {points.shape}')
    if shifts.shape != (points.shape[0], 2):
        raise ValueError(f'shifts must have shape ({points.shape[0]}, 2), got {shifts.shape}')
    if not (np.all(np.isfinite(points)) and np.all(np.isfinite(shifts))):
        raise ValueError('points and shifts must be finite')
    m = len(points)
    if m < MIN_VIEWS:
        return PooledShift(shifts.copy(), np.full(m, np.nan), 0, float('nan'), 'too_few',
                           f'{m} views < {MIN_VIEWS}: the fitted centres are kept')
    tree = cKDTree(points)
    # The choice is scored at up to MAX_SCORED views spread over the camera's (each predicted
    # from all the others): the mean error is the same, at a fraction of the cost.
    at = np.arange(0, m, max(1, m // MAX_SCORED))
    # From the roughest smooth to the smoothest: local planes, one plane, one constant.
    ks = [(k, None) for k in K_GRID if k < m - 1] + [(m - 1, 1), (m - 1, 0)]
    errors = np.array([np.mean((_local_linear(points, shifts, tree, k, True, g, at)[0] -
                                shifts[at]) ** 2, axis=1) for k, g in ks])   # (K, M) per axis
    best = int(np.argmin(errors.mean(axis=1)))
    # The one-standard-error rule: the widest neighbourhood whose prediction error is within
    # one standard error (paired over the views) of the best's.  Under even light the errors
    # are flat in k, and the minimum alone would be picked by the d's noise.
    diff = errors - errors[best]
    within = diff.mean(axis=1) <= diff.std(axis=1) / np.sqrt(len(at))
    choice = max(np.flatnonzero(within))
    (k, degree), err = ks[choice], float(errors[choice].mean())
    fit, kernel_sq = _local_linear(points, shifts, tree, k, False, degree)
    # The d's own noise: what the leave-one-out error leaves after the smooth's variance.
    _, loo_kernel_sq = _local_linear(points, shifts, tree, k, True, degree, at)
    if noise_var is not None:
        own = float(np.mean(np.asarray(noise_var, float)))
        ratio = np.sqrt(err / own) if own > 0 else np.inf
        if ratio > MAX_NOISE_RATIO:
            return PooledShift(shifts.copy(), np.full(m, np.nan), k, float(np.sqrt(err)),
                               'not_smooth',
                               f'the light\'s shift is not smooth over the marker\'s places '
                               f'(left-out views predicted to {np.sqrt(err):.3f} px, {ratio:.1f} '
                               f'x their own noise): the fitted centres are kept - a light '
                               f'that turns with the tool?')
    noise_var = err / (1.0 + float(np.mean(loo_kernel_sq)))
    how = {None: f'local planes through {k} neighbouring views', 1: 'one plane',
           0: 'one constant'}[degree]
    return PooledShift(fit, kernel_sq * noise_var, k if degree is None else m,
                       float(np.sqrt(err)), 'ok', f'{how} over {m} views', points.copy(),
                       shifts.copy(), degree, noise_var)


#: A camera changes to the other kind of centre when that kind's image noise is below the
#: one in use by this many relative standard errors of the difference (:func:`compare_solves`).
#: None: each comparison costs the same solve whatever it decides and is made only at each
#: doubling of the views, so a margin buys nothing, and at a tie either kind is as good, while
#: a margin keeps a better kind away: at two standard errors, over 40 views a camera,
#: fits 20 % less noisy by the truth (0.034 against 0.044 px, under even light) were not taken
#: and the calibration came out 1.4 x worse (docs/BENCHMARKS.md, *realism-effects*).
SWITCH_Z = 0.0


@dataclass
class CentreComparison:
    """
    A camera's two kinds of centre judged each by its own calibration (:func:`compare_solves`).

    ``sigma_used`` and ``sigma_other`` the image noise per axis of the centres in use and of
    the other kind (px), ``limit`` what the other must be below to be taken (px), ``switch``
    whether it is.
    """

    sigma_used: float
    sigma_other: float
    limit: float
    switch: bool


def compare_solves(used_residuals, used_redundancy, other_residuals, other_redundancy,
                   z=SWITCH_Z) -> CentreComparison:
    """
    Compare the image noise of a camera's two kinds of centre, each from its own solve.

    ``used_residuals`` (n, 2) the centres in use less the projections of a solve made with
    them (the camera's inlier views), ``used_redundancy`` that camera's degrees of freedom
    left there (2n less the sum of its observations' leverages); ``other_residuals`` (m, 2)
    and ``other_redundancy`` the same of a solve made with the other kind.  Each kind's noise
    is the unbiased estimate of its own solve,

        sigma^2 = sum |r|^2 / redundancy,

    and the other kind is taken when it is below ``sigma_used`` (1 - z sqrt(1 / 2r_u +
    1 / 2r_o)): ``z`` standard errors of the difference of two noise estimates over r_u and
    r_o degrees of freedom (an estimate over f of them has a relative standard error of
    1 / sqrt(2 f)); with the default (:data:`SWITCH_Z`), whichever is the lower.

    Why each kind by its own solve, not both against one: a solve takes in what it can of
    its centres' errors (a shift the camera's centre or distortion can follow), so the
    centres it was made with fit it better than any other centres of the same views, however
    good those are.  Judged against the solve of the kind in use, the choice stayed with a
    kind twice as noisy as the other (docs/BENCHMARKS.md, *realism-effects*).  Errors smooth
    enough for the camera's parameters to absorb are still seen by neither estimate.
    """
    used = _residuals(used_residuals, 'used_residuals')
    other = _residuals(other_residuals, 'other_residuals')
    nan = float('nan')
    if not (_usable(used, used_redundancy) and _usable(other, other_redundancy)):
        return CentreComparison(nan, nan, nan, False)
    s_u = float(np.sqrt(np.sum(used ** 2) / used_redundancy))
    s_o = float(np.sqrt(np.sum(other ** 2) / other_redundancy))
    limit = s_u * max(0.0, 1.0 - z * np.sqrt(0.5 / used_redundancy + 0.5 / other_redundancy))
    return CentreComparison(s_u, s_o, limit, bool(s_o < limit))


def _residuals(value, name):
    r = np.asarray(value, float)
    if r.ndim != 2 or r.shape[1] != 2:
        raise ValueError(f'{name} must have shape (n, 2), got {r.shape}')
    return r


def _usable(residuals, redundancy):
    """Whether a noise can be estimated: finite residuals and 0 < redundancy <= 2n."""
    return bool(np.isfinite(redundancy) and 0 < redundancy <= 2 * len(residuals) and
                np.all(np.isfinite(residuals)))
