"""robot_cal_tools data folders and the real-data regression (committed corner fixture)."""

import os

import numpy as np
import pytest

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.board_calibration import calibrate_board, CameraSpec
from armcal_ros.core.priors import PriorSettings
from armcal_ros.core.target import invert, rotation_angle_deg
from armcal_ros.frontend.detectors import CharucoBoard
from armcal_ros.io.rct_import import (board_data, is_rct_folder, load_rct_folder,
                                      load_views, RctFormatError)

HERE = os.path.dirname(os.path.abspath(__file__))
FIXTURE = os.path.join(HERE, 'data', 'rct_charuco', 'corners.json')
DATA = os.path.normpath(os.path.join(HERE, '..', '..', 'shared', 'data',
                                     'rct_test_set_charuco'))
REFERENCE = dict(fx=1352.02747, fy=1356.14287, cx=789.67065, cy=627.2995)
needs_data = pytest.mark.skipif(not os.path.isdir(DATA),
                                reason='real data ../shared/data/rct_test_set_charuco absent')


def fixture_problem():
    data, uvs, ids, size, _ = load_views(FIXTURE)
    board = CharucoBoard(*data.target.board_args, legacy=True)
    return data, board_data(data.poses, board.points(), uvs, ids), size


def test_fixture_is_compact_and_complete():
    assert os.path.getsize(FIXTURE) < 12000
    data, bd, size = fixture_problem()
    assert size == (1600, 1200) and len(data.poses) == 16
    assert len(bd) >= 290
    assert data.target_guess is not None and data.camera_guess is not None
    assert os.path.isfile(os.path.join(HERE, 'data', 'rct_charuco', 'LICENSE'))


def test_real_data_regression_fixed_model_with_mount():
    """Intrinsics k1 k2 free, camera pose and mount found without a guess: <= 1.25 px RMS."""
    data, bd, size = fixture_problem()
    res = calibrate_board([CameraSpec('camera', *size)], bd, PriorSettings(model='fixed'),
                          SolverSettings(free_distortion=('k1', 'k2')))
    assert res.success, res.calibration.message
    est = res.calibration.adjustment.cameras['camera']
    assert est.rms_px <= 1.25
    assert est.n_inliers >= 0.95 * est.n_observations
    cam = est.camera
    # The reference has no distortion; with k1, k2 free the focal lengths agree to 0.3 %,
    # the principal point to a few tens of pixels (it trades with the distortion centre).
    assert abs(cam.fx / REFERENCE['fx'] - 1) < 0.003
    assert abs(cam.fy / REFERENCE['fy'] - 1) < 0.003
    assert abs(cam.cx - REFERENCE['cx']) < 40 and abs(cam.cy - REFERENCE['cy']) < 40
    # The data set's earlier estimate of the camera pose and mount: about 1-2 cm and degree.
    T_bc = invert(np.vstack([np.column_stack([cam.rotation, cam.translation]), [0, 0, 0, 1]]))
    assert np.linalg.norm(T_bc[:3, 3] - data.camera_guess[:3, 3]) < 0.03
    assert rotation_angle_deg(T_bc[:3, :3], data.camera_guess[:3, :3]) < 2.0
    assert np.linalg.norm(res.T_link_target[:3, 3] - data.target_guess[:3, 3]) < 0.03
    assert rotation_angle_deg(res.T_link_target[:3, :3], data.target_guess[:3, :3]) < 3.0


def test_real_data_seeded_from_the_guess_reaches_the_same_solution():
    data, bd, size = fixture_problem()
    spec = [CameraSpec('camera', *size)]
    settings = SolverSettings(free_distortion=('k1', 'k2'))
    a = calibrate_board(spec, bd, PriorSettings(model='fixed'), settings)
    b = calibrate_board(spec, bd, PriorSettings(model='fixed'), settings,
                        T_link_target=data.target_guess)
    assert b.init.mount_seed == 'given'
    assert np.linalg.norm(a.T_link_target[:3, 3] - b.T_link_target[:3, 3]) < 1e-5
    assert abs(a.cameras['camera'].fx - b.cameras['camera'].fx) < 0.05


def test_legacy_numbering_matters_for_the_given_mount():
    """With new-style ids the data set's mount guess is a half turn off: a far worse fit."""
    data, uvs, ids, size, _ = load_views(FIXTURE)
    from armcal_ros.core.board_calibration import MountSettings
    spec = [CameraSpec('camera', *size)]
    rms = {}
    for legacy in (True, False):
        board = CharucoBoard(*data.target.board_args, legacy=legacy)
        # Fixture ids are legacy: map back to OpenCV ids for the new-style board.
        legacy_board = CharucoBoard(*data.target.board_args, legacy=True)
        new_ids = ids if legacy else [legacy_board.ids_from_opencv(i) for i in ids]
        bd = board_data(data.poses, board.points(), uvs, new_ids)
        res = calibrate_board(spec, bd, PriorSettings(model='fixed'),
                              SolverSettings(free_distortion=('k1', 'k2')),
                              T_link_target=data.target_guess,
                              mount=MountSettings(estimate=False))
        adj = res.calibration.adjustment
        rms[legacy] = adj.cameras['camera'].rms_px if adj is not None else np.inf
    # The guess is itself ~1.5 deg off (hence ~15 px), but the mirrored numbering is far worse.
    assert rms[True] < 25.0
    assert not rms[False] < 4 * rms[True]


def test_bad_folders_are_refused(tmp_path):
    assert not is_rct_folder(str(tmp_path))
    with pytest.raises(RctFormatError, match='cal_data.yaml'):
        load_rct_folder(str(tmp_path))
    (tmp_path / 'cal_data.yaml').write_text('- image: images/0.png\n  pose: poses/0.yaml\n')
    with pytest.raises(RctFormatError, match='does not exist'):
        load_rct_folder(str(tmp_path))
    (tmp_path / 'images').mkdir()
    (tmp_path / 'images' / '0.png').write_bytes(b'')
    (tmp_path / 'poses').mkdir()
    (tmp_path / 'poses' / '0.yaml').write_text('x: 0.1\ny: 0.2\nz: 0.3\nqx: 0\nqy: 0\nqz: 0\n')
    with pytest.raises(RctFormatError, match='qw'):
        load_rct_folder(str(tmp_path))
    (tmp_path / 'poses' / '0.yaml').write_text('x: 0\ny: 0\nz: 0\nqx: 0\nqy: 0\nqz: 0\nqw: 1\n')
    (tmp_path / 'target.yaml').write_text('target_finder:\n  type: rct_ros_tools::'
                                          'ModifiedCircleGridTargetFinderPlugin\n')
    with pytest.raises(RctFormatError, match='not supported'):
        load_rct_folder(str(tmp_path))
    with pytest.raises(RctFormatError, match='not a corner file'):
        load_views(str(tmp_path / 'cal_data.yaml'))


@needs_data
def test_real_folder_loads_with_its_guesses():
    data = load_rct_folder(DATA)
    assert len(data.image_paths) == len(data.poses) == 16
    assert np.allclose(np.linalg.det(data.poses[:, :3, :3]), 1.0)
    assert data.intrinsics_guess == dict(fx=1400.0, fy=1400.0, cx=800.0, cy=600.0)
    assert data.target.rows == 7 and data.target.cols == 5 and data.target.dictionary == 10
    fix, _, _, _, _ = load_views(FIXTURE)
    assert np.allclose(fix.poses, data.poses, atol=1e-9)
