"""The simulated cell: truth consistency, rendering geometry, timing and scenarios."""

import os

import numpy as np
import pytest

from armcal_ros.core.camera import undistort_normalized
from armcal_ros.sim.cell import (
    link_occluded, OCCLUSION_NONE, SCENARIOS, simulate_cell, SimSettings,
)
from armcal_ros.sim.cells import cell_parameters, CELLS, get_cell
from armcal_ros.sim.render import (
    marker_signal, SensorModel, sphere_coverage, sphere_image_offset,
)
from armcal_ros.sim.trajectory import min_jerk


@pytest.fixture(scope='module')
def cell():
    return simulate_cell('nongeometric', seed=5, duration=12.0)


def test_truth_is_true_forward_kinematics(cell):
    r, d = cell.robot, cell.dwells
    assert len(d) >= 4
    chain = cell.chain
    q_true = d.q + r.periodic_error(d.q) + r.compliance_error(d.q)
    np.testing.assert_allclose(d.true_marker, chain.fk(q_true, r.point, r.errors), atol=1e-12)
    np.testing.assert_allclose(d.nominal_marker, chain.fk(d.q, r.point), atol=1e-12)
    # the non-geometric joint errors are of the documented size (0.01-0.025 deg per term,
    # compliance ~0.02 deg on the most loaded joint)
    per = np.degrees(np.abs(r.periodic_error(d.q)))
    assert per.max() < 2 * 0.025 + 1e-9 and per.max() > 0.005
    comp = np.degrees(np.abs(r.compliance_error(d.q))).max()
    assert 0.002 < comp < 0.03
    bias = np.linalg.norm(d.nominal_marker - d.true_marker, axis=1)
    assert 0.3e-3 < np.sqrt(np.mean(bias ** 2)) < 6e-3


def test_joint_states_map_by_name_and_follow_the_trajectory(cell):
    names = cell.joint_names
    assert set(cell.chain.joint_names) < set(names) and 'gripper_finger_joint' in names
    idx = cell.chain.index_map(names)
    t = (cell.joint_stamps_ns - cell.start_ns) / 1e9
    np.testing.assert_allclose(np.diff(t), 1 / 200.0, atol=1e-9)
    np.testing.assert_allclose(cell.joint_positions[:, idx], cell.trajectory.positions(t))
    # dwell positions are held still in the joint stream
    d = cell.dwells
    k = len(d) // 2
    inside = (cell.joint_stamps_ns > d.start_ns[k]) & (cell.joint_stamps_ns < d.end_ns[k])
    assert inside.sum() > 40
    np.testing.assert_allclose(cell.joint_positions[inside][:, idx], d.q[k][None].repeat(
        inside.sum(), 0), atol=1e-12)


def test_camera_clocks_and_projection_truth(cell):
    f = cell.frames
    assert np.all(np.diff(f.log_ns) >= 0)
    for j, cam in enumerate(cell.cameras):
        m = f.camera == j
        period = np.diff(np.sort(f.exposure_ns[m])) / 1e9
        assert abs(np.median(period) - 1 / 15.0) < 1e-4
        jitter = (f.stamp_ns[m] - f.exposure_ns[m]) / 1e9
        assert 0.0005 < jitter.std() < 0.005
        np.testing.assert_allclose(f.uv[m], cam.project(f.marker[m]), atol=1e-9)
    assert len({int(f.exposure_ns[f.camera == j][0]) % 66_666_667 for j in range(3)}) == 3
    assert f.visible.mean() > 0.6


def test_clean_render_centroid_is_the_true_projection(cell):
    f = cell.frames
    checked = 0
    for i in np.flatnonzero(f.occlusion == OCCLUSION_NONE)[:40:4]:
        img = cell.render(i, clean=True).astype(float) - cell.settings.sensor.black_level
        v, u = np.nonzero(img > 0)
        w = img[v, u]
        c = np.array([(u * w).sum(), (v * w).sum()]) / w.sum()
        assert np.linalg.norm(c - f.uv[i]) < 0.1, (i, c, f.uv[i])
        checked += 1
    assert checked >= 5


