"""
A matte ball lit from one side (core/marker_light.py) against the renderer and the closed form.

The renderer (sim/render.py) shades the ball per sub-pixel ray; the model integrates the
shading over the disc seen along the viewing ray.  They must agree on the centroid's offset
from the centre's image within 0.02 px over many viewing directions (the detector's own
precision is ~0.01 px).
"""
from dataclasses import replace

import numpy as np
import pytest

from armcal_ros.core.marker_light import centroid_offset, image_offsets
from armcal_ros.sim.cell import OCCLUSION_NONE, simulate_cell
from armcal_ros.sim.render import marker_signal


def test_the_closed_form_for_a_lamp_at_right_angles_to_the_view():
    a = 0.25
    expected = (1 - a) * (np.pi / 8) / (a * np.pi + (1 - a) * 2 / 3)
    c = centroid_offset([1.0, 0.0, 0.0], a)
    assert c[0] == pytest.approx(expected, abs=2e-4) and abs(c[1]) < 1e-9
    # Fully ambient or lit from the camera's side: no offset.
    np.testing.assert_allclose(centroid_offset([0.6, 0.0, 0.8], 1.0), 0.0, atol=1e-12)
    np.testing.assert_allclose(centroid_offset([0.0, 0.0, -1.0], 0.25), 0.0, atol=1e-12)
    with pytest.raises(ValueError, match='ambient'):
        centroid_offset([1.0, 0.0, 0.0], 1.5)


def test_the_offsets_agree_with_the_renderer_over_many_views():
    sim = simulate_cell('geometric', seed=2, duration=30.0)
    st = sim.settings
    lamp = 0.5 * (np.asarray(st.workspace_min) + np.asarray(st.workspace_max)) + [0.3, -0.2, 1.5]
    sensor = replace(st.sensor, lamp=tuple(lamp), ambient=0.25)
    f = sim.frames
    frames = np.flatnonzero(f.occlusion == OCCLUSION_NONE)[::37][:40]
    rendered, idx = [], []
    for i in frames:
        cam = sim.cameras[int(f.camera[i])]
        X = f.marker[i]
        u0, v0, p = marker_signal(cam, X[None], st.marker_radius, sensor, 0.0)
        vv, uu = np.mgrid[v0:v0 + p.shape[0], u0:u0 + p.shape[1]]
        rendered.append(np.array([(uu * p).sum(), (vv * p).sum()]) / p.sum()
                        - cam.project(X[None])[0])
        idx.append(int(f.camera[i]))
    model = image_offsets(sim.cameras, idx, f.marker[frames], lamp, 0.25, st.marker_radius)
    rendered = np.array(rendered)
    assert np.median(np.linalg.norm(rendered, axis=1)) > 0.3        # a real bias
    assert np.max(np.linalg.norm(model - rendered, axis=1)) < 0.02
