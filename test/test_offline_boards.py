"""
``armcal calibrate`` on ChArUco boards: a robot_cal_tools folder, a pose-input bag, a joint bag.

The board scene of helpers/board_scene.py: one static camera sees a board on a robot link in 8
views.  The robot_cal_tools folder holds the images and the link poses; ``board_pose_bag`` a
PoseStamped link pose at 50 Hz and the images; ``board_joint_bag`` the joint states of a
Cartesian robot with a roll-pitch-yaw wrist at 100 Hz and the images at 10 Hz, with a 1 s dwell
at each view and a 0.5 s move between them (both bags are fixtures of conftest.py).
"""

import argparse
import json
import os

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from armcal_ros.core.target import invert
from armcal_ros.frontend.store import SampleStore
from armcal_ros.io.calib_files import read_camera_info
from armcal_ros.offline import calibrate_bag, CalibrateError, collect_samples, run
from armcal_ros.settings import load_settings
from helpers.board_scene import (BOARD, BOARD_SIZE, check_mount, JOINTS, joint_params, K, MOUNT,
                                 params, T_CAM_BASE, write_folder)


# -- a robot_cal_tools folder -----------------------------------------------------------

@pytest.fixture(scope='module')
def folder(tmp_path_factory):
    root = str(tmp_path_factory.mktemp('rct') / 'set')
    write_folder(root)
    return root


def test_calibrate_a_folder_end_to_end(folder, tmp_path, capsys):
    out = str(tmp_path / 'out')
    args = argparse.Namespace(bag=folder, params=params(tmp_path / 'p.yaml'), output=out,
                              noise_model=None, quiet=False)
    assert run(args) == 0
    printed = capsys.readouterr().out
    assert 'T_tool0_target' in printed and '(estimated)' in printed
    for name in ('cam.yaml', 'extrinsics.yaml', 'calibration.json', 'target.yaml',
                 'report.json'):
        assert os.path.isfile(os.path.join(out, name)), name
    cam = read_camera_info(os.path.join(out, 'cam.yaml'))
    assert abs(cam.fx - K[0, 0]) < 3 and abs(cam.fy - K[1, 1]) < 3
    assert abs(cam.cx - K[0, 2]) < 3 and abs(cam.cy - K[1, 2]) < 3
    with open(os.path.join(out, 'target.yaml')) as f:
        tgt = yaml.safe_load(f)
    assert tgt['estimated'] is True
    assert np.linalg.norm(np.array(tgt['translation']) - MOUNT[:3, 3]) < 2e-3
    q = Rotation.from_quat(tgt['rotation_xyzw'])
    assert (q.inv() * Rotation.from_matrix(MOUNT[:3, :3])).magnitude() < np.radians(0.2)


REAL = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', '..',
                                     'shared', 'data', 'rct_test_set_charuco'))
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.mark.skipif(not os.path.isdir(REAL), reason=f'real data {REAL} absent')
def test_the_real_folder_through_armcal_calibrate(tmp_path, capsys):
    # The folder's 16 views pass the front end as 16 dwells and give the fixed + mount solution
    # that bench/real_data.py computes from the detected corners directly (docs/BENCHMARKS.md,
    # "Real data", seeded column: fx 1351.7, cy 626.9, 1.138 px over 384 of 384 corners).
    out = tmp_path / 'out'
    args = argparse.Namespace(bag=REAL, params=os.path.join(ROOT, 'config', 'rct_charuco.yaml'),
                              output=str(out), noise_model=None, quiet=False)
    assert run(args) == 0
    with open(out / 'report.json') as f:
        report = json.load(f)
    assert report['n_samples'] == 16 and report['input']['kind'] == 'robot_cal_tools folder'
    cam = report['cameras']['camera']
    assert (cam['n_observations'], cam['n_inliers']) == (384, 384)
    assert abs(cam['rms_px'] - 1.138) < 0.002
    assert abs(cam['fx'] - 1351.7) < 0.1 and abs(cam['cy'] - 626.9) < 0.1
    assert report['target']['estimated'] is True