def test_sphere_image_offset_is_tiny_and_coverage_is_geometric(cell):
    cam = cell.cameras[0]
    X = cell.dwells.true_marker
    off = sphere_image_offset(cam, X, 0.005)
    assert np.all(np.abs(off) < 0.01)
    # without vignetting and blur the rendered centroid sits on pi(C) to ~0.01 px
    sensor = SensorModel(vignetting=False, supersample=16)
    u0, v0, patch = marker_signal(cam, X[:1], 0.005, sensor, 0.0)
    vv, uu = np.mgrid[v0:v0 + patch.shape[0], u0:u0 + patch.shape[1]]
    c = np.array([(uu * patch).sum(), (vv * patch).sum()]) / patch.sum()
    assert np.linalg.norm(c - cam.project(X[:1])[0]) < 0.02
    # the covered area matches the disc of the sphere's angular radius
    depth = cam.to_camera(X[:1])[0, 2]
    area = sphere_coverage(cam, X[0], 0.005, u0, v0, patch.shape[1], patch.shape[0], 16).sum()
    expected = np.pi * (cam.fx * 0.005 / depth) ** 2
    assert abs(area / expected - 1) < 0.15


def _coverage_by_every_subpixel(cam, centres, radius, u0, v0, width, height, S):
    """Coverage with every sub-pixel undistorted and tested (no pixel left out)."""
    a = (np.arange(S) + 0.5) / S - 0.5
    us = u0 + (np.arange(width)[:, None] + a[None, :]).ravel()
    vs = v0 + (np.arange(height)[:, None] + a[None, :]).ravel()
    gu, gv = np.meshgrid(us, vs)
    xy = undistort_normalized(cam, np.column_stack([gu.ravel(), gv.ravel()]))
    d = np.column_stack([xy, np.ones(len(xy))])
    hits = np.zeros(len(d))
    for C in cam.to_camera(np.atleast_2d(centres)):
        cross = np.cross(d, C)
        hits += (np.sum(cross * cross, axis=1) <= radius ** 2 * np.sum(d * d, axis=1)) & \
            (d @ C > 0)
    return (hits / len(np.atleast_2d(centres))).reshape(height, S, width, S).mean(axis=(1, 3))


@pytest.mark.parametrize('case', ['centre', 'corner_of_a_wide_lens', 'cut_by_the_window',
                                  'moving', 'close'])
def test_a_spheres_coverage_leaves_out_no_pixel_it_reaches(case):
    """
    Only the pixels the sphere's cone may reach are supersampled: never one it does reach.

    Against every sub-pixel undistorted and tested: a ball on the axis, in the corner of a
    lens of strong barrel distortion (k1 -0.35), cut by the window's edge, moving over the
    exposure, and 1 cm from the lens (its cone reaches z = 0: every pixel tested).
    The two differ only where a sub-pixel's ray is interpolated rather than undistorted
    (~1e-5 px), so by a sub-pixel or two on the outline at most.
    """
    from armcal_ros.core.camera import Camera
    k1 = -0.35 if case == 'corner_of_a_wide_lens' else -0.1
    cam = Camera('c', 640, 480, 400.0, 400.0, 320.0, 240.0, [k1, 0.08, 0.001, -0.001, 0.0])
    S, radius = 6, 0.01
    ray = {'corner_of_a_wide_lens': [0.75, 0.55, 1.0], 'close': [0.6, 0.3, 1.0]}.get(
        case, [0.05, -0.02, 1.0])
    depth = 0.0095 if case == 'close' else 1.0
    centres = np.array(ray)[None] * depth
    if case == 'moving':
        centres = centres + np.outer(np.linspace(0, 1, 4), [0.02, 0.01, 0.0])
    uv = cam.project(centres[:1])[0]
    size = 30 if case != 'close' else 120
    u0, v0 = int(uv[0]) - size // 2, int(uv[1]) - size // 2
    if case == 'cut_by_the_window':
        u0 = int(uv[0]) - 2
    got = sphere_coverage(cam, centres, radius, u0, v0, size, size, S)
    want = _coverage_by_every_subpixel(cam, centres, radius, u0, v0, size, size, S)
    assert want.sum() > 3.0
    assert np.abs(got - want).max() <= 2.0 / S ** 2 + 1e-12, np.abs(got - want).max()
    assert abs(got.sum() - want.sum()) <= 2.0 / S ** 2 * np.sqrt(want.sum()) + 1e-12


