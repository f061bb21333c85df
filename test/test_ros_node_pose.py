"""
The node with pose input on real rclpy and DDS: a replayed sphere bag with a PoseStamped topic.

A 30 s simulated bag carrying the marker link's pose (and the joint states, which a pose-input
node does not subscribe to) is replayed at 2x into ``calibrator_node`` started without any robot
model; ``~/calibrate`` at the end must give CameraInfo for every camera close to the truth.  A
pose-input node refuses the models that need joint angles at start-up, with the reason.
Helpers, QoS and the process hygiene: helpers/ros_nodes.py and conftest.py.
"""

import os

import numpy as np
import pytest

rclpy = pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from sensor_msgs.msg import CameraInfo  # noqa: E402

from armcal_ros.io.calib_files import read_cameras  # noqa: E402
from helpers.board_scene import BOARD_SIZE, params as board_params  # noqa: E402
from helpers.params_files import write_params  # noqa: E402
from helpers.ros_nodes import (check_camera_info, refused_start,  # noqa: E402
                               replay_and_calibrate, write_sim_bag_with_short_dwells)

pytestmark = [pytest.mark.slow, pytest.mark.timeout(240)]

CAMS = ['cam1', 'cam2', 'cam3']
POSE_TOPIC = '/tool_pose'
RATE = 2.0
DURATION = 30.0
NODE_PARAMS = dict(marker_link='marker', marker_offset=[0.0, 0.0, 0.0], solve_period=2.0,
                   min_samples=12, pose_topic=POSE_TOPIC, pose_type='pose_stamped',
                   noise_model='correlated', resume=False)


@pytest.fixture(scope='module')
def pose_sim(tmp_path_factory):
    return write_sim_bag_with_short_dwells(tmp_path_factory.mktemp('posesim') / 'bag', DURATION,
                                           pose_topic=POSE_TOPIC, pose_type='pose_stamped')


def test_pose_input_replay_gives_camera_info(ros_env, client, pose_sim, tmp_path):
    out = tmp_path / 'out'
    params = write_params(tmp_path / 'params.yaml', NODE_PARAMS, output_dir=str(out))
    info = {c: client.record(CameraInfo, f'/armcal/{c}/camera_info')[0] for c in CAMS}
    diag, _ = client.record(DiagnosticArray, '/diagnostics', 10)
    procs = []
    try:
        node, _ = replay_and_calibrate(client, ros_env, params, pose_sim, tmp_path, DURATION,
                                       RATE, procs, diag, info)
        log = node.log()
        assert 'pose' in log and POSE_TOPIC in log, log
    finally:
        for p in procs:
            p.kill()
    truth = {c.name: c for c in read_cameras(str(pose_sim / 'ground_truth'))[1]}
    check_camera_info(info, truth, CAMS)
    assert os.path.exists(out / 'extrinsics.yaml')


def test_pose_input_node_refuses_models_needing_joint_angles(ros_env, tmp_path):
    params = write_params(tmp_path / 'bad.yaml', NODE_PARAMS, output_dir=str(tmp_path / 'out'),
                          noise_model='kinematic')
    log = refused_start(ros_env, params, tmp_path / 'node.log')
    assert 'noise_model and pose_topic' in log, log


def test_board_with_pose_input_live_equals_offline(ros_env, client, board_pose_bag, tmp_path):
    """
    Give the same samples and calibration live and offline for a pose-input ChArUco bag.

    The node and ``armcal calibrate`` share one pipeline (compose.build_pipeline).
    """
    import json

    from armcal_ros.frontend.store import SampleStore
    from armcal_ros.offline import calibrate_bag
    from armcal_ros.settings import load_settings
    bag = board_pose_bag
    params = board_params(tmp_path / 'board.yaml', pose_topic='/tool_pose',
                          pose_type='pose_stamped', **BOARD_SIZE, solve_period=1.0,
                          resume=False, output_dir=str(tmp_path / 'live'))
    offline = calibrate_bag(bag, load_settings(params), str(tmp_path / 'offline'),
                            latency=False)
    info = {'cam': client.record(CameraInfo, '/armcal/cam/camera_info')[0]}
    diag, _ = client.record(DiagnosticArray, '/diagnostics', 10)
    procs = []
    try:
        # Every dwell must reach the node: the replay waits until the node has matched.
        replay_and_calibrate(client, ros_env, params, bag, tmp_path, 12.0, 1.0, procs, diag,
                             info)
    finally:
        for p in procs:
            p.kill()
    live = SampleStore.load(str(tmp_path / 'live'))
    off = SampleStore.load(str(tmp_path / 'offline'))
    assert len(live) == len(off) == offline.report['n_samples'] == 8

    def views(store):
        return sorted((s.stamp_ns, s.observations['cam'].ids.tolist(),
                       s.observations['cam'].uv.round(9).tolist(), s.pose.round(12).tolist())
                      for s in store.samples)
    assert views(live) == views(off)
    with open(tmp_path / 'live' / 'calibration.json') as f:
        a = json.load(f)['cameras']['cam']
    b = offline.report['cameras']['cam']
    # `free_distortion: []` in the file reaches the node as an empty list (rcl reads it as a
    # parameter without a type), not as the default k1, k2, p1, p2.
    assert a['dist'] == b['dist'] == [0.0] * 5
    for k in ('fx', 'fy', 'cx', 'cy'):
        assert abs(a[k] - b[k]) < 1e-3, (k, a[k], b[k])
    np.testing.assert_allclose(a['translation'], b['translation'], atol=1e-6)
    with open(tmp_path / 'live' / 'target.yaml') as f:
        import yaml
        mount = yaml.safe_load(f)
    np.testing.assert_allclose(mount['translation'],
                               offline.report['target']['T_link_target'][:3], atol=1e-6)


def test_given_intrinsics_from_the_drivers_camera_info(ros_env, client, tmp_path):
    """Hold the intrinsics the driver's CameraInfo gives (intrinsics_mode fixed, no file)."""
    from helpers.board_scene import K, write_capture_folder
    from armcal_ros.cli import main
    folder = tmp_path / 'captures'
    write_capture_folder(str(folder))
    bag = tmp_path / 'bag'
    assert main(['import-folder', str(folder), '--output', str(bag)]) == 0
    params = board_params(tmp_path / 'p.yaml', pose_topic='/tool_pose', **BOARD_SIZE,
                          image_topics=['/cam/image_raw/compressed'], intrinsics_mode=['fixed'],
                          solve_period=1.0, resume=False, output_dir=str(tmp_path / 'live'))
    info = {'cam': client.record(CameraInfo, '/armcal/cam/camera_info')[0]}
    diag, _ = client.record(DiagnosticArray, '/diagnostics', 10)
    procs = []
    try:
        node, _ = replay_and_calibrate(client, ros_env, params, bag, tmp_path, 9.0, 1.0, procs,
                                       diag, info)
        log = node.log()
    finally:
        for p in procs:
            p.kill()
    assert 'intrinsics given by CameraInfo on /cam/camera_info (fixed' in log, log
    k = np.asarray(info['cam'][-1][1].k).reshape(3, 3)
    np.testing.assert_allclose(k, K, atol=1e-3)
