"""
A folder of captures into a rosbag2 bag: images plus the arm's pose or joint angles per capture.

Layout (README, "Folders of captures")::

    DIR/poses.csv (or ee_poses.csv)   one row per capture, a header naming the columns:
        sample,x,y,z,qx,qy,qz,qw      the marker link's pose in the base frame (m, unit
                                      quaternion), or
        sample,<joint>,<joint>,...    joint angles (rad) by joint name
    DIR/images/<prefix><sample>_<camera>.<jpg|jpeg|png>
                                      one file per capture and camera (s00_cam0.jpg, 3_left.png);
                                      <camera> is the camera's name ([A-Za-z0-9_])
    DIR/camera_info/<camera>.yaml     optional: the camera's intrinsics (camera_info YAML), or
    DIR/intrinsics.json + samples.json
                                      optional: RealSense intrinsics by serial number and the
                                      serial of each image (the layout of facebookresearch/fairo's
                                      eyehandcal data)

The bag replays capture k at k + 1 seconds: the arm's state :data:`POSE_MARGIN_NS` before and
after the images (PoseStamped on ``pose_topic`` or JointState on ``/joint_states``), so that the
front end pairs every image as a still frame and pools each capture as a dwell of its own; the
image files' bytes unchanged as CompressedImage on ``/<camera>/image_raw/compressed``; and
CameraInfo on ``/<camera>/camera_info`` when the intrinsics are known.  Beside the bag's data:
``camera_info/<camera>.yaml`` and ``params.yaml``, the calibrator's parameters that describe
the folder (given intrinsics fixed), to be completed with the marker's.
"""

import csv
import json
import os
import re
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np
import yaml

from armcal_ros.core.camera import Camera
from armcal_ros.core.target import pose_matrix
from armcal_ros.io.bag import BagWriter, POSE_STAMPED
from armcal_ros.io.calib_files import read_camera_info, write_camera_info

#: Captures are replayed one per second, the arm's state given 20 ms either side of the images
#: (well inside the front end's 0.1 s gap limit for pose input and its joint-state gap).
CAPTURE_PERIOD_NS = 1_000_000_000
POSE_MARGIN_NS = 20_000_000
POSE_COLUMNS = ('x', 'y', 'z', 'qx', 'qy', 'qz', 'qw')
IMAGE_RE = re.compile(r'^[A-Za-z]*0*(\d+)_([A-Za-z0-9_]+)\.(jpe?g|png)$', re.IGNORECASE)


class FolderFormatError(ValueError):
    """The folder does not follow the layout; the message names the file and what is wrong."""


@dataclass
class CaptureFolder:
    """What a folder holds: per capture the link pose (4, 4) or joint angles, and the images."""

    root: str
    samples: List[int]
    poses: Optional[np.ndarray] = None             # (S, 4, 4) with pose input
    joint_names: List[str] = field(default_factory=list)
    joints: Optional[np.ndarray] = None            # (S, J) with joint angles
    images: Dict[str, Dict[int, str]] = field(default_factory=dict)   # camera -> sample -> path
    intrinsics: Dict[str, Camera] = field(default_factory=dict)

    @property
    def cameras(self):
        """Return the camera names, sorted."""
        return sorted(self.images)


def capture_stamp(k):
    """Return the stamp (ns) of capture ``k`` in a replayed folder."""
    return (int(k) + 1) * CAPTURE_PERIOD_NS


def _read_table(path):
    try:
        with open(path, newline='') as f:
            rows = list(csv.reader(f))
    except OSError as exc:
        raise FolderFormatError(f'{path}: cannot read: {exc}') from exc
    if len(rows) < 2 or not rows[0] or rows[0][0].strip() != 'sample':
        raise FolderFormatError(f'{path}: expected a header starting with "sample" and one row '
                                'per capture')
    header = [h.strip() for h in rows[0]]
    try:
        samples = [int(r[0]) for r in rows[1:] if r]
        values = np.array([[float(x) for x in r[1:]] for r in rows[1:] if r])
    except ValueError as exc:
        raise FolderFormatError(f'{path}: every cell after the header must be a number '
                                f'({exc})') from exc
    if values.shape[1] != len(header) - 1 or not np.all(np.isfinite(values)):
        raise FolderFormatError(f'{path}: every row needs {len(header) - 1} finite numbers')
    if len(set(samples)) != len(samples):
        raise FolderFormatError(f'{path}: sample numbers repeat')
    return header[1:], samples, values


def _fairo_intrinsics(root, images):
    """Read intrinsics.json + samples.json (RealSense serials) as camera name -> Camera."""
    with open(os.path.join(root, 'intrinsics.json')) as f:
        by_serial = json.load(f)
    with open(os.path.join(root, 'samples.json')) as f:
        samples = json.load(f)
    out = {}
    for s in samples:
        for rel, serial in zip(s.get('images', []), s.get('camera_serials', [])):
            m = IMAGE_RE.match(os.path.basename(rel))
            if m is None or serial not in by_serial or m.group(2) in out:
                continue
            d = by_serial[serial]
            out[m.group(2)] = Camera(m.group(2), int(d['width']), int(d['height']),
                                     float(d['fx']), float(d['fy']), float(d['ppx']),
                                     float(d['ppy']), np.asarray(d['coeffs'], float)[:5])
    return {k: v for k, v in out.items() if k in images}


