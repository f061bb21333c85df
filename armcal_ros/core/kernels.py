"""
Stationary kernels of the correlated prior and the bias field.

The paper's correlated prior (Thompson, Daniel and Murray 2004) correlates the biases of two
points X_i, X_k by a unit-variance stationary kernel of their distance d = |X_i - X_k| over a
coherence length L::

    squared_exponential   k(d) = exp(-d^2 / 2L^2)                  (the default)
    exponential           k(d) = exp(-d/L)
    matern32              k(d) = (1 + sqrt(3) d/L) exp(-sqrt(3) d/L)

Each coordinate axis carries an independent copy of the same scalar process, so the prior's
covariance is K_L (x) I_3 with K_L[i, k] = k(|X_i - X_k|) (:mod:`armcal_ros.core.priors`).
"""

import numpy as np

KERNELS = ('squared_exponential', 'exponential', 'matern32')


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
