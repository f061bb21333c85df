"""
Known intrinsics: a camera's K and distortion held fixed, or a Gaussian prior around them.

A factory-calibrated camera (RealSense, ZED, a driver's CameraInfo) comes with intrinsics that
14-20 views of one marker cannot improve on; estimating them anyway is ill-posed and lets them
trade with the pose.  Per camera, the adjustment then either holds them (``fixed``: only the
pose is estimated) or adds the prior term

    F_c = sum_k ((theta_k - mu_k) / sigma_k)^2

over theta = (fx, fy, cx, cy, the free distortion terms) to the objective (``prior``: the data
may move them by what they can support, the given standard deviations say how far).  ``fixed``
is the same term with standard deviations far below anything the images resolve
(:data:`FIXED_SIGMA_PX`, :data:`FIXED_SIGMA_DIST`), so the structure of the normal equations
and the reported covariance (standard deviations of about zero) stay those of the general case.
Distortion terms that are not free keep the given values.
"""

from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

from armcal_ros.core.camera import Camera

INTRINSICS_MODES = ('estimate', 'fixed', 'prior')
#: Standard deviation standing for "held fixed": 1e-6 px of focal length or principal point.
FIXED_SIGMA_PX = 1e-6
#: ... and for a distortion coefficient (dimensionless).
FIXED_SIGMA_DIST = 1e-9


@dataclass(frozen=True)
class IntrinsicsPrior:
    """
    Given intrinsics of one camera: K as (fx, fy, cx, cy), the five plumb_bob coefficients.

    ``sigma`` (4,) px and ``sigma_dist`` (5,) are the prior standard deviations; None holds
    the values fixed.  ``width`` and ``height`` (0: not known) are the image size the values
    belong to; images of another size are refused for them.
    """

    intrinsics: Sequence[float]
    dist: Sequence[float] = (0.0, 0.0, 0.0, 0.0, 0.0)
    sigma: Optional[Sequence[float]] = None
    sigma_dist: Optional[Sequence[float]] = None
    width: int = 0
    height: int = 0

    def __post_init__(self):
        intr = np.asarray(self.intrinsics, float)
        dist = np.asarray(self.dist, float)
        if intr.shape != (4,) or not np.all(np.isfinite(intr)) or intr[0] <= 0 or intr[1] <= 0:
            raise ValueError(f'intrinsics must be finite (fx, fy, cx, cy) with fx, fy > 0, '
                             f'got {self.intrinsics!r}')
        if dist.shape != (5,) or not np.all(np.isfinite(dist)):
            raise ValueError(f'dist must be 5 finite plumb_bob coefficients, got {self.dist!r}')
        for name, value, n in (('sigma', self.sigma, 4), ('sigma_dist', self.sigma_dist, 5)):
            if value is None:
                continue
            v = np.asarray(value, float)
            if v.shape != (n,) or not np.all(np.isfinite(v)) or np.any(v <= 0):
                raise ValueError(f'{name} must be {n} finite numbers > 0 (or None: fixed), '
                                 f'got {value!r}')

    @property
    def mode(self):
        """Return 'fixed' or 'prior'."""
        return 'fixed' if self.sigma is None and self.sigma_dist is None else 'prior'

    @classmethod
    def from_camera(cls, cam: Camera, sigma=None, sigma_dist=None):
        """Return the prior of a camera's current intrinsics (fixed without sigmas)."""
        return cls(tuple(float(v) for v in cam.intrinsics()), tuple(float(v) for v in cam.dist),
                   sigma, sigma_dist, int(cam.width), int(cam.height))

    def terms(self, dist_idx):
        """
        Return (mean, 1 / sigma^2) over (fx, fy, cx, cy, dist[dist_idx]).

        The order is that of a camera's block of the adjustment.
        """
        mean = np.concatenate([np.asarray(self.intrinsics, float),
                               np.asarray(self.dist, float)[dist_idx]])
        s = np.full(4, FIXED_SIGMA_PX) if self.sigma is None else np.asarray(self.sigma, float)
        sd = (np.full(5, FIXED_SIGMA_DIST) if self.sigma_dist is None
              else np.asarray(self.sigma_dist, float))
        return mean, 1.0 / np.concatenate([s, sd[dist_idx]]) ** 2

    def apply(self, cam: Camera) -> Camera:
        """Return a copy of ``cam`` with these intrinsics and distortion (pose kept)."""
        out = cam.copy()
        out.set_intrinsics(self.intrinsics)
        out.dist = np.asarray(self.dist, float).copy()
        return out

    @property
    def K(self):
        """Return the 3x3 camera matrix."""
        fx, fy, cx, cy = (float(v) for v in self.intrinsics)
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    def size_mismatch(self, width, height):
        """Return why images of ``width`` x ``height`` do not fit these values, or ''."""
        if self.width and self.height and (int(width), int(height)) != (self.width,
                                                                        self.height):
            return (f'its images are {int(width)}x{int(height)} but the given intrinsics are '
                    f'for {self.width}x{self.height}')
        return ''
