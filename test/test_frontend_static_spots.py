"""A view that stays put while the arm moves is dropped (frontend/static_spots.py)."""
import numpy as np

from armcal_ros.frontend.samples import Observation, Sample
from armcal_ros.frontend.static_spots import STATIC_MOVE_M, StaticSpotFilter


def _sample(X, views):
    return Sample(np.asarray(X, float), {n: Observation(np.asarray(uv, float)[None], [0],
                                                        n_frames=10)
                                         for n, uv in views.items()})


def test_a_fixed_spot_is_dropped_from_the_second_dwell_on_and_the_marker_kept():
    f = StaticSpotFilter()
    spot = [207.9, 244.8]
    samples = [_sample([0.5 + 0.05 * k, 0.1, 0.4],
                       {'cam3': np.add(spot, 0.02 * k), 'cam1': [300 + 40 * k, 200]})
               for k in range(6)]
    kept, dropped = f.filter(samples)
    assert len(kept) == 6 and dropped == ['cam3'] * 5
    assert 'cam3' in kept[0].observations
    assert all('cam3' not in s.observations and 'cam1' in s.observations for s in kept[1:])
    assert f.counts['observations_static'] == 5


def test_a_marker_that_dwells_twice_at_one_place_or_moves_a_little_is_kept():
    f = StaticSpotFilter()
    # The same place visited again (the arm back within a few millimetres), and a move too
    # small to tell a fixed spot from a marker.
    X = np.array([0.5, 0.1, 0.4])
    samples = [_sample(X, {'cam1': [320.0, 240.0]}),
               _sample(X + 0.5 * STATIC_MOVE_M, {'cam1': [320.3, 240.1]}),
               _sample(X + [0.1, 0, 0], {'cam1': [420.0, 240.0]})]
    kept, dropped = f.filter(samples)
    assert len(kept) == 3 and dropped == []


def test_a_sample_left_without_views_is_dropped():
    f = StaticSpotFilter()
    kept, _ = f.filter([_sample([0.5, 0.1, 0.4], {'cam1': [10.0, 20.0]}),
                        _sample([0.6, 0.1, 0.4], {'cam1': [10.0, 20.0]})])
    assert len(kept) == 1 and f.counts['samples_static'] == 1


def test_a_spot_the_detector_returns_to_after_true_views_is_still_dropped():
    f = StaticSpotFilter()
    spot = [207.9, 244.8]
    views = [spot, [350.0, 160.0], [380.0, 170.0], spot]
    kept, dropped = f.filter([_sample([0.5 + 0.05 * k, 0.1, 0.4], {'cam3': uv})
                              for k, uv in enumerate(views)])
    assert dropped == ['cam3'] and len(kept) == 3
