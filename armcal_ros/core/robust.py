"""
Robust losses on pixel residual norms, with the scale in pixels.

For an observation with residual norm d (pixels) and loss scale c (pixels), the cost is
rho(d^2) / s_px^2, where::

    none    rho(s) = s
    huber   rho(s) = s                         if s <= c^2
                   = 2 c sqrt(s) - c^2          otherwise
    cauchy  rho(s) = c^2 log(1 + s / c^2)

The solver uses iteratively reweighted Gauss-Newton: each residual pair is scaled by sqrt(w) with
w = rho'(s) (Huber: min(1, c/d); Cauchy: 1 / (1 + s/c^2)).  The second-order term of the robust
loss (Triggs et al., 2000) is dropped; it matters only for residuals far into the tail, which are
gated out after convergence anyway.
"""

import numpy as np

LOSSES = ('none', 'huber', 'cauchy')


def check_loss(loss, scale):
    """Validate a loss name and scale; return them."""
    if loss not in LOSSES:
        raise ValueError(f'loss must be one of {LOSSES}, got {loss!r}')
    if loss != 'none' and not scale > 0:
        raise ValueError(f'loss_scale must be > 0 pixels, got {scale}')
    return loss, float(scale)


def rho(s, loss, scale):
    """Robust cost of squared pixel residual norms ``s`` (px^2)."""
    s = np.asarray(s, float)
    if loss == 'none':
        return s.copy()
    c2 = scale * scale
    if loss == 'huber':
        d = np.sqrt(s)
        return np.where(s <= c2, s, 2.0 * scale * d - c2)
    return c2 * np.log1p(s / c2)


def weights(s, loss, scale):
    """IRLS weights rho'(s) for squared pixel residual norms ``s``."""
    s = np.asarray(s, float)
    if loss == 'none':
        return np.ones_like(s)
    if loss == 'huber':
        d = np.sqrt(s)
        return np.where(d <= scale, 1.0, scale / np.maximum(d, 1e-300))
    return 1.0 / (1.0 + s / (scale * scale))
