"""Priors: precision forms and the whitened residual (the kernels: test_core_kernels.py)."""
import numpy as np
import pytest

from armcal_ros.core.kernels import kernel_matrix
from armcal_ros.core.priors import PointPrior, PriorSettings


@pytest.mark.parametrize('kernel', ['squared_exponential', 'exponential', 'matern32'])
def test_dense_prior_cost_equals_mahalanobis(kernel):
    rng = np.random.default_rng(0)
    Xm = rng.uniform(-0.3, 0.3, (40, 3))
    s = PriorSettings('correlated', point_sigma=2e-4, bias_sigma=1e-3, coherence_length=0.3,
                      kernel=kernel)
    prior = PointPrior(Xm, s)
    X = Xm + rng.normal(0, 1e-3, Xm.shape)
    K = 1e-6 * kernel_matrix(Xm, Xm, 0.3, kernel) + 4e-8 * np.eye(40)
    D = X - Xm
    ref = sum(D[:, a] @ np.linalg.solve(K, D[:, a]) for a in range(3))
    assert prior.kind == 'dense'
    assert prior.cost(X) == pytest.approx(ref, rel=1e-8)
    assert np.allclose(prior.gradient_half(X), np.linalg.solve(K, D), rtol=1e-8)


def test_independent_and_vanishing_bias_are_block():
    Xm = np.zeros((5, 3))
    for s in (PriorSettings('independent', point_sigma=1e-3),
              PriorSettings('correlated', point_sigma=1e-3, bias_sigma=0.0)):
        prior = PointPrior(Xm, s)
        assert prior.kind == 'block'
        assert prior.cost(np.full((5, 3), 1e-3)) == pytest.approx(15.0)


def test_settings_are_validated_by_name():
    with pytest.raises(ValueError, match='noise_model'):
        PriorSettings('magic').validate()
    with pytest.raises(ValueError, match='point_sigma'):
        PriorSettings('independent', point_sigma=0.0).validate()
    with pytest.raises(ValueError, match='coherence_length'):
        PriorSettings('correlated', coherence_length=-1).validate()
