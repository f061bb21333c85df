"""Cameras knocked or refocused part-way through a simulated session."""

import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
import yaml

from armcal_ros.cli import main
from armcal_ros.io.calib_files import read_cameras
from armcal_ros.sim.cell import (
    CameraChange, OCCLUSION_NONE, simulate_cell, SimSettings,
)
from armcal_ros.sim.output import read_ground_truth, write_ground_truth

KNOCK = CameraChange('cam2', 20.0, rotation_deg=1.5, translation_mm=4.0)
REFOCUS = CameraChange('cam3', 25.0, focal_percent=2.5)


@pytest.fixture(scope='module')
def changed():
    return simulate_cell('geometric', seed=7, settings=SimSettings(
        duration=40.0, camera_changes=(KNOCK, REFOCUS)))


def _centroid(img, black):
    img = img.astype(float) - black
    v, u = np.nonzero(img > 0)
    w = img[v, u]
    return np.array([(u * w).sum(), (v * w).sum()]) / w.sum()


def test_no_changes_is_the_run_without_the_field():
    a = simulate_cell('geometric', seed=7, settings=SimSettings(duration=40.0))
    b = simulate_cell('geometric', seed=7,
                      settings=SimSettings(duration=40.0, camera_changes=()))
    for name in ('camera', 'stamp_ns', 'exposure_ns', 'log_ns', 'marker', 'uv', 'occlusion',
                 'exposure_markers'):
        np.testing.assert_array_equal(getattr(a.frames, name), getattr(b.frames, name))
    for name in ('start_ns', 'end_ns', 'q', 'true_marker', 'nominal_marker'):
        np.testing.assert_array_equal(getattr(a.dwells, name), getattr(b.dwells, name))
    np.testing.assert_array_equal(a.joint_positions, b.joint_positions)
    for ca, cb in zip(a.cameras, b.cameras):
        np.testing.assert_array_equal(ca.rotation, cb.rotation)
        np.testing.assert_array_equal(ca.translation, cb.translation)
        np.testing.assert_array_equal(ca.intrinsics(), cb.intrinsics())
    assert b.change_log == [] and all(len(e) == 1 for e in b.camera_epochs.values())
    assert b.final_cameras == b.cameras
    assert 'camera_changes' not in b.settings.to_dict()
    np.testing.assert_array_equal(a.render(10), b.render(10))


def test_changes_leave_the_other_draws_alone(changed):
    plain = simulate_cell('geometric', seed=7, settings=SimSettings(duration=40.0))
    for name in ('camera', 'exposure_ns', 'log_ns', 'marker'):
        np.testing.assert_array_equal(getattr(plain.frames, name), getattr(changed.frames, name))
    np.testing.assert_array_equal(plain.dwells.q, changed.dwells.q)
    before = plain.frames.exposure_ns < changed.start_ns + 20 * 10 ** 9
    np.testing.assert_array_equal(plain.frames.uv[before], changed.frames.uv[before])


def test_knocked_camera_projects_after_the_knock(changed):
    f, j = changed.frames, 1
    t_ns = changed.start_ns + 20 * 10 ** 9
    original, knocked = changed.cameras[j], changed.camera_at(j, t_ns)
    assert changed.camera_at(j, t_ns - 1) is original
    assert knocked is not original and changed.final_cameras[j] is knocked
    turn = Rotation.from_matrix(knocked.rotation @ original.rotation.T).magnitude()
    assert abs(np.degrees(turn) - 1.5) < 1e-9
    assert abs(1e3 * np.linalg.norm(knocked.center - original.center) - 4.0) < 1e-9
    np.testing.assert_array_equal(knocked.intrinsics(), original.intrinsics())
    np.testing.assert_array_equal(knocked.dist, original.dist)
    m = f.camera == j
    after = m & (f.exposure_ns >= t_ns)
    assert after.sum() > 100 and (m & ~after).sum() > 100
    np.testing.assert_allclose(f.uv[after], knocked.project(f.marker[after]), atol=1e-9)
    np.testing.assert_allclose(f.uv[m & ~after], original.project(f.marker[m & ~after]),
                               atol=1e-9)
    # 1.5 deg at f = 800 px moves the image by about 20 px
    shift = np.linalg.norm(f.uv[after] - original.project(f.marker[after]), axis=1)
    assert np.median(shift) > 5.0
    # camera 1 is untouched
    assert len(changed.camera_epochs[0]) == 1
    m0 = f.camera == 0
    np.testing.assert_allclose(f.uv[m0], changed.cameras[0].project(f.marker[m0]), atol=1e-9)


