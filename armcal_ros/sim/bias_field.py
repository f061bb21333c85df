"""
Smooth random bias fields drawn from the paper's correlated prior.

Two ways to draw b(X) ~ GP(0, s_b^2 k(|X - X'|; L) I_3):

* :func:`draw_bias_at` - the exact joint draw at a finite set of points (Cholesky of the kernel
  matrix); right for a fixed point set, O(N^3).
* :class:`FourierBiasField` - random Fourier features (Rahimi and Recht, 2007), a field that can be
  evaluated anywhere, so a simulated arm can carry the same bias along a continuous trajectory.
  For the squared-exponential kernel the frequencies are Gaussian with standard deviation 1/L per
  axis; for the exponential kernel, Cauchy; for Matern-3/2, Student-t with 3 degrees of freedom.
  With ``n_features`` features the covariance is exact in expectation and its Monte Carlo error
  falls as 1/sqrt(n_features).
"""

import numpy as np

from armcal_ros.core.kernels import kernel_matrix


def draw_bias_at(points, bias_sigma, coherence_length, rng, kernel='squared_exponential',
                 jitter=1e-10):
    """Draw one bias vector per point (N, 3) jointly from the correlated prior."""
    points = np.asarray(points, float)
    K = bias_sigma ** 2 * kernel_matrix(points, points, coherence_length, kernel)
    K[np.diag_indices_from(K)] += jitter * max(bias_sigma ** 2, 1e-30)
    L = np.linalg.cholesky(K)
    return L @ rng.standard_normal((points.shape[0], 3))


class FourierBiasField:
    """A smooth vector field b: R^3 -> R^3 whose statistics follow the correlated prior."""

    def __init__(self, bias_sigma, coherence_length, rng, kernel='squared_exponential',
                 n_features=2000):
        if coherence_length <= 0:
            raise ValueError(f'coherence_length must be > 0, got {coherence_length}')
        d = 3
        if kernel == 'squared_exponential':
            omega = rng.standard_normal((n_features, d)) / coherence_length
        elif kernel == 'exponential':
            # The 3-D exponential kernel's spectral density is a multivariate Cauchy (t, 1 dof).
            g = rng.standard_normal((n_features, d))
            chi = rng.chisquare(1, size=(n_features, 1))
            omega = g / np.sqrt(chi) / coherence_length
        elif kernel == 'matern32':
            g = rng.standard_normal((n_features, d))
            chi = rng.chisquare(3, size=(n_features, 1))
            omega = g / np.sqrt(chi / 3.0) * np.sqrt(3.0) / coherence_length
        else:
            raise ValueError(f'kernel must be squared_exponential, exponential or matern32, '
                             f'got {kernel!r}')
        self.omega = omega
        self.phase = rng.uniform(0.0, 2.0 * np.pi, n_features)
        self.weights = rng.standard_normal((n_features, 3))
        self.scale = bias_sigma * np.sqrt(2.0 / n_features)

    def __call__(self, points):
        """Evaluate the field at points (N, 3) -> (N, 3)."""
        points = np.atleast_2d(np.asarray(points, float))
        return self.scale * np.cos(points @ self.omega.T + self.phase) @ self.weights
