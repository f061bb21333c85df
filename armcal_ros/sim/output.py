"""
Write a simulated cell (:class:`~armcal_ros.sim.cell.SimResult`) to a rosbag2 bag with its truth.

Topics: ``/joint_states`` (sensor_msgs/JointState) and, per camera, ``/<cam>/image_raw``
(sensor_msgs/Image) or ``/<cam>/image_raw/compressed`` (sensor_msgs/CompressedImage, png or
jpeg), frame_id ``<cam>_optical_frame`` (or as ``frame_id_format`` says); messages in bag-time
(receive) order.  Optionally a pose topic (geometry_msgs/PoseStamped or TransformStamped, frame
``base_frame``) with the marker link's pose at every joint state, as a robot controller
reports it: forward kinematics of the nominal model at the joint readings (so it carries the
same bias as the joint states).

Ground truth goes to ``<bag>/ground_truth/`` (inside the bag directory, beside the storage
file, so it travels with the bag; rosbag2 readers ignore it):

- ``<cam>.yaml`` and ``extrinsics.yaml``: the true cameras at the end of the session (the
  calibrator's output formats, :mod:`armcal_ros.io.calib_files`);
- only when cameras change during the session (:class:`~armcal_ros.sim.cell.CameraChange`):
  ``epochs/epoch_<k>/`` the same files for each state k = 0, 1, ... of the camera set (0 the
  start), and ``changes.yaml``, per change in time order: camera, time_ns (bag time), time_s,
  rotation_deg, translation_mm, focal_percent, epoch (the state it starts), rotation_axis and
  translation_direction (unit vectors, base frame);
- ``markers.npz``: per dwell ``dwell_start_ns``, ``dwell_end_ns``, ``dwell_stamp_ns`` (middle),
  ``dwell_q`` (D, n) in ``joint_names`` order, ``dwell_true`` and ``dwell_nominal`` (D, 3) marker
  positions in the base frame (m); per frame ``frame_camera`` (index into ``camera_names``),
  ``frame_stamp_ns`` (header), ``frame_exposure_ns`` (true mid-exposure), ``frame_uv`` (true
  projection of the marker centre, px), ``frame_marker`` (true position), ``frame_occlusion``
  (0 visible, 1 hidden by a link, 2 random occlusion, 3 outside the image); and
  ``joint_names``, ``camera_names``;
- ``robot_errors.yaml``: the true robot's error parameters;
- ``scenario.yaml``: scenario, seed, settings, topics and what the files mean.
"""

import os
from pathlib import Path

import numpy as np
import yaml

from armcal_ros.io.bag import (BagWriter, COMPRESSED_FORMATS, IMAGE_ENCODINGS, POSE_STAMPED,
                               TRANSFORM_STAMPED)
from armcal_ros.io.calib_files import atomic_write_text, write_cameras

POSE_MSG_TYPES = {'pose_stamped': POSE_STAMPED, 'transform_stamped': TRANSFORM_STAMPED}


def image_topic(camera_name, compressed=None):
    """Topic of a camera's images: /<cam>/image_raw or /<cam>/image_raw/compressed."""
    return f'/{camera_name}/image_raw' + ('/compressed' if compressed else '')


def write_ground_truth(result, directory, topics=None):
    """Write the ground-truth files of ``result`` into ``directory`` (created)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    base = result.settings.base_frame
    write_cameras(directory, result.final_cameras, base)
    if result.change_log:
        for k, (_, cams) in enumerate(result.camera_set_epochs):
            epoch_dir = directory / 'epochs' / f'epoch_{k}'
            epoch_dir.mkdir(parents=True, exist_ok=True)
            write_cameras(epoch_dir, cams, base)
        atomic_write_text(directory / 'changes.yaml',
                          yaml.safe_dump(result.change_log, sort_keys=False))
    d, f = result.dwells, result.frames
    tmp = directory / '.markers.tmp.npz'
    np.savez_compressed(
        tmp, dwell_start_ns=d.start_ns, dwell_end_ns=d.end_ns, dwell_stamp_ns=d.stamp_ns,
        dwell_q=d.q, dwell_true=d.true_marker, dwell_nominal=d.nominal_marker,
        frame_camera=f.camera, frame_stamp_ns=f.stamp_ns, frame_exposure_ns=f.exposure_ns,
        frame_uv=f.uv, frame_marker=f.marker, frame_occlusion=f.occlusion,
        joint_names=np.array(result.chain.joint_names),
        camera_names=np.array([c.name for c in result.cameras]))
    os.replace(tmp, directory / 'markers.npz')
    atomic_write_text(directory / 'robot_errors.yaml',
                      yaml.safe_dump(result.robot.describe(), sort_keys=False))
    bias = d.nominal_marker - d.true_marker
    doc = {
        'scenario': result.scenario,
        'seed': result.seed,
        'start_time_ns': int(result.start_ns),
        'base_frame': result.settings.base_frame,
        'marker_link': result.settings.marker_link,
        'joint_names': list(result.chain.joint_names),
        'published_joint_names': list(result.joint_names),
        'camera_names': [c.name for c in result.cameras],
        'topics': topics or {},
        'dwells': len(d),
        'frames': len(f),
        'visible_frames': int(np.count_nonzero(f.visible)),
        'bias_rms_mm': float(1e3 * np.sqrt(np.mean(np.sum(bias ** 2, axis=1))))
        if len(d) else None,
        'settings': result.settings.to_dict(),
    }
    atomic_write_text(directory / 'scenario.yaml', yaml.safe_dump(doc, sort_keys=False))


def link_poses(result):
    """Return the marker link's nominal pose (N, 4, 4) at every joint state of ``result``."""
    chain = result.chain
    q = np.asarray(result.joint_positions)[:, chain.index_map(result.joint_names)]
    return chain.fk_pose(q)


