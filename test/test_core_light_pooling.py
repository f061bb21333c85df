"""Pooling a lit ball's light shift over a camera's views (core/light_pooling.py)."""
import numpy as np
import pytest

from armcal_ros.core.light_pooling import compare_solves, MIN_VIEWS, pool_light_shift
from armcal_ros.engine import lit_centres
from armcal_ros.frontend.samples import Observation, Sample
from armcal_ros.frontend.store import SampleStore


def _lamp_shift(points, lamp=(0.0, 0.0, 1.5), radius_px=6.0):
    """Return a shift like a lamp's: towards its image direction, 0.23 r at most, smooth."""
    to_lamp = np.asarray(lamp) - points
    to_lamp /= np.linalg.norm(to_lamp, axis=1, keepdims=True)
    return 0.23 * radius_px * to_lamp[:, :2] * np.array([1.0, -1.0])


def _views(m, seed):
    rng = np.random.default_rng(seed)
    return rng.uniform([-0.3, -0.3, 0.2], [0.3, 0.3, 0.7], (m, 3)), rng


def test_a_smooth_shift_is_recovered_below_the_noise_of_each_view():
    points, rng = _views(300, 1)
    truth = _lamp_shift(points)
    noise = 0.02
    d = truth + rng.normal(0, noise, truth.shape)
    pooled = pool_light_shift(points, d)
    assert pooled.status == 'ok' and pooled.shift.shape == (300, 2)
    err = pooled.shift - truth
    # The shift changes by about 0.5 px over the workspace; the smooth must follow it with
    # less than half the error of one view, with no bias left.
    assert np.sqrt(np.mean(err ** 2)) < 0.5 * noise, np.sqrt(np.mean(err ** 2))
    assert np.all(np.abs(err.mean(axis=0)) < 0.003)
    # Its stated variance is the error's size (within a factor of 2 either way).
    ratio = np.mean(err ** 2) / np.mean(pooled.variance)
    assert 0.25 < ratio < 4.0, ratio
    assert abs(pooled.loo_rms - noise) < 0.3 * noise


def test_the_smooth_predicts_the_shift_at_new_places_as_at_its_own_views():
    points, rng = _views(300, 1)
    pooled = pool_light_shift(points, _lamp_shift(points) + rng.normal(0, 0.02, (300, 2)))
    # At its own views the same smooth: what each view was solved with.
    assert np.allclose(pooled.at(points), pooled.shift, atol=1e-9)
    new, _ = _views(100, 7)
    err = pooled.at(new) - _lamp_shift(new)
    assert np.sqrt(np.mean(err ** 2)) < 0.01, np.sqrt(np.mean(err ** 2))
    flat = pool_light_shift(points, rng.normal(0, 0.02, (300, 2)))      # one plane or constant
    assert flat.degree is not None and np.allclose(flat.at(points), flat.shift, atol=1e-9)
    few = pool_light_shift(points[:5], np.zeros((5, 2)))
    with pytest.raises(ValueError, match='pooled'):
        few.at(new)


def test_no_shift_under_even_light_gives_the_smoothest_fit():
    points, rng = _views(200, 2)
    d = rng.normal(0, 0.02, (200, 2))
    pooled = pool_light_shift(points, d)
    assert pooled.k == 200, pooled.message              # one plane or one constant
    assert np.sqrt(np.mean(pooled.shift ** 2)) < 0.006


def test_a_lamp_close_to_the_ball_gets_a_smaller_neighbourhood():
    points, rng = _views(400, 3)
    noise = rng.normal(0, 0.02, (2, 400, 2))
    far = pool_light_shift(points, _lamp_shift(points, (0, 0, 3.0)) + noise[0])
    near = pool_light_shift(points, _lamp_shift(points, (0.05, 0, 0.75)) + noise[1])
    assert near.k < far.k, (near.message, far.message)


def test_few_views_keep_the_fitted_centres_and_bad_input_is_refused():
    points, rng = _views(MIN_VIEWS - 1, 4)
    d = rng.normal(0, 0.1, (MIN_VIEWS - 1, 2))
    pooled = pool_light_shift(points, d)
    assert pooled.status == 'too_few'
    np.testing.assert_array_equal(pooled.shift, d)
    with pytest.raises(ValueError, match='points'):
        pool_light_shift(points[:, :2], d)
    with pytest.raises(ValueError, match='shifts'):
        pool_light_shift(points, d[:-1])
    d[0, 0] = np.nan
    with pytest.raises(ValueError, match='finite'):
        pool_light_shift(points, d)


def test_the_engine_moves_centroids_to_the_pooled_centre():
    points, rng = _views(120, 5)
    truth_uv = rng.uniform(100, 500, (120, 2))
    shift = _lamp_shift(points)
    store = SampleStore(min_sample_spacing=0.0)
    for X, uv, s in zip(points, truth_uv, shift):
        centroid = uv - s + rng.normal(0, 0.005, 2)        # biased towards the lamp, low noise
        fitted = uv + rng.normal(0, 0.03, 2)               # unbiased, noisy
        store.add(Sample(point_nominal=X, observations={
            'cam1': Observation(uv=fitted, ids=[0], n_frames=3, spread_px=0.05,
                                centroid_uv=centroid, centroid_spread_px=0.01),
            'cam2': Observation(uv=uv + 1.0, ids=[0], n_frames=3, spread_px=0.05)}))
    a = store.arrays()
    lit = lit_centres(a)
    b, info = lit.arrays, lit.pooling
    assert set(info) == {'cam1'}                           # cam2 has no centroids
    c1 = a.camera_index == a.camera_names.index('cam1')
    c2 = ~c1
    np.testing.assert_array_equal(b.uv[c2], a.uv[c2])
    err_fitted = np.sqrt(np.mean((a.uv[c1] - truth_uv) ** 2))
    err_pooled = np.sqrt(np.mean((b.uv[c1] - truth_uv) ** 2))
    assert err_pooled < 0.5 * err_fitted, (err_pooled, err_fitted)
    # The spread now says the centroid's scatter plus the smooth's, not the fit's.
    assert np.all(b.spread_px[c1] >= 0.01) and np.all(b.spread_px[c1] < 0.05)