def test_refocus_scales_the_focal_length(changed):
    j, t_ns = 2, changed.start_ns + 25 * 10 ** 9
    before, after = changed.cameras[j], changed.camera_at(j, t_ns)
    assert after.fx == pytest.approx(1.025 * before.fx, rel=1e-12)
    assert after.fy == pytest.approx(1.025 * before.fy, rel=1e-12)
    assert (after.cx, after.cy) == (before.cx, before.cy)
    np.testing.assert_array_equal(after.rotation, before.rotation)
    np.testing.assert_array_equal(after.translation, before.translation)
    f = changed.frames
    m = (f.camera == j) & (f.exposure_ns >= t_ns)
    np.testing.assert_allclose(f.uv[m], after.project(f.marker[m]), atol=1e-9)


def test_render_after_the_knock_shows_the_marker_where_the_knocked_camera_sees_it(changed):
    f, j = changed.frames, 1
    t_ns = changed.start_ns + 20 * 10 ** 9
    knocked = changed.camera_at(j, t_ns)
    black = changed.settings.sensor.black_level
    idx = np.flatnonzero((f.camera == j) & (f.exposure_ns >= t_ns)
                         & (f.occlusion == OCCLUSION_NONE))
    old = changed.cameras[j].project(f.marker[idx])
    checked = 0
    for k in range(0, len(idx), max(1, len(idx) // 4))[:4]:
        c = _centroid(changed.render(idx[k], clean=True), black)
        true_uv = knocked.project(f.marker[idx[k]][None])[0]
        assert np.linalg.norm(c - true_uv) < 0.5, (idx[k], c, true_uv)
        assert np.linalg.norm(c - old[k]) > 2.0
        checked += 1
    assert checked >= 3


def test_background_moves_with_the_knocked_camera():
    s = SimSettings(duration=20.0, camera_changes=(CameraChange('cam1', 10.0, 2.0, 1.0),),
                    sensor={'clutter_level': 60.0, 'clutter_spots': 4})
    r = simulate_cell('geometric', seed=2, settings=s)
    before, after = r._clutter(0, s.sensor, 0), r._clutter(0, s.sensor, 1)
    c0, c1 = r.camera_epochs[0][0][1], r.camera_epochs[0][1][1]
    H = c1.K @ c1.rotation @ c0.rotation.T @ np.linalg.inv(c0.K)
    hits = 0
    for u, v in [(150, 120), (320, 240), (480, 300), (250, 380)]:
        p = H @ [u, v, 1.0]
        p = np.rint(p[:2] / p[2]).astype(int)
        if 0 <= p[0] < c0.width and 0 <= p[1] < c0.height:
            hits += abs(after[p[1], p[0]] - before[v, u]) < 0.5 * s.sensor.clutter_level
    assert hits >= 3
    assert np.abs(after - before).mean() > 1.0


def test_ground_truth_round_trip(changed, tmp_path):
    write_ground_truth(changed, tmp_path)
    _, final = read_cameras(str(tmp_path))
    for cam, truth in zip(final, changed.final_cameras):
        np.testing.assert_allclose(cam.rotation, truth.rotation, atol=1e-9)
        np.testing.assert_allclose(cam.center, truth.center, atol=1e-9)
        assert cam.fx == pytest.approx(truth.fx)
    sets = changed.camera_set_epochs
    assert len(sets) == 3
    for k, (_, cams) in enumerate(sets):
        _, got = read_cameras(str(tmp_path / 'epochs' / f'epoch_{k}'))
        for cam, truth in zip(got, cams):
            np.testing.assert_allclose(cam.center, truth.center, atol=1e-9)
            assert cam.fx == pytest.approx(truth.fx)
    gt = read_ground_truth(tmp_path)
    changes = gt['changes']
    assert [c['camera'] for c in changes] == ['cam2', 'cam3']
    assert [c['epoch'] for c in changes] == [1, 2]
    assert changes[0]['time_ns'] == changed.start_ns + 20 * 10 ** 9
    assert changes[0]['rotation_deg'] == 1.5 and changes[1]['focal_percent'] == 2.5
    assert np.linalg.norm(changes[0]['rotation_axis']) == pytest.approx(1.0)
    assert gt['scenario']['settings']['camera_changes'][0] == {
        'camera': 'cam2', 'time_s': 20.0, 'rotation_deg': 1.5, 'translation_mm': 4.0,
        'focal_percent': 0.0}
    again = SimSettings(**gt['scenario']['settings'])
    assert again.camera_changes == (KNOCK, REFOCUS)


def test_ground_truth_without_changes_has_no_epochs(tmp_path):
    r = simulate_cell('geometric', seed=1, duration=5.0)
    write_ground_truth(r, tmp_path)
    assert not (tmp_path / 'epochs').exists() and not (tmp_path / 'changes.yaml').exists()
    assert read_ground_truth(tmp_path)['changes'] == []


def test_changes_are_cumulative():
    first = CameraChange('cam1', 5.0, rotation_deg=1.0)
    second = CameraChange('cam1', 8.0, rotation_deg=1.0, focal_percent=-1.0)
    r = simulate_cell('geometric', seed=3, settings=SimSettings(
        duration=12.0, camera_changes=(second, first)))
    (t0, c0), (t1, c1), (t2, c2) = r.camera_epochs[0]
    assert t0 == r.start_ns and t1 == r.start_ns + 5 * 10 ** 9 and t2 == r.start_ns + 8 * 10 ** 9
    step = Rotation.from_matrix(c2.rotation @ c1.rotation.T).magnitude()
    assert abs(np.degrees(step) - 1.0) < 1e-9
    assert c2.fx == pytest.approx(0.99 * c0.fx, rel=1e-12)
    assert [c['time_s'] for c in r.change_log] == [5.0, 8.0]


@pytest.mark.parametrize('kwargs,field', [
    (dict(time_s=0.0), 'time_s'), (dict(time_s=float('nan')), 'time_s'),
    (dict(time_s=1.0, rotation_deg=-1.0), 'rotation_deg'),
    (dict(time_s=1.0, translation_mm=float('inf')), 'translation_mm'),
    (dict(time_s=1.0, translation_mm=-2.0), 'translation_mm'),
    (dict(time_s=1.0, focal_percent='a'), 'focal_percent'),
])
def test_camera_change_validation(kwargs, field):
    with pytest.raises(ValueError, match=field):
        CameraChange('cam1', **kwargs)


def test_unknown_camera_or_late_change_is_refused():
    with pytest.raises(ValueError, match=r"'camX'.*cam1"):
        simulate_cell('geometric', seed=0, settings=SimSettings(
            duration=10.0, camera_changes=(CameraChange('camX', 5.0, 1.0),)))
    with pytest.raises(ValueError, match='end of the session'):
        simulate_cell('geometric', seed=0, settings=SimSettings(
            duration=10.0, camera_changes=(CameraChange('cam1', 10.0, 1.0),)))


@pytest.mark.parametrize('option,value,expected', [
    ('--knock', 'cam1:10:1', 'CAM:TIME:DEG:MM'),
    ('--knock', 'cam1:ten:1:3', 'CAM:TIME:DEG:MM'),
    ('--knock', 'cam1:10:-1:3', 'rotation_deg'),
    ('--knock', 'camX:10:1:3', "cameras are \\['cam1', 'cam2', 'cam3'\\]"),
    ('--knock', 'cam1:30:1:3', 'end of the session'),
    ('--refocus', 'cam1:10', 'CAM:TIME:PERCENT'),
    ('--refocus', 'cam1:10:-100', 'focal_percent'),
])
def test_cli_rejects_bad_changes(tmp_path, capsys, option, value, expected):
    out = tmp_path / 'bag'
    assert main(['simulate', '--output', str(out), '--duration', '20', option, value,
                 '--quiet']) == 2
    err = capsys.readouterr().err
    assert option in err
    assert re.search(expected, err), err
    assert not out.exists()


def test_cli_simulate_with_a_knock(tmp_path):
    out = tmp_path / 'bag'
    assert main(['simulate', '--duration', '20', '--knock', 'cam1:10:1:3',
                 '--refocus', 'cam2:12:2', '--output', str(out), '--quiet']) == 0
    gt = out / 'ground_truth'
    changes = yaml.safe_load((gt / 'changes.yaml').read_text())
    assert [(c['camera'], c['time_s'], c['epoch']) for c in changes] == [
        ('cam1', 10.0, 1), ('cam2', 12.0, 2)]
    assert changes[0]['rotation_deg'] == 1.0 and changes[0]['translation_mm'] == 3.0
    assert changes[1]['focal_percent'] == 2.0
    assert sorted(p.name for p in (gt / 'epochs').iterdir()) == ['epoch_0', 'epoch_1',
                                                                 'epoch_2']
    scen = yaml.safe_load((gt / 'scenario.yaml').read_text())
    assert len(scen['settings']['camera_changes']) == 2
