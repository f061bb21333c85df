"""Priors: precision forms and the whitened residual (the kernels: test_core_kernels.py)."""
import numpy as np
import pytest

from armcal_ros.core.kernels import kernel_matrix
from armcal_ros.core.kinematic_prior import KinematicData
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


def test_relative_sigma_takes_out_only_rigid_motion():
    """sigma^2 = tr(P C P) / 3m: independent noise loses the 6 rigid dof of 3m, exactly."""
    rng = np.random.default_rng(1)
    Xm = rng.uniform(-0.3, 0.3, (30, 3))
    ind = PointPrior(Xm, PriorSettings('independent', point_sigma=1e-3))
    assert ind.relative_sigma() == pytest.approx(1e-3 * np.sqrt(1 - 6 / 90), rel=1e-9)
    assert PointPrior(Xm, PriorSettings('fixed')).relative_sigma() == 0.0
    # A bias coherent over far more than the points span is nearly a rigid shift: little
    # of its 1 mm is left; over a short coherence length nearly all of it.
    long = PointPrior(Xm, PriorSettings('correlated', point_sigma=1e-4, bias_sigma=1e-3,
                                        coherence_length=100.0))
    short = PointPrior(Xm, PriorSettings('correlated', point_sigma=1e-4, bias_sigma=1e-3,
                                         coherence_length=0.01))
    assert long.relative_sigma() < 1.2e-4
    assert short.relative_sigma() == pytest.approx(np.hypot(1e-3, 1e-4), rel=0.05)


def test_relative_sigma_of_a_kinematic_prior():
    """A base-frame offset is rigid and does not count; a link-length error does."""
    rng = np.random.default_rng(2)
    Xm = rng.uniform(-0.3, 0.3, (25, 3))
    shift = np.broadcast_to(np.eye(3), (25, 3, 3))
    stretch = np.zeros((25, 3, 1))
    stretch[:, 0, 0] = Xm[:, 0]                  # x scaled: not a rigid motion
    s = PriorSettings('kinematic', point_sigma=1e-4)
    rigid = PointPrior(Xm, s, KinematicData(shift, ['tx', 'ty', 'tz'], np.full(3, 1e-2)))
    assert rigid.relative_sigma() == pytest.approx(1e-4 * np.sqrt(1 - 6 / 75), rel=1e-6)
    scaled = PointPrior(Xm, s, KinematicData(stretch, ['sx'], np.array([1e-2])))
    assert scaled.relative_sigma() > 5 * rigid.relative_sigma()
    # The limit of the points considered: evenly spread, the same answer for a spread set.
    assert scaled.relative_sigma(limit=12) == pytest.approx(scaled.relative_sigma(), rel=0.5)
