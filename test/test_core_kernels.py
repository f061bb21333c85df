"""The stationary kernels of the correlated prior at known distances, and their checks."""
import numpy as np
import pytest

from armcal_ros.core.kernels import kernel_function


def test_kernels_at_known_distances():
    L = 0.3
    assert kernel_function(0.0, L) == pytest.approx(1.0)
    assert kernel_function(L, L) == pytest.approx(np.exp(-0.5))
    assert kernel_function(L, L, 'exponential') == pytest.approx(np.exp(-1.0))
    a = np.sqrt(3.0)
    assert kernel_function(L, L, 'matern32') == pytest.approx((1 + a) * np.exp(-a))
    with pytest.raises(ValueError, match='kernel'):
        kernel_function(1.0, L, 'gaussianish')
    with pytest.raises(ValueError, match='coherence_length'):
        kernel_function(1.0, 0.0)