def test_a_shift_that_is_not_a_function_of_the_place_is_refused():
    """An LED's shift follows the tool's turn: at one place it may point either way."""
    points, rng = _views(200, 6)
    turn = rng.choice([-1.0, 1.0], 200)[:, None]
    d = 0.3 * turn * np.array([1.0, 0.5]) + rng.normal(0, 0.01, (200, 2))
    own = np.full(200, 0.01 ** 2)
    refused = pool_light_shift(points, d, own)
    assert refused.status == 'not_smooth' and 'turns with the tool' in refused.message
    np.testing.assert_array_equal(refused.shift, d)
    # A lamp's smooth shift with the same noise is pooled.
    lamp = _lamp_shift(points) + rng.normal(0, 0.01, (200, 2))
    assert pool_light_shift(points, lamp, own).status == 'ok'


def _linear_fit(rng, n, params, sigma):
    """Residuals of a least-squares fit of 2n scalar equations with ``params`` unknowns."""
    A = rng.normal(size=(2 * n, params))
    truth = rng.normal(size=params)
    y = A @ truth + rng.normal(0, sigma, 2 * n)
    fitted = A @ np.linalg.lstsq(A, y, rcond=None)[0]
    return y, fitted, A @ truth


@pytest.mark.parametrize('sigma_used, sigma_other', [(0.12, 0.05), (0.05, 0.12), (0.08, 0.08)])
def test_each_kinds_noise_is_estimated_from_its_own_solve(sigma_used, sigma_other):
    """
    A known solution: a linear fit of 2n equations with p unknowns leaves r = 2n - p.

    Each kind's noise is its own fit's residual sum of squares over r: averaged over draws,
    the truth within a few per cent.  The other kind is taken where it is the better; at a
    tie it is a coin's toss, and with a margin of two standard errors nearly never.
    """
    rng = np.random.default_rng(11)
    n, params = 60, 15
    used_s, other_s, switches, margin = [], [], [], []
    for _ in range(400):
        y, fitted, _ = _linear_fit(rng, n, params, sigma_used)
        y2, fitted2, _ = _linear_fit(rng, n, params, sigma_other)
        residuals = ((y - fitted).reshape(n, 2), 2 * n - params,
                     (y2 - fitted2).reshape(n, 2), 2 * n - params)
        judged = compare_solves(*residuals)
        used_s.append(judged.sigma_used ** 2)
        other_s.append(judged.sigma_other ** 2)
        switches.append(judged.switch)
        margin.append(compare_solves(*residuals, z=2.0).switch)
    assert np.sqrt(np.mean(used_s)) == pytest.approx(sigma_used, rel=0.03)
    assert np.sqrt(np.mean(other_s)) == pytest.approx(sigma_other, rel=0.03)
    rate, rate_margin = np.mean(switches), np.mean(margin)
    if sigma_other < 0.5 * sigma_used:
        assert rate == 1.0 and rate_margin == 1.0
    elif sigma_other > sigma_used:
        assert rate == 0.0 and rate_margin == 0.0
    else:
        assert 0.4 < rate < 0.6, rate
        assert rate_margin < 0.05, rate_margin


def test_a_kind_whose_error_the_solve_absorbs_does_not_hide_the_better_kind():
    """
    Centres in use with a bias the fit can follow (in its column space) and more noise.

    Against the projections of the solve made with them, the better kind looks the worse
    (the solve bent to the bias); each judged by its own solve, the better kind is taken.
    """
    rng = np.random.default_rng(5)
    n, params = 60, 15
    A = rng.normal(size=(2 * n, params))
    truth = A @ rng.normal(size=params)
    bias = A @ rng.normal(0, 0.1, params)          # what a camera's parameters can follow
    used = truth + bias + rng.normal(0, 0.09, 2 * n)
    better = truth + rng.normal(0, 0.04, 2 * n)

    def fit(y):
        return A @ np.linalg.lstsq(A, y, rcond=None)[0]

    p_used = fit(used)
    assert np.sqrt(np.mean((better - p_used) ** 2)) > np.sqrt(np.mean((used - p_used) ** 2))
    judged = compare_solves((used - p_used).reshape(n, 2), 2 * n - params,
                            (better - fit(better)).reshape(n, 2), 2 * n - params)
    assert judged.switch, judged
    assert judged.sigma_other == pytest.approx(0.04, rel=0.3)
    assert judged.sigma_used == pytest.approx(0.09, rel=0.3)


def test_centres_compared_with_no_redundancy_or_wrong_shapes():
    r = np.zeros((10, 2))
    assert not compare_solves(r, 0.0, r, 12.0).switch     # a fit that took in everything
    assert not compare_solves(r + 1.0, 12.0, r + np.nan, 12.0).switch
    with pytest.raises(ValueError, match='used_residuals'):
        compare_solves(np.zeros(10), 5.0, r, 5.0)
    with pytest.raises(ValueError, match='other_residuals'):
        compare_solves(r, 5.0, r[:, :1], 5.0)
