"""
Point-level synthetic calibration problems: true cameras, true points, robot-measured points.

No robot and no images: points are drawn in a workspace box, the "robot" reports them with a
bias drawn from the paper's correlated prior plus independent noise, and the cameras see their
true projections plus pixel noise.  This isolates the estimator (bench/solver.py, the core tests,
and the pre-bag demo); the full cell simulator lives beside it.
"""

from dataclasses import dataclass, field
from typing import Dict, List

import numpy as np

from armcal_ros.core.adjustment import Observations
from armcal_ros.core.calibration import CameraSpec
from armcal_ros.core.camera import Camera
from armcal_ros.sim.bias_field import draw_bias_at
from armcal_ros.sim.cameras import ring_of_cameras

WORKSPACE_CENTER = (0.5, 0.0, 0.4)
WORKSPACE_HALF_SIZE = 0.3


@dataclass
class SyntheticProblem:
    """A problem with its truth: ``measured`` = ``true_points`` + ``bias`` + noise."""

    cameras: List[Camera]
    true_points: np.ndarray
    measured: np.ndarray
    bias: np.ndarray
    obs: Observations
    test_points: np.ndarray
    settings: Dict[str, float] = field(default_factory=dict)

    @property
    def specs(self):
        """Return the camera names and sizes, as the calibrator needs them."""
        return [CameraSpec(c.name, c.width, c.height) for c in self.cameras]

    @property
    def truth(self):
        """Return the true cameras by name."""
        return {c.name: c for c in self.cameras}


def workspace_points(n, rng, center=WORKSPACE_CENTER, half=WORKSPACE_HALF_SIZE):
    """Uniform points in the workspace box."""
    return np.asarray(center) + rng.uniform(-half, half, (n, 3))


def make_problem(n_points, seed, n_cameras=3, bias_sigma=0.001, coherence_length=0.3,
                 point_sigma=0.0, pixel_sigma=0.3, outlier_fraction=0.0, n_test=500,
                 kernel='squared_exponential') -> SyntheticProblem:
    """
    Draw a problem: ``n_cameras`` around the workspace, ``n_points`` true points.

    The robot's measurements carry a bias from the correlated prior (``bias_sigma`` per axis,
    ``coherence_length``) plus independent noise ``point_sigma``; pixels carry ``pixel_sigma``
    noise, and ``outlier_fraction`` of the observations are replaced by gross errors (10-60 px).
    """
    rng = np.random.default_rng(seed)
    cams = ring_of_cameras(n_cameras, WORKSPACE_CENTER, rng)
    X = workspace_points(n_points, rng)
    bias = (draw_bias_at(X, bias_sigma, coherence_length, rng, kernel) if bias_sigma > 0
            else np.zeros_like(X))
    measured = X + bias + (rng.normal(0.0, point_sigma, X.shape) if point_sigma > 0 else 0.0)
    ci, pi, uvs = [], [], []
    for j, c in enumerate(cams):
        uv = c.project(X)
        ok = ((uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0) & (uv[:, 1] < c.height)
              & c.in_front(X))
        idx = np.flatnonzero(ok)
        ci.append(np.full(idx.size, j))
        pi.append(idx)
        uvs.append(uv[idx] + rng.normal(0.0, pixel_sigma, (idx.size, 2)))
    obs = Observations(np.concatenate(ci), np.concatenate(pi), np.vstack(uvs))
    if outlier_fraction > 0:
        m = len(obs)
        bad = rng.choice(m, int(round(outlier_fraction * m)), replace=False)
        ang = rng.uniform(0, 2 * np.pi, bad.size)
        mag = rng.uniform(10.0, 60.0, bad.size)
        obs.uv[bad] += np.column_stack([np.cos(ang), np.sin(ang)]) * mag[:, None]
        outliers = np.zeros(m, bool)
        outliers[bad] = True
    else:
        outliers = np.zeros(len(obs), bool)
    test = workspace_points(n_test, rng)
    settings = dict(n_points=n_points, seed=seed, bias_sigma=bias_sigma,
                    coherence_length=coherence_length, point_sigma=point_sigma,
                    pixel_sigma=pixel_sigma, outlier_fraction=outlier_fraction)
    prob = SyntheticProblem(cams, X, measured, bias, obs, test, settings)
    prob.outliers = outliers
    return prob
