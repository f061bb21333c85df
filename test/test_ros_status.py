"""The node's status: camera frusta, bias vectors and the diagnostics (no DDS traffic)."""
import numpy as np
import pytest

from armcal_ros.ros import conversions as conv
from armcal_ros.ros.status import bias_vectors, diagnostic_statuses, frustum_segments, NodeState
from helpers.cameras import camera, points

pytestmark = pytest.mark.timeout(60)


def test_frustum_far_corners_project_to_the_image_corners():
    cam = camera()
    cam.dist = np.zeros(5)
    segs = frustum_segments(cam, depth=0.3)
    assert segs.shape == (8, 2, 3)
    np.testing.assert_allclose(segs[:4, 0], np.tile(cam.center, (4, 1)))
    uv = cam.project(segs[:4, 1])
    np.testing.assert_allclose(uv, [[0, 0], [640, 0], [640, 480], [0, 480]], atol=1e-9)
    np.testing.assert_allclose(cam.to_camera(segs[:4, 1])[:, 2], 0.3)
    with pytest.raises(ValueError, match='depth'):
        frustum_segments(cam, 0.0)


def test_bias_vectors_pair_each_estimate_with_its_own_sample():
    nominal = points(40, seed=3)
    rng = np.random.default_rng(4)
    estimated = nominal + rng.normal(0, 0.0007, nominal.shape)
    order = rng.permutation(40)
    segs = bias_vectors(nominal, estimated[order])
    assert segs.shape == (40, 2, 3)
    np.testing.assert_allclose(segs[:, 0], nominal[order])
    np.testing.assert_allclose(segs[:, 1], estimated[order])
    far = estimated.copy()
    far[0] += 0.05
    assert len(bias_vectors(nominal, far)) == 39


def _state(**kw):
    base = dict(camera_names=['cam1', 'cam2'], n_samples=3, min_samples=20,
                samples_per_camera={'cam1': 3, 'cam2': 1}, image_sizes={'cam1': (640, 480)},
                solving=False, n_solves=0, n_rejected=0,
                input_counts={'time_jump': 2, 'image_decode_error': 1},
                queue_dropped={'image': 0, 'joint': 0}, queue_depth={'image': 1, 'joint': 0})
    base.update(kw)
    return NodeState(**base)


def test_diagnostics_before_a_calibration():
    st = diagnostic_statuses(_state())
    assert [s.name for s in st] == ['armcal: calibration', 'armcal: cam1', 'armcal: cam2']
    main = st[0]
    assert main.level == 1 and main.message.startswith('collecting samples (3 of 20)')
    assert main.values['input_time_jump'] == '2'
    assert main.values['input_image_decode_error'] == '1'
    assert main.values['samples_cam2'] == '1'
    assert st[1].values['image_size'] == '640x480' and st[2].values['image_size'] == 'no image yet'
    msg = conv.diagnostic_array_msg(st, conv.time_msg(0))
    from diagnostic_msgs.msg import DiagnosticStatus
    assert msg.status[0].level == DiagnosticStatus.WARN
    assert conv.diagnostic_values(msg, 'armcal: calibration')['samples'] == '3'
    assert conv.diagnostic_values(msg, 'nope') is None
    dropped = diagnostic_statuses(_state(queue_dropped={'image': 4}))[0]
    assert 'dropped' in dropped.message and dropped.values['queue_dropped_image'] == '4'


def test_diagnostics_say_a_camera_changed_and_is_withheld():
    from armcal_ros.change_tracking import ChangeRecord
    start = 1_000_000_000_000
    moved = ChangeRecord('camera', 'cam2', 1, start + int(95e9), start + int(101e9), 30.0, 23.4,
                         8, new_observations=7)
    st = diagnostic_statuses(_state(changes=[moved], withheld=['cam2'], start_ns=start))
    main, cam2 = st[0], st[2]
    assert main.level == 1 and 'withheld until recalibrated: cam2' in main.message
    assert main.values['changes'] == '1'
    assert cam2.level == 1
    assert cam2.message.startswith('cam2 changed at t = 95.0 s: recalibrating')
    assert '(7 of 20 new views)' in cam2.message
    # Recalibrated: the camera's status carries what happened.
    moved.status, moved.what = 'recalibrated', 'pose'
    moved.rotation_deg, moved.translation_mm, moved.focal_percent = 0.6, 4.0, 0.01
    st = diagnostic_statuses(_state(changes=[moved], start_ns=start))
    assert st[2].values['last_change'] == ('cam2 changed at t = 95.0 s: pose (0.60 deg / 4.0 '
                                           'mm, focal +0.01 %), recalibrated')
    # An arm alarm is a warning on the calibrator's status until it is confirmed or gone.
    arm = ChangeRecord('arm', None, 1, start + int(200e9), start + int(205e9), 30.0, 23.4, 5,
                       status='reported')
    main = diagnostic_statuses(_state(changes=[moved, arm], start_ns=start))[0]
    assert main.level == 1 and 'disagreed with the arm at t = 200.0 s' in main.message


def test_each_camera_says_how_the_light_was_pooled():
    said = 'not_smooth: the light\'s shift is not smooth over the marker\'s places'
    st = diagnostic_statuses(_state(light_pooling={'cam2': said}))
    assert 'light_pooling' not in st[1].values and st[2].values['light_pooling'] == said


def test_a_camera_whose_last_fit_was_degenerate_says_so():
    from armcal_ros.core.camera import Camera
    from armcal_ros.core.results import Calibration, CameraCalibration
    cam = Camera('cam1', 640, 480, 800.0, 800.0, 320.0, 240.0)
    why = 'only 6 of its 18 observations fit (fewer than 50%)'
    cal = Calibration({'cam1': CameraCalibration(cam, {}, np.eye(6), 0.2, 40, 40)}, 'fixed',
                      1.0, 40, 0.1, 1.7e9, 'converged', 'ok', {}, {'cam1': why, 'cam2': why})
    st = diagnostic_statuses(_state(calibration=cal))
    # cam1 keeps an earlier calibration (published, with a warning); cam2 has none.
    assert st[1].level == 1 and 'the previous calibration kept' in st[1].message
    assert st[1].values['last_fit_unusable'] == why and 'fx' in st[1].values
    assert st[2].level == 1 and st[2].message == f'not calibrated yet: its fit is not a ' \
        f'calibration ({why})'


def test_a_moved_cameras_status_says_how_its_earlier_views_were_solved():
    from armcal_ros.core.camera import Camera
    from armcal_ros.core.results import Calibration, CameraCalibration
    cams = {n: CameraCalibration(Camera(n, 640, 480, 800.0, 800.0, 320.0, 240.0), {},
                                 np.eye(6), 0.2, 40, 40) for n in ('cam1', 'cam2')}
    said = 'solved with the lens of cam2 (Wald 5.9 (limit 20.1, 8 dof), ...: one lens)'
    cal = Calibration(cams, 'kinematic', 1.0, 40, 0.1, 1.7e9, 'converged', 'ok',
                      {'earlier_epochs': {'cam2#1': said}}, {})
    st = diagnostic_statuses(_state(calibration=cal))
    assert not any(k.startswith('views_before_change') for k in st[1].values)
    assert st[2].values['views_before_change_1'] == f'cam2#1: {said}'
