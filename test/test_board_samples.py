"""
ChArUco boards through the shared collector and engine: joint input and pose input.

A Cartesian robot with a roll-pitch-yaw wrist (three prismatic joints, three revolute ones: its
inverse kinematics is exact and trivial) carries the rendered board of test_rct_cli.py in front of
its static camera; the bag holds its joint states at 100 Hz and camera images at 10 Hz, with a
1 s dwell at each of 8 views and a 0.5 s move between them.
"""

import argparse
import json
import os

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.priors import PriorSettings
from armcal_ros.core.target import invert
from armcal_ros.engine import CalibrationEngine, EngineSettings
from armcal_ros.frontend.samples import BoardTarget, Observation, Sample
from armcal_ros.frontend.store import AddResult, FILE_NAME, SampleStore
from armcal_ros.io.bag import BagWriter
from armcal_ros.io.calib_files import read_camera_info
from armcal_ros.offline import calibrate_bag, collect_samples, run
from armcal_ros.settings import load_settings
from armcal_ros.robot.kinematics import KinematicChain
from test_charuco_pose_bag import view_poses, write_bag as write_pose_bag
from test_rct_cli import BOARD, K, MOUNT, params, render, T_CAM_BASE

URDF = '''<robot name="cartesian">
  <link name="base_link"/><link name="lx"/><link name="ly"/><link name="lz"/>
  <link name="la"/><link name="lb"/><link name="tool0"/>
  <joint name="x" type="prismatic"><parent link="base_link"/><child link="lx"/>
    <axis xyz="1 0 0"/><limit lower="-5" upper="5" velocity="1" effort="1"/></joint>
  <joint name="y" type="prismatic"><parent link="lx"/><child link="ly"/>
    <axis xyz="0 1 0"/><limit lower="-5" upper="5" velocity="1" effort="1"/></joint>
  <joint name="z" type="prismatic"><parent link="ly"/><child link="lz"/>
    <axis xyz="0 0 1"/><limit lower="-5" upper="5" velocity="1" effort="1"/></joint>
  <joint name="yaw" type="continuous"><parent link="lz"/><child link="la"/>
    <axis xyz="0 0 1"/></joint>
  <joint name="pitch" type="continuous"><parent link="la"/><child link="lb"/>
    <axis xyz="0 1 0"/></joint>
  <joint name="roll" type="continuous"><parent link="lb"/><child link="tool0"/>
    <axis xyz="1 0 0"/></joint>
</robot>
'''
JOINTS = ['x', 'y', 'z', 'yaw', 'pitch', 'roll']
BOARD_PARAMS = dict(charuco_rows=7, charuco_cols=5, charuco_square_size=0.04,
                    charuco_marker_size=0.02, min_samples=5)


def ik(T):
    """Joint angles of the Cartesian robot for the link pose T: T(x, y, z) Rz Ry Rx."""
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_euler('ZYX')])