def test_wrong_board_parameters_are_named(folder, tmp_path):
    args = argparse.Namespace(bag=folder, params=params(tmp_path / 'p.yaml', charuco_rows=6),
                              output=str(tmp_path / 'out'), noise_model=None, quiet=False)
    with pytest.raises(CalibrateError, match='charuco_rows'):
        run(args)


def test_unknown_mount_without_estimation_is_refused(folder, tmp_path):
    args = argparse.Namespace(
        bag=folder, params=params(tmp_path / 'p.yaml', estimate_marker_offset=False),
        output=str(tmp_path / 'out'), noise_model=None, quiet=False)
    with pytest.raises(CalibrateError, match='estimate_marker_offset or target_pose_guess'):
        run(args)


# -- a bag with a PoseStamped link pose -------------------------------------------------

def test_calibrate_a_pose_input_bag(board_pose_bag, tmp_path, capsys):
    out = str(tmp_path / 'out')
    p = params(tmp_path / 'p.yaml', pose_topic='/tool_pose', **BOARD_SIZE)
    assert run(argparse.Namespace(bag=board_pose_bag, params=p, output=out, noise_model=None,
                                  quiet=True)) == 0
    with open(os.path.join(out, 'report.json')) as f:
        report = json.load(f)
    counts = report['front_end']
    # 8 dwells, one sample each (the last pose's second still frame joins its dwell); 7 frames
    # while moving.
    assert report['n_samples'] == 8 and counts['frames_moving'] == 7
    cam = read_camera_info(os.path.join(out, 'cam.yaml'))
    assert abs(cam.fx - K[0, 0]) < 3 and abs(cam.cy - K[1, 2]) < 3
    assert np.linalg.norm(np.array(report['target']['T_link_target'][:3]) -
                          MOUNT[:3, 3]) < 2e-3


def test_pose_input_needs_a_board_and_the_topic(board_pose_bag, tmp_path):
    p = params(tmp_path / 'p.yaml', pose_topic='/nope', **BOARD_SIZE)
    with pytest.raises(CalibrateError, match='pose_topic /nope'):
        run(argparse.Namespace(bag=board_pose_bag, params=p, output=str(tmp_path / 'o'),
                               noise_model=None, quiet=False))
    p = params(tmp_path / 'q.yaml', pose_topic='/tool_pose')
    with pytest.raises(CalibrateError, match='charuco_rows'):
        run(argparse.Namespace(bag=board_pose_bag, params=p, output=str(tmp_path / 'o'),
                               noise_model=None, quiet=False))


def test_charuco_with_joint_states_takes_the_joint_front_end(board_pose_bag, tmp_path):
    # Not refused: a board with joint input is collected from joint states,
    # so a bag without them says so; the board's size must be given.
    p = params(tmp_path / 'p.yaml', robot_description='<robot name="x"/>', **BOARD_SIZE)
    with pytest.raises(CalibrateError, match='joint_states_topic'):
        run(argparse.Namespace(bag=board_pose_bag, params=p, output=str(tmp_path / 'o'),
                               noise_model=None, quiet=False))
    from armcal_ros.compose import build_board
    from armcal_ros.params import defaults
    from armcal_ros.settings import settings_from_values
    settings = settings_from_values(dict(defaults(), marker_type='charuco',
                                         robot_description='<robot name="x"/>'))
    with pytest.raises(ValueError, match='charuco_rows'):
        build_board(settings)


def test_charuco_pose_input_through_the_collector(board_pose_bag, tmp_path):
    settings = load_settings(params(tmp_path / 'p.yaml', pose_topic='/tool_pose',
                                    **BOARD_SIZE, min_samples=5))
    res = calibrate_bag(board_pose_bag, settings, tmp_path / 'out')
    rep = res.report
    # 8 dwells; the last pose's second still frame is the same place: merged into its view.
    assert rep['n_samples'] == 8 and rep['samples']['merged'] == 1
    assert rep['front_end']['frames_moving'] == 7
    check_mount(rep['target']['T_link_target'])
    cam = read_camera_info(str(tmp_path / 'out' / 'cam.yaml'))
    assert abs(cam.fx - K[0, 0]) < 3 and abs(cam.cy - K[1, 2]) < 3


