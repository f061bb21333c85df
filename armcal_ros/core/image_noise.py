"""
The image noise s_px (px per axis) that the Laplace evidence of ``auto`` is computed with.

The evidence weighs the image term against the prior through s_px, so it is only as good as
s_px.  :func:`estimate_pixel_sigma` takes it from a free-network adjustment, in which every
point may move far more than any arm's bias (a 10 mm prior), so the residuals hold image noise
only, divided by the redundancy::

    s_px^2 = sum |r_k|^2 / (2 M - (C - 7) - sum_i d_i)

over the M inlier observations, C camera parameters fitted (less the 7 of the similarity the
images cannot fix; intrinsics held at given values are not fitted) and d_i = 3 unknowns per
point seen at least twice (2 if seen once): the a-posteriori variance factor of
photogrammetry.  The parameters are counted, not weighed by leverage
(:attr:`~armcal_ros.core.adjustment.CameraEstimate.redundancy`): the estimate rests on the
points being free, which the loose prior only approximates, and a leverage taken at that prior
would credit a single camera's views with redundancy they do not have.  That model does not
depend on which noise model is true, so one estimate serves every candidate.

With one camera (or cameras that never see the same sample) the free network has no
redundancy: each point can move to fit its single view exactly.  Then the scatter of the pooled
detections serves (:func:`pooled_pixel_sigma`): each observation pools n_k frames of one dwell,
whose RMS distance from their mean is d_k, so the per-frame noise per axis is
s_f^2 = sum n_k d_k^2 / (2 sum (n_k - 1)) and the pooled observation's is s_f^2 / n_k.  It is a
lower bound - an error that stays put for a dwell (marker appearance, a detector's bias for one
view) does not scatter - so it is used only where the free network cannot be.
"""

from dataclasses import dataclass, replace

import numpy as np

from armcal_ros.core.adjustment import (AdjustmentResult, Observations, SolverSettings,
                                        adjust)
from armcal_ros.core.priors import PriorSettings

#: Point sigma (m) of the free-network adjustment that estimates the image noise: far looser
#: than any arm's bias, so the points follow the images, yet a regulariser for points seen once.
FREE_POINT_SIGMA = 0.01


@dataclass
class NoiseEstimate:
    """Image noise from a free-network adjustment (:func:`estimate_pixel_sigma`)."""

    pixel_sigma: float
    redundancy: float
    n_observations: int
    result: AdjustmentResult

    @property
    def success(self):
        """Whether the estimate is usable (finite, positive, with redundancy left)."""
        return bool(np.isfinite(self.pixel_sigma) and self.pixel_sigma > 0 and
                    self.redundancy > 0 and self.result.status != 'failed')


def pooled_pixel_sigma(spread_px, n_frames) -> float:
    """
    Image noise (px per axis) of pooled observations from the scatter of their frames.

    ``spread_px`` (M,) is each observation's RMS distance of its pooled detections from the
    pooled value, ``n_frames`` (M,) how many frames it pooled (module doc):

        s_f^2 = sum_k n_k d_k^2 / (2 sum_k (n_k - 1)),   s_px = sqrt(mean_k s_f^2 / n_k).

    NaN when no observation pooled two frames or more.
    """
    d = np.asarray(spread_px, float).reshape(-1)
    n = np.asarray(n_frames, float).reshape(-1)
    if d.shape != n.shape:
        raise ValueError(f'spread_px and n_frames must have one entry per observation, got '
                         f'{d.shape} and {n.shape}')
    ok = np.isfinite(d) & (n >= 2)
    dof = 2.0 * np.sum(n[ok] - 1.0)
    if dof <= 0:
        return float('nan')
    frame_var = float(np.sum(n[ok] * d[ok] ** 2) / dof)
    return float(np.sqrt(np.mean(frame_var / n[ok])))


def estimate_pixel_sigma(cameras, measured, obs: Observations, settings: SolverSettings = None,
                         inliers=None, point_sigma: float = FREE_POINT_SIGMA) -> NoiseEstimate:
    """
    Estimate the image noise s_px (px per axis) from a free-network adjustment (module doc).

    ``cameras`` are warm-start estimates, ``inliers`` the observations to use (default all).
    The points get an independent prior of ``point_sigma`` (m), much looser than the images,
    so the residuals are image noise; their sum of squares over the redundancy
    2 M - (C - 7) - sum_i d_i is the a-posteriori variance factor of photogrammetry (C counts
    the camera parameters fitted: intrinsics held at given values are not).
    """
    if not point_sigma > 0:
        raise ValueError(f'point_sigma must be > 0, got {point_sigma}')
    settings = settings or SolverSettings()
    measured = np.asarray(measured, float)
    res = adjust(cameras, measured, obs, PriorSettings('independent', point_sigma=point_sigma),
                 replace(settings, max_gate_rounds=0), inliers=inliers, redundancy=False)
    active = res.inliers
    m = int(np.count_nonzero(active))
    if res.status == 'failed' or m == 0:
        return NoiseEstimate(float('nan'), 0.0, m, res)
    rss = sum(e.rms_px ** 2 * e.n_inliers for e in res.cameras.values() if e.n_inliers)
    seen = np.bincount(obs.point[active], minlength=measured.shape[0])
    point_dof = 3.0 * np.count_nonzero(seen >= 2) + 2.0 * np.count_nonzero(seen == 1)
    # Intrinsics held at given values are not parameters of the fit.
    per_camera = len(res.parameter_names) // max(len(res.cameras), 1)
    held = sum(per_camera - 6 for c in cameras
               if c.name in settings.intrinsics and settings.intrinsics[c.name].mode == 'fixed')
    n_cam = len(res.parameter_names) - held
    redundancy = 2.0 * m - max(n_cam - 7, 0) - point_dof
    sigma = float(np.sqrt(rss / redundancy)) if redundancy > 0 else float('nan')
    return NoiseEstimate(sigma, float(redundancy), m, res)
