"""
Board calibration on synthetic views: cameras and the board's mount on the link recovered.

The board is seen by one or two static cameras in views posed to face camera 0; the corners are
projected by the true cameras with 0.2 px noise (the mount's maths: test_core_target.py).
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.board_calibration import (BoardData, calibrate_board, CameraSpec,
                                               MountSettings)
from armcal_ros.core.camera import Camera
from armcal_ros.core.priors import PriorSettings
from armcal_ros.core.target import correct_mount, invert, mount_points, rotation_angle_deg
from armcal_ros.frontend.detectors import CharucoBoard
from helpers.board_scene import transform

MOUNT = transform([0.3, -2.0, 0.4], [0.05, 0.11, 0.20])
BOARD = CharucoBoard(7, 5, 0.036, 0.018, 'DICT_6X6_250')


def make_scene(n_views=14, noise_px=0.2, seed=1, width=1600, height=1200, cameras=1):
    """Make static camera(s) and views of a board on a link, posed to face camera 0."""
    rng = np.random.default_rng(seed)
    cams = []
    for j in range(cameras):
        eye = np.array([0.0 + 0.5 * j, 1.3, 0.3 + 0.1 * j])
        cams.append(Camera.look_at(f'cam{j}', width, height, 1350.0 + 10 * j, 1355.0,
                                   790.0, 620.0, [-0.12, 0.2, 0.0, 0.0, 0.0], eye,
                                   [0.1, 0.4, 0.5]))
    c0 = cams[0]
    T_base_cam0 = invert(np.vstack([np.column_stack([c0.rotation, c0.translation]),
                                    [0, 0, 0, 1]]))
    centre = -0.5 * np.array([5 * 0.036, 7 * 0.036, 0.0])
    poses, view, camera, corner, uv = [], [], [], [], []
    P = BOARD.points()
    for v in range(n_views):
        # Board facing camera 0 from 0.8-1.1 m, tilted up to ~35 deg.
        R_ct = Rotation.from_rotvec(rng.uniform(-0.6, 0.6, 3)).as_matrix()
        t_ct = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.1, 0.1),
                         rng.uniform(0.8, 1.1)]) - R_ct @ (-centre)
        T_ct = np.eye(4)
        T_ct[:3, :3], T_ct[:3, 3] = R_ct, t_ct
        T_bl = T_base_cam0 @ T_ct @ invert(MOUNT)
        poses.append(T_bl)
        X = mount_points(T_bl[None], MOUNT, np.zeros(len(P), int), P)
        for j, c in enumerate(cams):
            x = c.project(X) + rng.normal(0, noise_px, (len(P), 2))
            ok = c.in_front(X) & (x[:, 0] > 0) & (x[:, 0] < width - 1) & \
                (x[:, 1] > 0) & (x[:, 1] < height - 1)
            view += [v] * int(ok.sum())
            camera += [j] * int(ok.sum())
            corner += list(np.flatnonzero(ok))
            uv.append(x[ok])
    data = BoardData(np.array(poses), P, view, camera, corner, np.vstack(uv))
    specs = [CameraSpec(c.name, width, height) for c in cams]
    return data, specs, cams


@pytest.mark.parametrize('seeded', [False, True])
def test_fixed_board_calibration_recovers_camera_and_mount(seeded):
    data, specs, truth = make_scene()
    seed = correct_mount(MOUNT, [0.01, -0.008, 0.005, 0.02, -0.01, 0.015]) if seeded else None
    res = calibrate_board(specs, data, PriorSettings(model='fixed'),
                          SolverSettings(free_distortion=('k1', 'k2')), T_link_target=seed)
    assert res.success, res.calibration.message
    assert res.init.mount_seed == ('given' if seeded else 'hand-eye (cam0)')
    cam, true = res.cameras['cam0'], truth[0]
    assert abs(cam.fx - true.fx) < 3 and abs(cam.fy - true.fy) < 3
    assert abs(cam.cx - true.cx) < 3 and abs(cam.cy - true.cy) < 3
    assert abs(cam.dist[0] - true.dist[0]) < 0.02
    assert np.linalg.norm(cam.center - true.center) < 2e-3
    assert np.linalg.norm(res.T_link_target[:3, 3] - MOUNT[:3, 3]) < 1e-3
    assert rotation_angle_deg(res.T_link_target[:3, :3], MOUNT[:3, :3]) < 0.1
    rms = res.calibration.adjustment.cameras['cam0'].rms_px
    assert 0.15 < rms < 0.35          # the 0.2 px image noise, per axis -> ~0.28 px norm
    assert res.mount_std is not None
    assert np.all(res.mount_std[:3] < 5e-4) and np.all(res.mount_std[3:] < np.radians(0.1))
    # Held-out prediction of the training views reproduces the fit.
    pred = res.predict_uv(data, [s.name for s in specs])
    assert np.sqrt(np.mean(np.sum((pred - data.uv) ** 2, axis=1))) < 0.4


def test_two_cameras_and_a_fixed_mount():
    data, specs, truth = make_scene(cameras=2, seed=3)
    res = calibrate_board(specs, data, PriorSettings(model='fixed'),
                          SolverSettings(free_distortion=('k1', 'k2')), T_link_target=MOUNT,
                          mount=MountSettings(estimate=False))
    assert res.success
    assert res.mount_std is None and np.allclose(res.T_link_target, MOUNT)
    for c in truth:
        assert np.linalg.norm(res.cameras[c.name].center - c.center) < 3e-3


def test_independent_model_with_mount_absorbs_pose_noise():
    data, specs, truth = make_scene(seed=4)
    rng = np.random.default_rng(5)
    data.poses = np.array([p @ transform(rng.normal(0, 2e-4, 3), rng.normal(0, 2e-4, 3))
                           for p in data.poses])
    res = calibrate_board(specs, data, PriorSettings(model='independent', point_sigma=3e-4),
                          SolverSettings(free_distortion=('k1', 'k2')))
    assert res.success and res.model == 'independent+mount'
    assert np.linalg.norm(res.T_link_target[:3, 3] - MOUNT[:3, 3]) < 3e-3
    assert abs(res.cameras['cam0'].fx - truth[0].fx) < 10


def test_bad_input_is_refused():
    data, specs, _ = make_scene(n_views=4)
    with pytest.raises(ValueError, match='T_link_target is needed'):
        calibrate_board(specs, data, mount=MountSettings(estimate=False))
    with pytest.raises(ValueError, match='cannot estimate a board mount'):
        calibrate_board(specs, data, PriorSettings(model='kinematic'))
    with pytest.raises(ValueError, match='corner must index'):
        BoardData(data.poses, data.points[:3], data.view, data.camera, data.corner, data.uv)
    with pytest.raises(ValueError, match='sigma_rotation'):
        MountSettings(sigma_rotation=0).validate()


def test_two_solves_are_compared_by_their_image_noise_when_each_estimated_it():
    # Each solve whitened by its own estimated noise has a cost near its redundancy however
    # well it fits: the noise estimates compare, the costs do not.  With the noise given,
    # both are weighted alike and the costs compare.
    from types import SimpleNamespace
    from armcal_ros.core.board_calibration import _fits_better

    def result(sigma, cost, source='residuals'):
        return SimpleNamespace(pixel_sigma=sigma, noise_source=source,
                               adjustment=SimpleNamespace(cost=cost))
    assert _fits_better(result(0.078, 52.4), result(0.147, 50.9))
    assert not _fits_better(result(0.147, 50.9), result(0.078, 52.4))
    assert _fits_better(result(0.5, 40.0, 'given'), result(0.5, 50.0, 'given'))
    assert not _fits_better(result(0.5, 60.0, 'given'), result(0.5, 50.0, 'given'))
