"""The image noise estimates: the free-network fit of the images, the scatter of pooled frames."""
import numpy as np
import pytest

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.image_noise import estimate_pixel_sigma, pooled_pixel_sigma
from armcal_ros.core.priors import PriorSettings
from armcal_ros.sim.synthetic import make_problem


def _fixed(prob, s):
    fx = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)
    return fx.adjustment.camera_list(), fx.adjustment.inliers


@pytest.mark.parametrize('true_sigma', [0.05, 0.3, 1.0])
def test_free_network_estimate_recovers_the_image_noise_under_a_bias(true_sigma):
    # 1 mm of correlated bias is ~0.5 px here: far above the smaller noise levels, so the
    # estimate must come from the images, not from the fit of the robot's points.
    prob = make_problem(300, 3, bias_sigma=1e-3, coherence_length=0.3, pixel_sigma=true_sigma)
    s = SolverSettings(pixel_sigma=0.5)
    cams, inl = _fixed(prob, s)
    est = estimate_pixel_sigma(cams, prob.measured, prob.obs, s, inliers=inl)
    assert est.success
    assert est.pixel_sigma == pytest.approx(true_sigma, rel=0.15)
    assert 0 < est.redundancy < 2 * est.n_observations


def test_pooled_scatter_recovers_the_noise_of_pooled_observations():
    rng = np.random.default_rng(3)
    sigma = 0.04
    n = rng.integers(2, 20, 400)
    spread = []
    for k in n:
        uv = rng.normal(0.0, sigma, (k, 2))
        spread.append(np.sqrt(np.mean(np.sum((uv - uv.mean(axis=0)) ** 2, axis=1))))
    expected = np.sqrt(np.mean(sigma ** 2 / n))
    assert pooled_pixel_sigma(spread, n) == pytest.approx(expected, rel=0.05)
    assert np.isnan(pooled_pixel_sigma([0.1, 0.2], [1, 1]))    # single frames: no scatter
    with pytest.raises(ValueError, match='spread_px and n_frames'):
        pooled_pixel_sigma([0.1, 0.2], [3])
