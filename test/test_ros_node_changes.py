"""
The live node follows a knocked camera, on real rclpy and DDS.

``knocked_bag``: cam2 knocked by 1 deg and 4 mm half-way through 150 s, replayed at 2 x.  (At
4 x the lamp-lit ball's centre fits, the solves every 2 s and 180 VGA frames a second are more
than two cores carry: the node dropped two thirds of the images and kept too few of cam2's
views after the knock to recalibrate it within the bag.  At 2 x it keeps about 88 %.)

The node must say what happened on /diagnostics, withdraw cam2's calibration while it has too
few new views (an uncalibrated CameraInfo: K zero), and end with cam2's CameraInfo and pose
those of the knocked camera, not the old one; the other cameras keep theirs.
"""

import json

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip('rclpy')

from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402
from sensor_msgs.msg import CameraInfo  # noqa: E402

from armcal_ros.io.calib_files import read_cameras  # noqa: E402
from helpers.ros_nodes import diag_values, replay_and_calibrate, wait_until  # noqa: E402

pytestmark = [pytest.mark.slow, pytest.mark.timeout(400)]

CAMS = ['cam1', 'cam2', 'cam3']
RATE = 2.0
DURATION = 150.0


def test_node_detects_a_knocked_camera_withdraws_and_recalibrates_it(ros_env, client,
                                                                     knocked_bag, tmp_path):
    gt = knocked_bag / 'ground_truth'
    with open(gt / 'params.yaml') as f:
        params = yaml.safe_load(f)
    p = params['armcal']['ros__parameters']
    p.update(output_dir=str(tmp_path / 'out'), solve_period=2.0, noise_model='kinematic',
             resume=False)
    params_file = tmp_path / 'params.yaml'
    params_file.write_text(yaml.safe_dump(params))
    info = {c: client.record(CameraInfo, f'/armcal/{c}/camera_info')[0] for c in CAMS}
    pose = {c: client.record(PoseWithCovarianceStamped, f'/armcal/{c}/pose')[0] for c in CAMS}
    diag, _ = client.record(DiagnosticArray, '/diagnostics', 10)
    procs = []
    try:
        _, t_cal = replay_and_calibrate(client, ros_env, str(params_file), knocked_bag,
                                        tmp_path, DURATION, RATE, procs, diag, info)
        wait_until(lambda: pose['cam2'] and pose['cam2'][-1][0] >= t_cal, 20, 'pose of cam2')
        v = wait_until(lambda: diag_values(diag, 'armcal: cam2', t_cal), 20,
                       'diagnostics of cam2')
        main = diag_values(diag, 'armcal: calibration')
    finally:
        for p_ in procs:
            p_.kill()
    assert 'cam2 changed at' in v['last_change'] and 'recalibrated' in v['last_change'], v
    # The onset against the bag's own clock: the "t = ..." of the summary counts from the
    # first stored sample, which comes later when a loaded machine drops the first dwells.
    with open(tmp_path / 'out' / 'changes.json') as f:
        onset = [r['onset_ns'] for r in json.load(f)['records'] if r['camera'] == 'cam2']
    with open(gt / 'changes.yaml') as f:
        knock = yaml.safe_load(f)[0]['time_ns']
    # Not before the knock (one dwell's margin), and within the first 10 views of cam2 the
    # node stored after it (the change monitor's target).  Counted in the node's own views:
    # a machine too slow for the 4 x replay drops dwells (on a slow machine the onset came
    # 8-34 s after the knock, 5 views after it when the node was alone).
    store = np.load(tmp_path / 'out' / 'samples.npz')
    cam = json.loads(str(store['meta']))['camera_names'].index('cam2')
    obs = np.concatenate([store['obs'], store['retired_obs']])
    views = np.sort(obs[obs[:, 1] == cam, 3])
    after = views[views >= knock - 5_000_000_000]
    assert onset and -5.0 < (onset[0] - knock) * 1e-9, (onset, knock)
    assert len(after) >= 10 and onset[0] <= after[9], (onset, knock, after[:10])
    assert main['changes'] == '1', main
    withdrawn = [m for _, m in info['cam2'] if m.k[0] == 0.0]
    assert withdrawn, 'no uncalibrated CameraInfo while cam2 was being recalibrated'
    final = {c.name: c for c in read_cameras(str(gt))[1]}
    before = {c.name: c for c in read_cameras(str(gt / 'epochs' / 'epoch_0'))[1]}
    q = pose['cam2'][-1][1].pose.pose.orientation
    # The pose is T_base_camera: its rotation is the camera's R^T.
    R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix().T

    def angle(Ra, Rb):
        return np.degrees(np.linalg.norm(Rotation.from_matrix(Ra @ Rb.T).as_rotvec()))

    assert angle(R, final['cam2'].rotation) < 0.4
    assert angle(R, before['cam2'].rotation) > 0.7
    K = np.asarray(info['cam2'][-1][1].k).reshape(3, 3)
    assert abs(K[0, 0] / final['cam2'].fx - 1.0) < 0.01
