"""
The board scene of the ChArUco tests: a board on a robot link in front of one static camera.

The camera (800 x 600 px, pinhole ``K``) is at ``T_CAM_BASE`` (camera from base); the board
``BOARD`` (7 x 5 squares of 40 mm, DICT_6X6_250) is mounted on the link at ``MOUNT``
(T_link_target).  :func:`view_targets` draws board poses 0.65-0.8 m in front of the camera,
tilted up to 0.5 rad; from them :func:`view_poses` gives the link poses, :func:`write_folder` a
robot_cal_tools folder, :func:`write_pose_bag` a bag with a PoseStamped link pose, and
:func:`write_joint_bag` a bag of a Cartesian robot with a roll-pitch-yaw wrist (three prismatic
joints, three revolute ones: its inverse kinematics is exact and trivial) carrying the board
through the same views.  :func:`params` writes a parameter file for this camera and board.
"""

import os

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from armcal_ros.core.camera import Camera
from armcal_ros.core.target import invert, pose_vector
from armcal_ros.frontend.detectors import CharucoBoard
from armcal_ros.io.bag import BagWriter
from armcal_ros.io.calib_files import write_camera_info
from armcal_ros.robot.kinematics import KinematicChain
from helpers.params_files import write_params


def transform(rotvec, t):
    """Return the 4x4 rigid transform of rotation vector ``rotvec`` and translation ``t``."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


W, H = 800, 600
K = np.array([[700.0, 0, 399.5], [0, 705.0, 299.5], [0, 0, 1]])
BOARD_SIZE = dict(charuco_rows=7, charuco_cols=5, charuco_square_size=0.04,
                  charuco_marker_size=0.02)
BOARD = CharucoBoard(7, 5, 0.04, 0.02, 'DICT_6X6_250')
MOUNT = transform([0.2, -1.9, 0.3], [0.03, 0.08, 0.15])
T_CAM_BASE = transform([2.0, 0.3, -0.2], [0.1, -0.2, 1.4])
POSE = 'geometry_msgs/msg/PoseStamped'

CARTESIAN_URDF = '''<robot name="cartesian">
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


def render_board(board, R, t, K, size, pps, margin, blur=0.7, noise=1.5, seed=0):
    """Render ``board`` (opencv orientation) seen by pinhole ``K`` at camera-from-board (R, t)."""
    tex = board.render(pps, margin)
    s = board.square_size / pps
    # Texture pixel (centre convention) -> board-plane metres.
    S = np.array([[s, 0, -(margin - 0.5) * s], [0, s, -(margin - 0.5) * s], [0, 0, 1]])
    Hm = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ S
    img = cv2.warpPerspective(tex, Hm, size, flags=cv2.INTER_LINEAR, borderValue=128)
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), blur)
    img += np.random.default_rng(seed).normal(0, noise, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def render(T_ct, pps=50, margin=25):
    """Render the scene's board at camera-from-target pose T_ct (light blur and noise)."""
    return render_board(BOARD, T_ct[:3, :3], T_ct[:3, 3], K, (W, H), pps, margin)


def view_targets(n_views, seed=0):
    """Camera-from-target poses: the board 0.65-0.8 m in front of the camera, tilted <= 0.5 rad."""
    rng = np.random.default_rng(seed)
    centre = np.array([2.5 * 0.04, 3.5 * 0.04, 0.0])
    out = []
    for _ in range(n_views):
        R = Rotation.from_rotvec(rng.uniform(-0.5, 0.5, 3)).as_matrix()
        T_ct = np.eye(4)
        T_ct[:3, :3] = R
        T_ct[:3, 3] = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.04, 0.04),
                                rng.uniform(0.65, 0.8)]) - R @ centre
        out.append(T_ct)
    return out


def link_pose(T_ct):
    """Return the link pose (in the base frame) that shows the board at camera pose ``T_ct``."""
    return invert(T_CAM_BASE) @ T_ct @ invert(MOUNT)


def view_poses(n_views, seed=0):
    """Link poses of :func:`view_targets`."""
    return [link_pose(T_ct) for T_ct in view_targets(n_views, seed)]


