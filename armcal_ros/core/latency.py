"""
A camera's stamp latency from the marker's motion: how late its image stamps are.

Why.  The front end pairs each still frame with the joint angles at its stamp.  A camera whose
stamps are late by d (exposure at t - d, stamped t) pairs a frame with angles the arm had d
later; at rest that costs nothing, but a dwell's first and last frames, and the whole dwell of
an arm that settles, are paired with the wrong place.  The motion between dwells measures d:
the marker's image at stamp t is where the calibrated camera sees the arm's point at t - d.

Model.  For the frames m of one camera in motion, with detections x_m at stamps t_m and the
calibration's prediction p(t) (forward kinematics of the joint angles interpolated at t,
projected),

    x_m = p(t_m - d) + b + e_m,                                                          (1)

b a constant image offset (what a marker's lighting or a small calibration error leaves;
profiled out as the mean residual) and e_m the detection noise.  d minimises the residual sum
of squares of (1); a grid over ``bounds`` (every ``grid_s``) finds its basin, and Gauss-Newton
refines it with the image velocity v_m = dp/dt: the step is sum v.r / sum |v|^2 (d r / d d
= v).  Residuals beyond ``outlier_px`` of the median residual are left out (a detection of
something else).  Standard deviation: the sandwich (heteroscedasticity-consistent) one of
that least-squares step,

    var d = sum_m (v_m . r_m)^2 / (sum_m |v_m|^2)^2,                                      (2)

v_m centred - the information is the motion, and frames at rest carry none - or, when larger,
a block jackknife over stretches of the recording (residuals that err alike from frame to
frame).  (2) and not s^2 / sum |v|^2 (s the residual RMS per coordinate): a stamp's jitter j_m
moves its residual by v_m j_m, along v_m only and more for faster frames, and the textbook
formula, which spreads the residual over both coordinates and every frame alike, claimed about
half the variance the jitter gives (measured on the simulator, 2 ms of jitter: 0.09-0.10 ms
against 0.16-0.18 ms by (2)).  For isotropic noise of one size the two agree.
"""

from dataclasses import dataclass

import numpy as np


#: Contiguous blocks of the block jackknife (at most; five frames a block at least).
JACKKNIFE_BLOCKS = 20


def _gauss_newton(t, uv, predict, d, h, iterations=3):
    """Return d refined on the frames (t, uv) by Gauss-Newton steps of (1), b profiled out."""
    for _ in range(iterations):
        pd = predict(t - d)
        v = (pd - predict(t - d - h)) / h
        r = uv - pd
        r = r - r.mean(axis=0)
        v = v - v.mean(axis=0)
        vv = float((v * v).sum())
        if vv <= 0:
            break
        step = -float((v * r).sum()) / vv
        d += step
        if abs(step) < 1e-7:
            break
    return d