def write_joint_bag(path, chain, n_views=8):
    """Joint states at 100 Hz (dwell 1 s, move 0.5 s per view) and 10 Hz rendered images."""
    qs = [ik(T) for T in view_poses(n_views)]
    t0, dwell, move = 1_000_000_000, 1.0, 0.5
    period = dwell + move

    def q_at(t):
        v = min(int(t // period), n_views - 1)
        a = np.clip((t - v * period - dwell) / move, 0.0, 1.0) if v < n_views - 1 else 0.0
        return (1 - a) * qs[v] + a * qs[min(v + 1, n_views - 1)]

    total = n_views * period
    with BagWriter(path, storage='mcap') as w:
        events = [(k * 0.01, 0) for k in range(int(total / 0.01))]
        events += [(0.003 + k * 0.1, 1) for k in range(int(total / 0.1) - 1)]
        for t, kind in sorted(events):
            stamp = t0 + int(round(t * 1e9))
            q = q_at(t)
            if kind == 0:
                w.write_joint_state('/joint_states', stamp, JOINTS, q)
            else:
                T_ct = T_CAM_BASE @ chain.fk_pose(q)[0] @ MOUNT
                w.write_image('/cam/image_raw', stamp, render(T_ct))


@pytest.fixture(scope='module')
def chain():
    c = KinematicChain.from_urdf(URDF, 'base_link', 'tool0')
    for T in view_poses(3):
        np.testing.assert_allclose(c.fk_pose(ik(T))[0], T, atol=1e-12)
    return c


@pytest.fixture(scope='module')
def joint_bag(tmp_path_factory, chain):
    d = tmp_path_factory.mktemp('boardjoints')
    write_joint_bag(str(d / 'bag'), chain)
    (d / 'robot.urdf').write_text(URDF)
    return d


def _joint_params(d, tmp_path, name='p.yaml', **kw):
    return params(tmp_path / name, robot_description_file=str(d / 'robot.urdf'),
                  marker_link='tool0', **BOARD_PARAMS, **kw)


def _check_mount(T_vec, tol_m=2e-3, tol_deg=0.3):
    assert np.linalg.norm(np.asarray(T_vec[:3]) - MOUNT[:3, 3]) < tol_m
    dR = Rotation.from_quat(T_vec[3:]).as_matrix().T @ MOUNT[:3, :3]
    assert np.degrees(Rotation.from_matrix(dR).magnitude()) < tol_deg


@pytest.mark.slow
def test_charuco_with_joint_input_calibrates_through_the_cli(joint_bag, tmp_path):
    out = tmp_path / 'out'
    p = _joint_params(joint_bag, tmp_path)
    assert run(argparse.Namespace(bag=str(joint_bag / 'bag'), params=p, output=str(out),
                                  noise_model=None, quiet=True)) == 0
    report = json.loads((out / 'report.json').read_text())
    assert report['accepted'] and report['n_samples'] == 8
    assert report['front_end']['frames_moving'] >= 8 * 3
    assert report['target']['estimated']
    _check_mount(report['target']['T_link_target'])
    cam = read_camera_info(str(out / 'cam.yaml'))
    assert abs(cam.fx - K[0, 0]) < 3 and abs(cam.fy - K[1, 1]) < 3
    assert abs(cam.cx - K[0, 2]) < 3 and abs(cam.cy - K[1, 2]) < 3
    assert report['cameras']['cam']['rms_px'] < 0.3
    # The camera pose in the base frame, from the extrinsics written beside it.
    with open(out / 'extrinsics.yaml') as f:
        ext = yaml.safe_load(f)['cameras']['cam']
    assert np.linalg.norm(np.array(ext['translation']) - invert(T_CAM_BASE)[:3, 3]) < 3e-3
    assert os.path.exists(out / 'target.yaml')


def test_charuco_joint_input_board_samples_store_round_trip(joint_bag, tmp_path):
    front = collect_samples(str(joint_bag / 'bag'),
                            load_settings(_joint_params(joint_bag, tmp_path)))
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


def test_max_views_per_dwell_parameter_reaches_the_front_end(joint_bag, tmp_path):
    settings = load_settings(_joint_params(joint_bag, tmp_path), {'max_views_per_dwell': 1})
    front = collect_samples(str(joint_bag / 'bag'), settings)
    assert len(front.store) == 8
    assert front.counts['detections'] == 8
    assert all(s.observations['cam'].n_frames == 1 for s in front.store.samples)


@pytest.mark.slow
def test_engine_solves_board_samples_and_resumes_its_mount(joint_bag, tmp_path):
    front = collect_samples(str(joint_bag / 'bag'),
                            load_settings(_joint_params(joint_bag, tmp_path)))
    board = BoardTarget(BOARD.points(), None, estimate_mount=True)
    settings = EngineSettings(['cam'], PriorSettings('correlated'),
                              SolverSettings(pixel_sigma=0.2, free_distortion=()),
                              min_samples=5, board=board, marker_link='tool0')
    eng = CalibrationEngine(settings)
    eng.set_image_size('cam', 800, 600)
    for s in front.store.samples:
        eng.add_sample(s)
    out = eng.solve()
    assert out.accepted, out.reason
    assert out.calibration.model == 'correlated+mount'
    assert abs(out.calibration.cameras['cam'].camera.fx - K[0, 0]) < 3
    T = eng.T_link_target
    _check_mount(np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()]))
    eng.save(tmp_path / 'o')
    fresh = CalibrationEngine(settings)
    said = fresh.load(tmp_path / 'o')
    assert 'mount' in said and len(fresh.store) == 8
    np.testing.assert_allclose(fresh.T_link_target, T, atol=1e-6)
    with pytest.raises(ValueError, match='8 saved samples are board samples'):
        CalibrationEngine(EngineSettings(['cam'])).load(tmp_path / 'o')