def test_noisy_render_has_marker_noise_glints_and_dark_background(cell):
    f = cell.frames
    i = int(np.flatnonzero(f.visible)[3])
    img = cell.render(i)
    assert img.dtype == np.uint8 and img.shape == (480, 640)
    u, v = np.round(f.uv[i]).astype(int)
    assert img[v - 1:v + 2, u - 1:u + 2].max() > 80
    assert np.median(img) == 2
    np.testing.assert_array_equal(img, cell.render(i))      # deterministic per frame
    rgb = cell.render(i, 'rgb8')
    bgr = cell.render(i, 'bgr8')
    assert rgb.shape == (480, 640, 3) and bgr.shape == (480, 640, 3)
    assert rgb[v, u, 0] >= rgb[v, u, 2] and bgr[v, u, 2] >= bgr[v, u, 0]
    glinty = SimSettings(duration=5.0, sensor=SensorModel(glint_rate=3.0))
    r = simulate_cell('geometric', seed=2, settings=glinty)
    specks = 0
    for k in range(10):
        img = r.render(k).astype(int)
        u, v = np.round(r.frames.uv[k]).astype(int)
        img[max(v - 8, 0):v + 9, max(u - 8, 0):u + 9] = 0
        specks += int((img > 40).sum())
    assert specks > 0


def test_scenarios_share_draws_and_differ_as_documented():
    out = {s: simulate_cell(s, seed=3, duration=6.0) for s in SCENARIOS}
    q = out['geometric'].dwells.q
    for s, r in out.items():
        np.testing.assert_array_equal(r.dwells.q, q)       # same trajectory for one seed
    gp = out['gp-prior']
    assert not np.any(gp.robot.errors) and gp.robot.bias_field is not None
    np.testing.assert_allclose(gp.dwells.true_marker - gp.dwells.nominal_marker,
                               gp.robot.bias_field(gp.dwells.nominal_marker), atol=1e-15)
    geo = out['geometric']
    assert geo.robot.bias_field is None and not np.any(geo.robot.compliance)
    np.testing.assert_array_equal(out['mixed'].robot.errors, geo.robot.errors)
    assert np.any(out['nongeometric'].robot.periodic_amplitude)
    with pytest.raises(ValueError, match='scenario'):
        simulate_cell('nope', seed=0, duration=5.0)


def test_min_jerk_and_link_occlusion(cell):
    s, ds = min_jerk(np.array([0.0, 0.5, 1.0]))
    np.testing.assert_allclose(s, [0, 0.5, 1])
    np.testing.assert_allclose(ds, [0, 1.875, 0])
    chain = cell.chain
    q = cell.dwells.q[:1]
    x = chain.fk(q, cell.robot.point)
    wrist = chain.link_frames(q)[0, -1, :3, 3]
    behind = wrist + 2.0 * (wrist - x[0]) / np.linalg.norm(wrist - x[0])
    assert link_occluded(chain, q, x, behind, 0.035, 0.02)[0]
    beside = x[0] + np.cross(wrist - x[0], [0, 0, 1.0]) * 30
    assert not link_occluded(chain, q, x, beside, 0.035, 0.02)[0]