def _block_jackknife(t, uv, predict, mask, d, h):
    """
    Return the block-jackknife standard deviation of d over contiguous blocks of frames.

    The formula s / sqrt(sum |v|^2) holds for independent residuals; a calibration's error
    along the path and the arm's own errors are smooth in time, so neighbouring frames err
    alike and the formula claims too much (measured: errors 2-4 x its value on the simulator).
    Leaving out one stretch of the recording at a time, sqrt((G - 1) / G sum (d_g - d_mean)^2),
    sees that correlation.
    """
    idx = np.flatnonzero(mask)
    idx = idx[np.argsort(t[idx], kind='stable')]
    blocks = min(JACKKNIFE_BLOCKS, len(idx) // 5)
    if blocks < 3:
        return 0.0
    parts = np.array_split(idx, blocks)
    ds = []
    for g in range(blocks):
        rest = np.concatenate([p for k, p in enumerate(parts) if k != g])
        ds.append(_gauss_newton(t[rest], uv[rest], predict, d, h))
    ds = np.asarray(ds)
    return float(np.sqrt((blocks - 1) / blocks * ((ds - ds.mean()) ** 2).sum()))


@dataclass(frozen=True)
class LatencyEstimate:
    """
    One camera's delay.

    ``latency_s`` (stamp minus exposure; NaN if not estimated), ``std_s``, ``frames`` used,
    ``rms_px`` of (1) at the estimate, ``status`` ('ok', 'too_little_motion', 'at_bound',
    'too_few_frames', 'no_fit') and ``message``.
    """

    latency_s: float
    std_s: float
    frames: int
    rms_px: float
    status: str
    message: str = ''

    @property
    def ok(self):
        """Return True when the latency was estimated (within its bounds, from enough motion)."""
        return self.status == 'ok'


def estimate_latency(stamps_s, uv, predict, bounds=(-0.1, 0.25), grid_s=0.002,
                     outlier_px=3.0, min_frames=10, max_std_s=0.005, iterations=5):
    """
    Return the :class:`LatencyEstimate` of (1) in the module doc.

    ``stamps_s`` (M,) frame stamps (s), ``uv`` (M, 2) detections; ``predict(times_s)`` returns
    (M, 2) predicted image points at ``times_s`` (M,) (NaN where unknown, e.g. outside the
    joint record).  ``bounds`` (s) is the range searched; the estimate is refused when its
    standard deviation exceeds ``max_std_s`` (too little motion) or it lies on a bound.
    """
    t = np.asarray(stamps_s, float).reshape(-1)
    uv = np.asarray(uv, float)
    if uv.shape != (t.size, 2):
        raise ValueError(f'uv must have shape ({t.size}, 2) to match stamps_s, got {uv.shape}')
    lo, hi = (float(b) for b in bounds)
    if not lo < hi:
        raise ValueError(f'bounds must be (low, high) with low < high, got {bounds}')
    if not grid_s > 0:
        raise ValueError(f'grid_s must be > 0, got {grid_s}')
    nan = float('nan')
    if t.size < min_frames:
        return LatencyEstimate(nan, nan, int(t.size), nan, 'too_few_frames',
                               f'{t.size} frames in motion (at least {min_frames} needed)')

    h = 1e-3                    # the step of the image velocity's finite difference (s)

    def residuals(d):
        """Return (residuals of the frames kept, their mask); (None, None) without a fit."""
        r = uv - predict(t - d)
        # A frame at an end of the joint record has a prediction but no velocity: left out.
        good = np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(predict(t - d - h)), axis=1)
        if good.sum() < min_frames:
            return None, None
        r = r[good] - np.median(r[good], axis=0)
        keep = np.hypot(r[:, 0], r[:, 1]) <= outlier_px
        if keep.sum() < min_frames:
            return None, None
        mask = np.zeros(t.size, bool)
        mask[np.flatnonzero(good)[keep]] = True
        return r[keep] - r[keep].mean(axis=0), mask

    def cost(d):
        r, _ = residuals(d)
        if r is None:
            return np.inf
        # Frames left out count at the outlier bound, so a delay cannot win by losing frames.
        return float((r * r).sum() + (t.size - len(r)) * outlier_px ** 2)

    grid = np.arange(lo, hi + 0.5 * grid_s, grid_s)
    costs = np.array([cost(d) for d in grid])
    if not np.any(np.isfinite(costs)):
        return LatencyEstimate(nan, nan, 0, nan, 'no_fit',
                               f'no delay from {1e3 * lo:.0f} to {1e3 * hi:.0f} ms brings '
                               f'{min_frames} frames within {outlier_px} px of the prediction')
    k = int(np.argmin(costs))
    d = float(grid[k])
    for _ in range(iterations):
        r, mask = residuals(d)
        if r is None:
            break
        pd = predict(t[mask] - d)
        v = (pd - predict(t[mask] - d - h)) / h            # dp/dt at t - d
        v = v - v.mean(axis=0)                              # b absorbs a constant part
        vv = float((v * v).sum())
        if vv <= 0:
            break
        # r(d) = x - p(t - d) - b: d r / d d = +v, so the Gauss-Newton step is -sum v.r / |v|^2.
        step = -float((v * r).sum()) / vv
        d = min(max(d + step, lo), hi)
        if abs(step) < 1e-6:
            break
    r, mask = residuals(d)
    if r is None:
        return LatencyEstimate(nan, nan, 0, nan, 'too_few_frames',
                               'too few frames with a prediction near the estimate')
    pd = predict(t[mask] - d)
    v = (pd - predict(t[mask] - d - h)) / h
    v = v - v.mean(axis=0)
    dof = max(2 * len(r) - 3, 1)
    rms = float(np.sqrt((r * r).sum() / dof))
    vv = max(float((v * v).sum()), 1e-300)
    # (2), with the small-sample factor n / (n - 1) of the one parameter d.
    std = float(np.sqrt(((v * r).sum(axis=1) ** 2).sum() * len(r) / max(len(r) - 1, 1)) / vv)
    n = int(mask.sum())
    std = max(std, _block_jackknife(t, uv, predict, mask, d, h))
    if std > max_std_s:
        return LatencyEstimate(d, std, n, rms, 'too_little_motion',
                               f'{1e3 * d:.1f} ms +- {1e3 * std:.1f} ms: too little motion in '
                               f'view to time the camera (+- {1e3 * max_std_s:.0f} ms needed)')
    if min(d - lo, hi - d) < grid_s:
        return LatencyEstimate(d, std, n, rms, 'at_bound',
                               f'{1e3 * d:.1f} ms is at the edge of the range searched '
                               f'({1e3 * lo:.0f} to {1e3 * hi:.0f} ms)')
    return LatencyEstimate(d, std, n, rms, 'ok',
                           f'{1e3 * d:.1f} ms +- {1e3 * std:.2f} ms from {n} frames in motion')
