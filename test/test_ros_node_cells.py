"""
The node on a cell unlike the demo's, on real rclpy and DDS: a UR5 with two colour cameras.

``armcal simulate --cell ur5-2cam`` writes a bag of a UR5 (ur_description's link and joint
names, joints published shuffled with an extra gripper joint) watched by cameras ``left`` and
``right`` publishing sensor_msgs/CompressedImage (JPEG, rgb8); the node, started with the
parameter file the simulator wrote for the cell (nothing else but the output directory, the
solve period and the noise model), must subscribe to the compressed topics, pair the shuffled
joints by name, and publish CameraInfo and poses for exactly those two cameras close to the
truth (focal within 3 %, camera centre within 40 mm: test_offline.py's tolerances).  The
``right`` camera's driver stamps its images 50 ms late: the node times each camera from the
frames in motion and reports it on /diagnostics, within 5 ms of the simulator's truth (the
target of ``armcal calibrate``'s measurement, which the node shares).
Helpers, QoS and the process hygiene: helpers/ros_nodes.py and conftest.py.
"""

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from sensor_msgs.msg import CameraInfo  # noqa: E402

from armcal_ros.io.calib_files import read_cameras  # noqa: E402
from armcal_ros.sim.cells import CELLS  # noqa: E402
from helpers.ros_nodes import (check_camera_info, diag_values,  # noqa: E402
                               replay_and_calibrate, wait_until)

pytestmark = [pytest.mark.slow, pytest.mark.timeout(300)]

CELL = 'ur5-2cam'
CAMS = list(CELLS[CELL].sim_settings().camera_names)
RATE = 2.0
DURATION = 45.0


@pytest.fixture(scope='module')
def ur5_bag(tmp_path_factory):
    from armcal_ros.cli import main
    bag = tmp_path_factory.mktemp('ur5') / 'bag'
    assert main(['simulate', '--cell', CELL, '--output', str(bag), '--duration', str(DURATION),
                 '--seed', '2', '--no-zstd', '--quiet', '--stamp-latency', 'right:0.05']) == 0
    return bag


def test_node_calibrates_a_ur5_with_two_compressed_colour_cameras(ros_env, client, ur5_bag,
                                                                  tmp_path):
    with open(ur5_bag / 'ground_truth' / 'params.yaml') as f:
        params = yaml.safe_load(f)
    p = params['armcal']['ros__parameters']
    assert all(t.endswith('/compressed') for t in p['image_topics'])
    p.update(output_dir=str(tmp_path / 'out'), solve_period=2.0, min_samples=12,
             noise_model='kinematic', resume=False)
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(yaml.safe_dump(params))
    info = {c: client.record(CameraInfo, f'/armcal/{c}/camera_info')[0] for c in CAMS}
    pose = {c: client.record(PoseWithCovarianceStamped, f'/armcal/{c}/pose')[0] for c in CAMS}
    diag, _ = client.record(DiagnosticArray, '/diagnostics', 10)
    procs = []
    try:
        _, t_cal = replay_and_calibrate(client, ros_env, str(params_file), ur5_bag, tmp_path,
                                        DURATION, RATE, procs, diag, info)
        for c in CAMS:
            wait_until(lambda: pose[c] and pose[c][-1][0] >= t_cal, 20, f'pose of {c}')
        final = diag_values(diag, 'armcal: calibration')
        latency = {}
        for c in CAMS:
            v = wait_until(lambda: diag_values(diag, f'armcal: {c}', t_cal), 20,
                           f'diagnostics of {c}')
            assert v['image_size'] == '640x480', v          # decoded from JPEG
            latency[c] = wait_until(lambda: (diag_values(diag, f'armcal: {c}') or {}).get(
                'stamp_latency_ms'), 30, f'stamp latency of {c}')
    finally:
        for p_ in procs:
            p_.kill()
    assert int(final['samples']) >= 12, final
    marks = np.load(ur5_bag / 'ground_truth' / 'markers.npz')
    for j, c in enumerate(str(n) for n in marks['camera_names']):
        m = marks['frame_camera'] == j
        expected_ms = np.median(marks['frame_stamp_ns'][m] - marks['frame_exposure_ns'][m]) / 1e6
        assert abs(float(latency[c]) - expected_ms) < 5.0, (c, latency[c], expected_ms)
    assert all(int(final[f'samples_{c}']) > 0 for c in CAMS), final
    truth = {c.name: c for c in read_cameras(str(ur5_bag / 'ground_truth'))[1]}
    assert sorted(truth) == sorted(CAMS)
    check_camera_info(info, truth, CAMS)
    for c in CAMS:
        p_ = pose[c][-1][1].pose.pose.position
        centre = np.array([p_.x, p_.y, p_.z])
        assert np.linalg.norm(centre - truth[c].center) < 0.040, (c, centre, truth[c].center)