def test_charuco_pose_input_through_the_collector(tmp_path):
    bag = str(tmp_path / 'bag')
    write_pose_bag(bag)
    settings = load_settings(params(tmp_path / 'p.yaml', pose_topic='/tool_pose',
                                    **BOARD_PARAMS))
    res = calibrate_bag(bag, settings, tmp_path / 'out')
    rep = res.report
    # 8 dwells; the last pose's second still frame is the same place: merged into its view.
    assert rep['n_samples'] == 8 and rep['samples']['merged'] == 1
    assert rep['front_end']['frames_moving'] == 7
    _check_mount(rep['target']['T_link_target'])
    cam = read_camera_info(str(tmp_path / 'out' / 'cam.yaml'))
    assert abs(cam.fx - K[0, 0]) < 3 and abs(cam.cy - K[1, 2]) < 3


def _board_sample(pose, ref_link):
    ref = ref_link @ pose[:3, :3].T + pose[:3, 3]
    return Sample(point_nominal=ref.mean(axis=0), pose=pose, reference_points=ref,
                  observations={'cam': Observation(np.zeros((3, 2)), [0, 1, 2])})


def test_store_tells_turned_board_views_apart():
    ref = BoardTarget(BOARD.points(), np.eye(4)).reference_points_in_link()
    ref = ref - ref.mean(axis=0)                    # centred: a turn keeps the centre
    store = SampleStore(min_sample_spacing=0.005)
    turned = np.eye(4)
    turned[:3, :3] = Rotation.from_rotvec([0, 0, 0.2]).as_matrix()
    assert store.add(_board_sample(np.eye(4), ref)) is AddResult.ADDED
    assert store.add(_board_sample(turned, ref)) is AddResult.ADDED
    assert store.add(_board_sample(turned, ref)) is AddResult.MERGED
    point = Sample(point_nominal=[1, 0, 0],
                   observations={'cam': Observation(np.zeros((1, 2)), [0])})
    with pytest.raises(ValueError, match='one kind of target'):
        store.add(point)


def test_version_1_store_files_still_load(tmp_path):
    store = SampleStore()
    for k in range(3):
        store.add(Sample(point_nominal=[0.1 * k, 0, 0], q=[k, 0.0],
                         observations={'cam': Observation([[10.0 * k, 5.0]], [0])}))
    store.save(tmp_path)
    path = tmp_path / FILE_NAME
    with np.load(path) as z:
        data = {k: z[k] for k in z.files if k not in ('has_reference', 'reference_points')}
    meta = json.loads(str(data['meta']))
    meta['version'] = 1
    data['meta'] = np.array(json.dumps(meta))
    np.savez_compressed(path, **data)
    back = SampleStore.load(tmp_path)
    assert len(back) == 3 and all(s.reference_points is None for s in back)
    np.testing.assert_allclose(sorted(s.point_nominal[0] for s in back), [0, 0.1, 0.2])