def test_named_cells_simulate_and_describe_themselves_to_the_calibrator():
    for name, c in CELLS.items():
        s = c.sim_settings()
        r = simulate_cell(c.scenario, seed=0, duration=6.0, settings=s)
        assert [cam.name for cam in r.cameras] == list(s.camera_names), name
        assert sorted(r.joint_names) == sorted(list(r.chain.joint_names) + list(s.extra_joints))
        p = cell_parameters(s, c.compressed)
        suffix = '/compressed' if c.compressed else ''
        assert p['camera_names'] == list(s.camera_names)
        assert p['image_topics'] == [f'/{n}/image_raw{suffix}' for n in s.camera_names]
        assert os.path.exists(p['robot_description_file'])
    with pytest.raises(ValueError, match='cell must be one of'):
        get_cell('nope')


def test_dh_error_model_keeps_the_draws_on_dh_components_only():
    from armcal_ros.sim.true_robot import draw_geometric_errors
    chain = simulate_cell('geometric', seed=0, duration=3.0).chain
    full = draw_geometric_errors(chain, np.random.default_rng(5))
    dh = draw_geometric_errors(chain, np.random.default_rng(5), model='dh')
    for name, a, b in zip(chain.error_names, full, dh):
        joint, comp = name.rsplit('/', 1)
        if joint == chain.joint_names[0]:
            expected = a if comp == 'offset' else 0.0       # the base frame is DH frame 0
        elif joint in chain.joint_names:
            expected = a if comp in ('offset', 'tx', 'tz', 'rx') else 0.0    # theta, a, d, alpha
        else:
            expected = a                                   # the marker mount
        assert b == expected, name
    assert np.count_nonzero(dh) == 6 + 5 * 3 + 3
    with pytest.raises(ValueError, match='error_model must be one of'):
        SimSettings(error_model='hayati')


def test_a_lamp_shades_the_ball_and_moves_its_centroid_towards_the_light(cell):
    from dataclasses import replace
    f = cell.frames
    sensor = cell.settings.sensor
    i = int(np.flatnonzero(f.occlusion == OCCLUSION_NONE)[3])
    cam = cell.cameras[int(f.camera[i])]
    X = f.marker[i]
    radius = cell.settings.marker_radius

    def centroid(s):
        u0, v0, patch = marker_signal(cam, X[None], radius, s, 0.6)
        vv, uu = np.mgrid[v0:v0 + patch.shape[0], u0:u0 + patch.shape[1]]
        return np.array([(uu * patch).sum(), (vv * patch).sum()]) / patch.sum(), patch
    # No lamp: as before, the centroid is the centre's image (to the perspective offset).
    c0, p0 = centroid(sensor)
    assert np.linalg.norm(c0 - cam.project(X[None])[0]) < 0.01
    # A lamp straight along the camera's +x axis (image right) from the ball, far away: the
    # centroid moves right, not up or down, by a fraction of the image radius.
    lamp = X + 5.0 * cam.rotation[0]
    c1, p1 = centroid(replace(sensor, lamp=tuple(lamp), ambient=0.25))
    r_px = cam.fx * radius / cam.to_camera(X[None])[0, 2]
    shift = c1 - c0
    assert 0.1 * r_px < shift[0] < 0.6 * r_px and abs(shift[1]) < 0.05 * r_px
    # Nothing brighter than a fully lit point, the unlit side at the ambient fraction.
    assert p1.max() <= p0.max() + 1e-9 and p1.sum() < p0.sum()
    with pytest.raises(ValueError, match='ambient'):
        SensorModel(ambient=1.5)
    with pytest.raises(ValueError, match='lamp'):
        SensorModel(lamp=(0.0, 1.0))