def read_capture_folder(root) -> CaptureFolder:
    """Read a folder of captures (module docstring); FolderFormatError names what is wrong."""
    table = next((os.path.join(root, n) for n in ('poses.csv', 'ee_poses.csv')
                  if os.path.isfile(os.path.join(root, n))), None)
    if table is None:
        raise FolderFormatError(f'{root}: no poses.csv or ee_poses.csv (one row per capture)')
    columns, samples, values = _read_table(table)
    out = CaptureFolder(os.path.abspath(root), samples)
    if tuple(columns) == POSE_COLUMNS:
        try:
            out.poses = np.array([pose_matrix(v[:3], v[3:]) for v in values])
        except ValueError as exc:
            raise FolderFormatError(f'{table}: {exc}') from exc
    else:
        out.joint_names, out.joints = list(columns), values
    img_dir = os.path.join(root, 'images')
    if not os.path.isdir(img_dir):
        raise FolderFormatError(f'{root}: no images/ folder')
    known = set(samples)
    for name in sorted(os.listdir(img_dir)):
        m = IMAGE_RE.match(name)
        if m is None or int(m.group(1)) not in known:
            continue
        out.images.setdefault(m.group(2), {})[int(m.group(1))] = os.path.join(img_dir, name)
    if not out.images:
        raise FolderFormatError(f'{img_dir}: no image named <prefix><sample>_<camera>.jpg/png '
                                f'for the samples of {os.path.basename(table)}')
    info_dir = os.path.join(root, 'camera_info')
    try:
        if os.path.isdir(info_dir):
            for cam in out.images:
                path = os.path.join(info_dir, f'{cam}.yaml')
                if os.path.isfile(path):
                    out.intrinsics[cam] = read_camera_info(path)
        elif os.path.isfile(os.path.join(root, 'intrinsics.json')):
            out.intrinsics = _fairo_intrinsics(root, out.images)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise FolderFormatError(f'{root}: cannot read the intrinsics: {exc}') from exc
    return out


def write_capture_bag(folder: CaptureFolder, path, pose_topic='/tool_pose',
                      base_frame='base_link', marker_link='tool0', storage='mcap'):
    """
    Write ``folder`` as a rosbag2 bag at ``path`` (must not exist), with its parameter file.

    Returns the path of ``params.yaml`` written beside the bag's data.
    """
    cams = folder.cameras
    with BagWriter(path, storage=storage) as w:
        for k, s in enumerate(folder.samples):
            t = capture_stamp(k)
            for dt in (-POSE_MARGIN_NS, POSE_MARGIN_NS):
                if folder.poses is not None:
                    w.write_pose(pose_topic, POSE_STAMPED, t + dt, folder.poses[k], base_frame,
                                 marker_link)
                else:
                    w.write_joint_state('/joint_states', t + dt, folder.joint_names,
                                        folder.joints[k])
                if dt < 0:
                    for cam in cams:
                        _write_capture_images(w, folder, cam, s, t)
    info_dir = os.path.join(path, 'camera_info')
    os.makedirs(info_dir, exist_ok=True)
    for cam, info in folder.intrinsics.items():
        write_camera_info(os.path.join(info_dir, f'{cam}.yaml'), info, camera_name=cam)
    params = dict(camera_names=cams,
                  image_topics=[f'/{c}/image_raw/compressed' for c in cams],
                  base_frame=base_frame, marker_link=marker_link,
                  min_samples=min(20, len(folder.samples)))
    if folder.poses is not None:
        params.update(pose_topic=pose_topic, pose_type='pose_stamped')
    if folder.intrinsics:
        params.update(intrinsics_mode=['fixed' if c in folder.intrinsics else 'estimate'
                                       for c in cams],
                      intrinsics_files=[f'camera_info/{c}.yaml' if c in folder.intrinsics
                                        else '' for c in cams])
    out = os.path.join(path, 'params.yaml')
    with open(out, 'w') as f:
        f.write(f'# The calibrator parameters that describe {folder.root}\n'
                '# (add the marker: marker_type, marker_offset, and with joint angles the robot '
                'model).\n')
        yaml.safe_dump({'armcal': {'ros__parameters': params}}, f, sort_keys=False)
    return out


def _write_capture_images(w: BagWriter, folder, cam, sample, t):
    path = folder.images[cam].get(sample)
    if path is None:
        return
    with open(path, 'rb') as f:
        data = f.read()
    ext = os.path.splitext(path)[1].lower()
    frame = f'{cam}_optical_frame'
    w.write_encoded_image(f'/{cam}/image_raw/compressed', t, data,
                          'png' if ext == '.png' else 'jpeg', frame)
    info = folder.intrinsics.get(cam)
    if info is not None:
        w.write_camera_info(f'/{cam}/camera_info', t, info.K, info.dist, info.width,
                            info.height, frame)