def write_sim_bag(result, path, storage='mcap', compressed=None, encoding='mono8',
                  compress=True, ground_truth=True, jpeg_quality=90, progress=None,
                  pose_topic=None, pose_type='pose_stamped',
                  frame_id_format='{camera}_optical_frame'):
    """
    Write ``result`` to the rosbag2 bag directory ``path`` (must not exist).

    ``compressed`` is None (raw sensor_msgs/Image), ``'png'`` or ``'jpeg'``; ``encoding`` is
    mono8, rgb8 or bgr8; ``compress`` turns on zstd chunk compression (mcap only).
    ``pose_topic`` (e.g. ``/tool_pose``) adds the marker link's pose at every joint state as
    ``pose_type`` ``'pose_stamped'`` or ``'transform_stamped'`` (module docstring).
    ``frame_id_format`` names each camera's images' frame (``{camera}`` is its name), e.g.
    ``'{camera}_color_optical_frame'`` as a RealSense driver would.
    ``progress(i, n)`` is called now and then.  Returns {topic: message count}.
    """
    if '{camera}' not in frame_id_format:
        raise ValueError(f'frame_id_format must contain {{camera}}, got {frame_id_format!r}')
    if pose_type not in POSE_MSG_TYPES:
        raise ValueError(f'pose_type must be one of {sorted(POSE_MSG_TYPES)}, got {pose_type!r}')
    if compressed is not None and compressed not in COMPRESSED_FORMATS:
        raise ValueError(f'compressed must be None or one of {COMPRESSED_FORMATS}, '
                         f'got {compressed!r}')
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f'encoding must be one of {IMAGE_ENCODINGS}, got {encoding!r}')
    path = Path(path)
    js_topic = '/joint_states'
    cam_topics = [image_topic(c.name, compressed) for c in result.cameras]
    frames = result.frames
    js_log = result.joint_stamps_ns + 500_000      # 0.5 ms from the controller to the bag
    # merge the streams in receive order (events: 0 joint state, 1 image, 2 pose)
    n_pose = len(js_log) if pose_topic else 0
    events = np.concatenate([np.zeros(len(js_log), np.int64), np.ones(len(frames), np.int64),
                             np.full(n_pose, 2, np.int64)])
    index = np.concatenate([np.arange(len(js_log)), np.arange(len(frames)), np.arange(n_pose)])
    times = np.concatenate([js_log, frames.log_ns, js_log[:n_pose]])
    order = np.lexsort((events, times))
    total = len(order)
    poses = link_poses(result) if pose_topic else None
    pose_msgtype = POSE_MSG_TYPES[pose_type]
    base, link = result.settings.base_frame, result.settings.marker_link
    with BagWriter(path, storage=storage, compress=compress) as w:
        w.connection(js_topic, 'sensor_msgs/msg/JointState')
        for t in cam_topics:
            w.connection(t, 'sensor_msgs/msg/CompressedImage' if compressed
                         else 'sensor_msgs/msg/Image')
        if pose_topic:
            w.connection(pose_topic, pose_msgtype)
        for k, o in enumerate(order):
            i = int(index[o])
            if events[o] == 2:
                w.write_pose(pose_topic, pose_msgtype, int(result.joint_stamps_ns[i]),
                             poses[i], base, link, log_ns=int(js_log[i]))
            elif events[o] == 0:
                w.write_joint_state(js_topic, int(result.joint_stamps_ns[i]), result.joint_names,
                                    result.joint_positions[i], result.joint_velocities[i],
                                    log_ns=int(js_log[i]))
            else:
                j = int(frames.camera[i])
                cam = result.cameras[j]
                img = result.render(i, encoding)
                frame_id = frame_id_format.format(camera=cam.name)
                if compressed:
                    w.write_compressed_image(cam_topics[j], int(frames.stamp_ns[i]), img,
                                             compressed, encoding, frame_id,
                                             log_ns=int(frames.log_ns[i]),
                                             jpeg_quality=jpeg_quality)
                else:
                    w.write_image(cam_topics[j], int(frames.stamp_ns[i]), img, encoding,
                                  frame_id, log_ns=int(frames.log_ns[i]))
            if progress is not None and k % 2000 == 0:
                progress(k, total)
        counts = dict(w.counts)
    if ground_truth:
        topics = {'joint_states': js_topic,
                  'images': {c.name: t for c, t in zip(result.cameras, cam_topics)}}
        if pose_topic:
            topics['pose'] = {'topic': pose_topic, 'type': pose_msgtype}
        write_ground_truth(result, path / 'ground_truth', topics)
    return counts


def read_ground_truth(directory):
    """
    Load a ground-truth directory into one dictionary.

    The arrays of markers.npz, ``scenario`` (scenario.yaml) and ``changes`` (changes.yaml, []
    when the cameras did not change).
    """
    directory = Path(directory)
    with np.load(directory / 'markers.npz') as z:
        out = {k: z[k] for k in z.files}
    with open(directory / 'scenario.yaml', encoding='utf-8') as f:
        out['scenario'] = yaml.safe_load(f)
    out['changes'] = []
    if (directory / 'changes.yaml').exists():
        with open(directory / 'changes.yaml', encoding='utf-8') as f:
            out['changes'] = yaml.safe_load(f) or []
    return out