# -- a bag with the joint states of a Cartesian robot -----------------------------------

@pytest.mark.slow
def test_charuco_with_joint_input_calibrates_through_the_cli(board_joint_bag, tmp_path):
    out = tmp_path / 'out'
    p = joint_params(tmp_path / 'p.yaml', board_joint_bag)
    assert run(argparse.Namespace(bag=str(board_joint_bag / 'bag'), params=p, output=str(out),
                                  noise_model=None, quiet=False)) == 0
    report = json.loads((out / 'report.json').read_text())
    assert report['accepted'] and report['n_samples'] == 8
    assert report['front_end']['frames_moving'] >= 8 * 3
    assert report['target']['estimated']
    check_mount(report['target']['T_link_target'])
    cam = read_camera_info(str(out / 'cam.yaml'))
    assert abs(cam.fx - K[0, 0]) < 3 and abs(cam.fy - K[1, 1]) < 3
    assert abs(cam.cx - K[0, 2]) < 3 and abs(cam.cy - K[1, 2]) < 3
    assert report['cameras']['cam']['rms_px'] < 0.3
    # The camera pose in the base frame, from the extrinsics written beside it.
    with open(out / 'extrinsics.yaml') as f:
        ext = yaml.safe_load(f)['cameras']['cam']
    assert np.linalg.norm(np.array(ext['translation']) - invert(T_CAM_BASE)[:3, 3]) < 3e-3
    assert os.path.exists(out / 'target.yaml')


def test_charuco_joint_input_board_samples_store_round_trip(board_joint_bag, tmp_path):
    front = collect_samples(str(board_joint_bag / 'bag'),
                            load_settings(joint_params(tmp_path / 'p.yaml', board_joint_bag)))
    samples = sorted(front.store.samples, key=lambda s: s.id)
    assert len(samples) == 8
    # About 9 still frames per 1 s dwell; the board is searched in the first
    # max_views_per_dwell (3) only.
    assert front.counts['detections'] == 8 * 3
    assert front.counts['frames_skipped_dwell_full'] == front.counts['frames_still'] - 8 * 3 > 30
    for s in samples:
        obs = s.observations['cam']
        assert s.q is not None and s.pose is not None and s.reference_points.shape == (4, 3)
        assert len(obs.ids) >= 12 and obs.n_frames == 3
        # The board's corners project where the camera saw them (link pose from FK).
        X = (s.pose @ MOUNT @ np.column_stack([BOARD.points()[obs.ids],
                                               np.ones(len(obs.ids))]).T).T[:, :3]
        Xc = X @ T_CAM_BASE[:3, :3].T + T_CAM_BASE[:3, 3]
        uv = (Xc @ K.T)[:, :2] / Xc[:, 2:]
        assert np.sqrt(np.mean(np.sum((uv - obs.uv) ** 2, axis=1))) < 0.3
    front.store.save(tmp_path / 'st')
    back = SampleStore.load(tmp_path / 'st', joint_names=JOINTS)
    assert len(back) == 8
    for a, b in zip(samples, sorted(back.samples, key=lambda s: s.id)):
        np.testing.assert_array_equal(a.pose, b.pose)
        np.testing.assert_array_equal(a.q, b.q)
        np.testing.assert_array_equal(a.reference_points, b.reference_points)
        np.testing.assert_array_equal(a.observations['cam'].ids, b.observations['cam'].ids)
        np.testing.assert_array_equal(a.observations['cam'].uv, b.observations['cam'].uv)


def test_max_views_per_dwell_parameter_reaches_the_front_end(board_joint_bag, tmp_path):
    settings = load_settings(joint_params(tmp_path / 'p.yaml', board_joint_bag),
                             {'max_views_per_dwell': 1})
    front = collect_samples(str(board_joint_bag / 'bag'), settings)
    assert len(front.store) == 8
    assert front.counts['detections'] == 8
    assert all(s.observations['cam'].n_frames == 1 for s in front.store.samples)
