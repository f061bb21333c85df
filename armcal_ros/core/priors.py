"""
Priors on the true 3-D points X given the robot's measured points X^ (the noise models).

Thompson, Daniel and Murray (2004) treat the arm's forward-kinematics positions as measurements
whose errors are smooth biases correlated over a coherence length L.  With N measured points
stacked point-major (x0, y0, z0, x1, ...)::

    fixed        X = X^ exactly (test-field calibration, the classic baseline)
    independent  X ~ N(X^, s_n^2 I)                       (Lavest et al.)
    correlated   X ~ N(X^, (s_b^2 K_L + s_n^2 I_N) (x) I_3),
                 K_L[i, k] = k(|X^_i - X^_k| / L)

with a stationary kernel k: squared exponential exp(-d^2 / 2L^2) (the default), exponential
exp(-d/L), or Matern-3/2 (1 + sqrt(3) d/L) exp(-sqrt(3) d/L).  Each coordinate axis carries an
independent copy of the same scalar process.  The small independent term s_n keeps the matrix
positive definite (0.02 mm was enough in double precision).

A prior enters the objective as the quadratic (X - X^)^T P (X - X^) with precision P = Cov^-1;
the solver needs only P, either as N 3x3 blocks (``block_precision``) or dense
(``scalar_precision``, the N x N factor of the Kronecker product).
"""

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_factor, cho_solve

KERNELS = ('squared_exponential', 'exponential', 'matern32')
NOISE_MODELS = ('fixed', 'independent', 'correlated')


def kernel_function(d, coherence_length, kernel='squared_exponential'):
    """Evaluate the unit-variance stationary kernel at distances ``d`` (any shape)."""
    if coherence_length <= 0:
        raise ValueError(f'coherence_length must be > 0, got {coherence_length}')
    s = np.asarray(d, float) / coherence_length
    if kernel == 'squared_exponential':
        return np.exp(-0.5 * s * s)
    if kernel == 'exponential':
        return np.exp(-s)
    if kernel == 'matern32':
        a = np.sqrt(3.0) * s
        return (1.0 + a) * np.exp(-a)
    raise ValueError(f'kernel must be one of {KERNELS}, got {kernel!r}')


def kernel_matrix(A, B, coherence_length, kernel='squared_exponential'):
    """Kernel matrix k(|A_i - B_k|; L) for point sets A (N, 3) and B (M, 3)."""
    A = np.asarray(A, float)
    B = np.asarray(B, float)
    d2 = (np.sum(A * A, 1)[:, None] + np.sum(B * B, 1)[None, :] - 2.0 * A @ B.T)
    d = np.sqrt(np.maximum(d2, 0.0))
    return kernel_function(d, coherence_length, kernel)


@dataclass
class PriorSettings:
    """
    Hyperparameters of the point prior.

    point_sigma is s_n (metres), bias_sigma s_b (metres), coherence_length L (metres).
    """

    model: str = 'correlated'
    point_sigma: float = 0.0002
    bias_sigma: float = 0.001
    coherence_length: float = 0.3
    kernel: str = 'squared_exponential'

    def validate(self):
        """Raise ValueError naming the first bad field."""
        if self.model not in NOISE_MODELS:
            raise ValueError(f'noise_model must be one of {NOISE_MODELS}, got {self.model!r}')
        if self.kernel not in KERNELS:
            raise ValueError(f'kernel must be one of {KERNELS}, got {self.kernel!r}')
        if self.model != 'fixed' and not self.point_sigma > 0:
            raise ValueError(f'point_sigma must be > 0 for the {self.model} model, '
                             f'got {self.point_sigma}')
        if self.model == 'correlated':
            if not self.bias_sigma >= 0:
                raise ValueError(f'bias_sigma must be >= 0, got {self.bias_sigma}')
            if not self.coherence_length > 0:
                raise ValueError(f'coherence_length must be > 0, got {self.coherence_length}')
        return self


class PointPrior:
    """
    Gaussian prior on the points: cost (X - X^)^T P (X - X^).

    ``kind`` is 'fixed' (points are not unknowns), 'block' (P is N 3x3 blocks) or 'dense'.
    """

    def __init__(self, measured, settings: PriorSettings):
        settings.validate()
        self.settings = settings
        self.measured = np.asarray(measured, float)
        if self.measured.ndim != 2 or self.measured.shape[1] != 3:
            raise ValueError(f'measured points must have shape (N, 3), got {self.measured.shape}')
        n = self.measured.shape[0]
        self.n = n
        model = settings.model
        if model == 'fixed':
            self.kind = 'fixed'
        elif model == 'independent' or (model == 'correlated' and settings.bias_sigma == 0):
            self.kind = 'block'
            self._blocks = np.broadcast_to(np.eye(3) / settings.point_sigma ** 2, (n, 3, 3))
        else:
            self.kind = 'dense'
            K = settings.bias_sigma ** 2 * kernel_matrix(
                self.measured, self.measured, settings.coherence_length, settings.kernel)
            K[np.diag_indices(n)] += settings.point_sigma ** 2
            self._chol = cho_factor(K, lower=True)
            # K^-1 (N x N); the 3N x 3N precision is K^-1 (x) I_3.
            self._kinv = cho_solve(self._chol, np.eye(n))

    def block_precision(self):
        """Precision as (N, 3, 3) blocks (kind 'block' only)."""
        if self.kind != 'block':
            raise ValueError(f'block_precision needs a block prior, this one is {self.kind}')
        return self._blocks

    def scalar_precision(self):
        """Return the N x N matrix K^-1 whose Kronecker product with I_3 is the precision."""
        if self.kind != 'dense':
            raise ValueError(f'scalar_precision needs a dense prior, this one is {self.kind}')
        return self._kinv

    def residual(self, X):
        """Whitened residual vector r with |r|^2 = (X - X^)^T P (X - X^), shape (3N,)."""
        D = np.asarray(X, float) - self.measured
        if self.kind == 'fixed':
            return np.zeros(0)
        if self.kind == 'block':
            return (D / self.settings.point_sigma).reshape(-1)
        # Whitening with the Cholesky factor: r = L^-1 D per axis.
        from scipy.linalg import solve_triangular
        return solve_triangular(self._chol[0], D, lower=True).reshape(-1)

    def cost(self, X):
        """Return (X - X^)^T P (X - X^)."""
        r = self.residual(X)
        return float(r @ r)

    def gradient_half(self, X):
        """Return P (X - X^) as (N, 3), half the gradient of :meth:`cost`."""
        D = np.asarray(X, float) - self.measured
        if self.kind == 'fixed':
            return np.zeros_like(D)
        if self.kind == 'block':
            return D / self.settings.point_sigma ** 2
        return self._kinv @ D