def test_an_led_is_brightest_where_the_tool_points_and_turns_with_it(cell):
    from dataclasses import replace
    f = cell.frames
    i = int(np.flatnonzero(f.occlusion == OCCLUSION_NONE)[3])
    cam = cell.cameras[int(f.camera[i])]
    X = f.marker[i]
    radius = cell.settings.marker_radius
    sensor = replace(cell.settings.sensor, led_axis=(0.0, 0.0, 2.0))
    assert sensor.led_axis == (0.0, 0.0, 1.0)                 # normalised
    # The axis is the tool's z axis under the arm's true joint angles and geometry.
    a = cell.led_axis(i, sensor)
    t = (int(f.exposure_ns[i]) - cell.start_ns) * 1e-9
    q = cell.robot.true_joint_angles(cell.trajectory.positions(np.array([t])))
    np.testing.assert_allclose(a, cell.robot.chain.fk_pose(q, cell.robot.errors)[0, :3, 2])
    assert cell.led_axis(i) is None                           # no LED in the cell's sensor

    def centroid(axis, falloff=1.0):
        s = replace(sensor, led_falloff=falloff)
        u0, v0, patch = marker_signal(cam, X[None], radius, s, 0.6, led_axis=axis)
        vv, uu = np.mgrid[v0:v0 + patch.shape[0], u0:u0 + patch.shape[1]]
        return np.array([(uu * patch).sum(), (vv * patch).sum()]) / patch.sum()
    # Pointing along the camera's +x axis (image right), then -y (image up): the centroid
    # follows, by a fraction of the image radius.  A narrower beam lights less of the ball
    # beside the ambient glow, so it pulls less.
    c0 = cam.project(X[None])[0]
    r_px = cam.fx * radius / cam.to_camera(X[None])[0, 2]
    right, up = centroid(cam.rotation[0]) - c0, centroid(-cam.rotation[1]) - c0
    assert 0.1 * r_px < right[0] < 0.6 * r_px and abs(right[1]) < 0.05 * r_px
    assert 0.1 * r_px < -up[1] < 0.6 * r_px and abs(up[0]) < 0.05 * r_px
    assert 0.0 < centroid(cam.rotation[0], 4.0)[0] - c0[0] < right[0]
    with pytest.raises(ValueError, match='led_axis'):
        SensorModel(led_axis=(0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match='give one'):
        SensorModel(led_axis=(0.0, 0.0, 1.0), lamp=(1.0, 1.0, 1.0))
    with pytest.raises(ValueError, match='led_falloff'):
        SensorModel(led_falloff=0.0)


def test_an_opaque_ball_hides_the_scene_behind_it(cell):
    """Over a scene brighter than its unlit side, the ball's unlit side stays dark."""
    from dataclasses import replace
    from armcal_ros.sim.render import expose
    f = cell.frames
    i = int(np.flatnonzero(f.occlusion == OCCLUSION_NONE)[3])
    cam = cell.cameras[int(f.camera[i])]
    X = f.marker[i]
    lamp = X + 5.0 * cam.rotation[0]                       # lit from the image's right
    sensor = replace(cell.settings.sensor, lamp=tuple(lamp), ambient=0.25, read_noise=0.0,
                     gain=1e6)
    u0, v0, signal, alpha = marker_signal(cam, X[None], cell.settings.marker_radius, sensor,
                                          0.6, with_alpha=True)
    assert 0.99 < alpha.max() <= 1.0 + 1e-9 and alpha.min() >= 0.0
    scene = np.full((cam.height, cam.width), 0.6 * signal.max())
    rng = np.random.default_rng(0)
    hidden = expose(cam, [(u0, v0, signal)], rng, sensor, 'mono8', scene,
                    [(u0, v0, alpha)]).astype(float)
    brighter = expose(cam, [(u0, v0, signal)], rng, sensor, 'mono8', scene).astype(float)
    k = np.unravel_index(np.argmax(alpha - signal / signal.max()), alpha.shape)   # unlit, covered
    at = (v0 + k[0], u0 + k[1])
    expected = signal[k] + (1.0 - alpha[k]) * scene[at] + sensor.black_level
    assert hidden[at] == pytest.approx(expected, abs=1.0) and hidden[at] < scene[at] - 5.0
    assert brighter[at] == pytest.approx(scene[at] + sensor.black_level, abs=1.0)
    # Far from the ball the scene shows either way.
    assert hidden[0, 0] == brighter[0, 0]
