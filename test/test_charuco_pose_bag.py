"""Pose input: a bag with a PoseStamped link pose and images of a board, end to end."""

import argparse
import os

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from armcal_ros.core.target import invert, pose_vector
from armcal_ros.io.bag import BagWriter
from armcal_ros.io.calib_files import read_camera_info
from armcal_ros.offline import CalibrateError, run
from test_rct_cli import K, MOUNT, params, render, T_CAM_BASE

POSE = 'geometry_msgs/msg/PoseStamped'


def view_poses(n_views, seed=0):
    """Link poses that put the board 0.65-0.8 m in front of the camera, tilted up to 0.5 rad."""
    rng = np.random.default_rng(seed)
    centre = np.array([2.5 * 0.04, 3.5 * 0.04, 0.0])
    out = []
    for _ in range(n_views):
        R = Rotation.from_rotvec(rng.uniform(-0.5, 0.5, 3)).as_matrix()
        T_ct = np.eye(4)
        T_ct[:3, :3] = R
        T_ct[:3, 3] = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04),
                                rng.uniform(0.65, 0.8)]) - R @ centre
        out.append(invert(T_CAM_BASE) @ T_ct @ invert(MOUNT))
    return out


def write_bag(path, n_views=8, seed=0):
    link = view_poses(n_views, seed)
    with BagWriter(path, storage='mcap') as w:
        types = w.typestore.types
        t = 1_000_000_000
        for v, T in enumerate(link):
            nxt = link[min(v + 1, n_views - 1)]
            # 1 s dwell at 50 Hz, then 0.4 s of motion towards the next pose.
            for k in range(70):
                a = max(0.0, (k - 50) / 20.0)
                p = (1 - a) * T[:3, 3] + a * nxt[:3, 3]
                q = pose_vector(T if a == 0 else nxt)[3:] if a in (0.0, 1.0) else \
                    pose_vector(T)[3:]
                msg = types[POSE](header=w.header(t, 'base_link'), pose=types[
                    'geometry_msgs/msg/Pose'](position=types['geometry_msgs/msg/Point'](
                        x=p[0], y=p[1], z=p[2]), orientation=types[
                        'geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3])))
                w.write_message('/tool_pose', POSE, t, msg)
                if k in (25, 60):           # one still frame, one while moving
                    T_ct = T_CAM_BASE @ T @ MOUNT
                    w.write_image('/cam/image_raw', t + 3_000_000, render(T_ct))
                t += 20_000_000


@pytest.fixture(scope='module')
def bag(tmp_path_factory):
    path = str(tmp_path_factory.mktemp('posebag') / 'bag')
    write_bag(path)
    return path


def test_calibrate_a_pose_input_bag(bag, tmp_path, capsys):
    out = str(tmp_path / 'out')
    p = params(tmp_path / 'p.yaml', pose_topic='/tool_pose', charuco_rows=7, charuco_cols=5,
               charuco_square_size=0.04, charuco_marker_size=0.02)
    assert run(argparse.Namespace(bag=bag, params=p, output=out, noise_model=None,
                                  quiet=True)) == 0
    import json
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


def test_pose_input_needs_a_board_and_the_topic(bag, tmp_path):
    p = params(tmp_path / 'p.yaml', pose_topic='/nope', charuco_rows=7, charuco_cols=5,
               charuco_square_size=0.04, charuco_marker_size=0.02)
    with pytest.raises(CalibrateError, match='pose_topic /nope'):
        run(argparse.Namespace(bag=bag, params=p, output=str(tmp_path / 'o'),
                               noise_model=None, quiet=True))
    p = params(tmp_path / 'q.yaml', pose_topic='/tool_pose')
    with pytest.raises(CalibrateError, match='charuco_rows'):
        run(argparse.Namespace(bag=bag, params=p, output=str(tmp_path / 'o'),
                               noise_model=None, quiet=True))


def test_charuco_with_joint_states_takes_the_joint_front_end(bag, tmp_path):
    # Not refused: a board with joint input is collected from joint states,
    # so a bag without them says so; the board's size must be given.
    p = params(tmp_path / 'p.yaml', robot_description='<robot name="x"/>',
               charuco_rows=7, charuco_cols=5, charuco_square_size=0.04,
               charuco_marker_size=0.02)
    with pytest.raises(CalibrateError, match='joint_states_topic'):
        run(argparse.Namespace(bag=bag, params=p, output=str(tmp_path / 'o'),
                               noise_model=None, quiet=True))
    from armcal_ros.compose import build_board
    from armcal_ros.params import defaults
    from armcal_ros.settings import settings_from_values
    settings = settings_from_values(dict(defaults(), marker_type='charuco',
                                         robot_description='<robot name="x"/>'))
    with pytest.raises(ValueError, match='charuco_rows'):
        build_board(settings)
