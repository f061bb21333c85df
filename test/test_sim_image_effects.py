"""The simulator's camera and operator effects: rolling shutter, lenses, exposure, pauses."""

from dataclasses import replace

import numpy as np
import pytest

from armcal_ros.sim.cell import OCCLUSION_NONE, SimSettings, simulate_cell
from armcal_ros.sim.render import SensorModel

DURATION = 20.0


@pytest.fixture(scope='module')
def plain():
    return simulate_cell('geometric', 7, DURATION, SimSettings(duration=DURATION))


def _with(**kw):
    return simulate_cell('geometric', 7, DURATION, SimSettings(duration=DURATION, **kw))


def test_a_rolling_shutter_sees_each_row_when_it_is_read(plain):
    readout = 0.03
    rs = _with(rolling_shutter=readout)
    f, g = plain.frames, rs.frames
    assert np.array_equal(f.exposure_ns, g.exposure_ns)       # no other draw changes
    # Each frame's marker is where the arm was when the marker's own row was read.
    height = np.array([c.height for c in rs.cameras])[g.camera]
    row = g.uv[:, 1] / (height - 1.0) - 0.5
    t = (g.exposure_ns - rs.start_ns) * 1e-9 + row * readout
    x = rs.robot.marker(rs.trajectory.positions(t))
    inside = (g.uv[:, 1] > 0) & (g.uv[:, 1] < height - 1)
    np.testing.assert_allclose(x[inside], g.marker[inside], atol=1e-6)
    # Moving frames shift by up to the speed x 15 ms; still ones not at all.
    shift = np.linalg.norm(g.uv - f.uv, axis=1)
    t0 = (f.exposure_ns - plain.start_ns) * 1e-9
    ends = [plain.robot.marker(plain.trajectory.positions(t0 + d)) for d in (-0.016, 0.016)]
    still = np.linalg.norm(ends[1] - ends[0], axis=1) < 1e-12    # over the whole readout
    assert np.any(still) and np.all(shift[still] < 1e-6)
    assert np.percentile(shift[~still], 90) > 0.2


def test_lenses_get_the_given_k3_and_tangential_terms_and_nothing_else_changes(plain):
    lens = _with(lens_k3=0.08, lens_tangential=0.003)
    k3 = np.array([c.dist[4] for c in lens.cameras])
    assert np.all((k3 >= 0.8 * 0.08) & (k3 <= 1.2 * 0.08))
    p = np.array([c.dist[2:4] for c in lens.cameras]).ravel()
    assert 0.0005 < np.std(p) < 0.009 and len(set(p)) == len(p)
    for a, b in zip(plain.cameras, lens.cameras):
        np.testing.assert_array_equal(a.dist[:2], b.dist[:2])
        assert a.fx == b.fx and np.array_equal(a.rotation, b.rotation)


def test_auto_exposure_steps_scale_each_camera_in_steps(plain):
    sensor = replace(plain.settings.sensor, exposure_steps=(4.0, 1.6))
    f = plain.frames
    t = (f.exposure_ns - plain.start_ns) * 1e-9
    factor = np.array([plain.exposure_factor(i, sensor) for i in range(len(f))])
    assert np.all((factor >= 1 / 1.6) & (factor <= 1.6))
    for j in range(len(plain.cameras)):
        for k in range(int(DURATION // 4)):
            m = (f.camera == j) & (t // 4.0 == k)
            assert np.ptp(factor[m]) == 0.0                    # constant within a step
    assert len(np.unique(np.round(factor, 9))) > 5
    assert plain.exposure_factor(0) == 1.0                     # off by default
    # The marker's image brightens with the step (the same noise draws: within a few %).
    i = next(i for i in np.flatnonzero(f.occlusion == OCCLUSION_NONE)
             if 0.7 < factor[i] < 1.0 or 1.0 < factor[i] < 1.3)
    base = plain.render(i).astype(float) - sensor.black_level
    stepped = plain.render(i, sensor=sensor).astype(float) - sensor.black_level
    assert stepped.sum() / base.sum() == pytest.approx(factor[i], rel=0.05)
    with pytest.raises(ValueError, match='exposure_steps'):
        SensorModel(exposure_steps=(0.0, 2.0))


def test_read_noise_is_the_stated_std_on_the_dark_background(plain):
    sensor = replace(plain.settings.sensor, read_noise=2.0, black_level=10.0, glint_rate=0.0)
    image = plain.render(5, sensor=sensor).astype(float)
    corner = image[:100, :100]
    assert corner.std() == pytest.approx(2.0, rel=0.1)
    assert corner.mean() == pytest.approx(10.0, abs=0.2)


def test_short_pauses_and_bad_settings():
    short = _with(dwell=(0.2, 0.5))
    spans = short.trajectory.dwells()
    length = spans[:, 1] - spans[:, 0]
    assert np.all((length >= 0.2 - 1e-9) & (length <= 0.5 + 1e-9)), length
    for kw, name in ((dict(rolling_shutter=-0.01), 'rolling_shutter'),
                     (dict(lens_k3=1.5), 'lens_k3'),
                     (dict(lens_tangential=0.1), 'lens_tangential'),
                     (dict(dwell=(0.5, 0.2)), 'dwell')):
        with pytest.raises(ValueError, match=name):
            SimSettings(**kw)