def write_folder(root, n_views=8, seed=0):
    """Write a robot_cal_tools folder: images, link poses, cal_data.yaml and target.yaml."""
    os.makedirs(os.path.join(root, 'images'))
    os.makedirs(os.path.join(root, 'poses'))
    entries = []
    for v, T_ct in enumerate(view_targets(n_views, seed)):
        cv2.imwrite(os.path.join(root, 'images', f'{v}.png'), render(T_ct))
        x, y, z, qx, qy, qz, qw = (float(a) for a in pose_vector(link_pose(T_ct)))
        with open(os.path.join(root, 'poses', f'{v}.yaml'), 'w') as f:
            yaml.safe_dump(dict(x=x, y=y, z=z, qx=qx, qy=qy, qz=qz, qw=qw), f)
        entries.append(dict(image=f'images/{v}.png', pose=f'poses/{v}.yaml'))
    with open(os.path.join(root, 'cal_data.yaml'), 'w') as f:
        yaml.safe_dump(entries, f)
    with open(os.path.join(root, 'target.yaml'), 'w') as f:
        yaml.safe_dump(dict(target_finder=dict(
            type='rct_ros_tools::CharucoGridTargetFinderPlugin', rows=7, cols=5,
            chessboard_dim=0.04, aruco_marker_dim=0.02, dictionary=10)), f)


def write_pose_bag(path, n_views=8, seed=0):
    """
    Write a bag of link poses on /tool_pose (50 Hz) and images on /cam/image_raw.

    Per view a 1 s dwell, then 0.4 s of motion towards the next pose; one image while still and
    one while moving.
    """
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


def ik(T):
    """Joint angles of the Cartesian robot for the link pose T: T(x, y, z) Rz Ry Rx."""
    return np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_euler('ZYX')])


def cartesian_chain():
    """Build the Cartesian robot's chain, base_link to tool0; check :func:`ik` against it."""
    chain = KinematicChain.from_urdf(CARTESIAN_URDF, 'base_link', 'tool0')
    for T in view_poses(3):
        np.testing.assert_allclose(chain.fk_pose(ik(T))[0], T, atol=1e-12)
    return chain


def write_joint_bag(path, n_views=8):
    """Joint states at 100 Hz (dwell 1 s, move 0.5 s per view) and 10 Hz rendered images."""
    chain = cartesian_chain()
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


def params(path, **extra):
    """Write the parameters of the scene's camera ``cam`` and a ChArUco target; the path."""
    return write_params(path, dict(
        camera_names=['cam'], image_topics=['/cam/image_raw'], marker_type='charuco',
        estimate_marker_offset=True, noise_model='fixed', free_distortion=[], min_samples=3),
        **extra)


def joint_params(path, joint_bag, **extra):
    """:func:`params` for the Cartesian robot's bag folder (robot.urdf beside the bag)."""
    return params(path, robot_description_file=str(joint_bag / 'robot.urdf'),
                  marker_link='tool0', **BOARD_SIZE, min_samples=5, **extra)


def check_mount(T_vec, tol_m=2e-3, tol_deg=0.3):
    """Assert that ``T_vec`` (x, y, z, qx, qy, qz, qw) is ``MOUNT`` within the tolerances."""
    assert np.linalg.norm(np.asarray(T_vec[:3]) - MOUNT[:3, 3]) < tol_m
    dR = Rotation.from_quat(T_vec[3:]).as_matrix().T @ MOUNT[:3, :3]
    assert np.degrees(Rotation.from_matrix(dR).magnitude()) < tol_deg


def write_capture_folder(root, n=8, link_of=link_pose):
    """
    Write the scene as a capture folder: poses.csv, images/sNN_cam.png, camera_info.

    ``link_of(T_ct)`` is the link pose that shows the board at camera-from-target ``T_ct``
    (default: the static camera and the board on the link).
    """
    os.makedirs(os.path.join(root, 'images'))
    os.makedirs(os.path.join(root, 'camera_info'))
    rows = ['sample,x,y,z,qx,qy,qz,qw']
    for k, T_ct in enumerate(view_targets(n)):
        cv2.imwrite(os.path.join(root, 'images', f's{k:02d}_cam.png'), render(T_ct))
        rows.append(f'{k},' + ','.join(f'{v:.10f}' for v in pose_vector(link_of(T_ct))))
    with open(os.path.join(root, 'poses.csv'), 'w') as f:
        f.write('\n'.join(rows) + '\n')
    write_camera_info(os.path.join(root, 'camera_info', 'cam.yaml'),
                      Camera('cam', W, H, K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
