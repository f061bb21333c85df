"""A folder of captures through ``armcal import-folder`` and ``armcal calibrate``."""

import argparse
import json
import os
import shutil

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from armcal_ros.cli import main
from armcal_ros.io.calib_files import write_camera_info
from armcal_ros.io.folder_import import POSE_COLUMNS, read_capture_folder
from armcal_ros.offline import run


def import_and_calibrate(folder, tmp_path, **marker):
    """
    Import ``folder`` into a bag, add ``marker`` to its params.yaml, calibrate; the report.

    ``marker`` holds the parameters the folder cannot know (marker type, place, model...);
    a list value is written as a YAML flow list.
    """
    bag = tmp_path / 'bag'
    assert main(['import-folder', str(folder), '--output', str(bag)]) == 0
    with open(bag / 'params.yaml', 'a') as f:
        for k, v in marker.items():
            f.write(f'    {k}: {json.dumps(v) if isinstance(v, list) else v}\n')
    out = tmp_path / 'out'
    assert run(argparse.Namespace(bag=str(bag), params=str(bag / 'params.yaml'),
                                  output=str(out), noise_model=None, quiet=True)) == 0
    return json.loads((out / 'report.json').read_text())


#: The real Franka set, committed (test/data/fairo_franka_3cam/README.md).
FRANKA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'data',
                      'fairo_franka_3cam')


def write_mixed_cell_folder(root):
    """
    Write one capture folder of a cell with static cameras and a wrist camera; return its path.

    The real Franka world-camera captures (cam0-cam2, tag id 0 on the gripper) as captures
    0-19, then the wrist camera's (renamed ``wrist``, tag id 1 on the table) as 20-39: one
    recording of both kinds of camera, as a cell with both records it.
    """
    root = str(root)
    os.makedirs(os.path.join(root, 'images'))
    os.makedirs(os.path.join(root, 'camera_info'))
    rows = ['sample,' + ','.join(POSE_COLUMNS)]
    for first, src, rename in ((0, 'caldata_world_cam', {}),
                               (20, 'caldata_wrist_cam', {'cam0': 'wrist'})):
        f = read_capture_folder(os.path.join(FRANKA, src))
        for k, s in enumerate(f.samples):
            T = f.poses[k]
            x = np.concatenate([T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()])
            rows.append(f'{first + k},' + ','.join(f'{v:.9f}' for v in x))
            for cam, files in f.images.items():
                if s in files:
                    shutil.copy(files[s], os.path.join(
                        root, 'images', f's{first + k:02d}_{rename.get(cam, cam)}.jpg'))
        for cam, c in f.intrinsics.items():
            write_camera_info(os.path.join(root, 'camera_info', f'{rename.get(cam, cam)}.yaml'), c)
    with open(os.path.join(root, 'poses.csv'), 'w') as f:
        f.write('\n'.join(rows) + '\n')
    return root


def write_group_params(bag, **extra):
    """
    Write the two calibrators' parameter files of :func:`write_mixed_cell_folder`'s bag.

    ``static.yaml`` (section ``armcal``): cam0-cam2 and the tag on the gripper, its place
    guessed 5 cm off per axis; ``hand.yaml`` (section ``/**``, read by a node of any name):
    the wrist camera on the flange (eye_in_hand) and the tag on the table, guessed half a
    metre in front of the robot.  Both from the import's params.yaml plus ``extra``.
    Returns {'static': path, 'hand': path}.
    """
    bag = str(bag)
    with open(os.path.join(bag, 'params.yaml')) as f:
        base = yaml.safe_load(f)['armcal']['ros__parameters']
    out = {}
    for name, key, cams, marker in (
            ('static', 'armcal', ['cam0', 'cam1', 'cam2'],
             dict(aruco_id=0, marker_offset=[0.05, 0.05, -0.05])),
            ('hand', '/**', ['wrist'],
             dict(aruco_id=1, marker_offset=[0.5, 0.0, 0.0], eye_in_hand=True))):
        p = dict(base, camera_names=cams,
                 image_topics=[f'/{c}/image_raw/compressed' for c in cams],
                 intrinsics_mode=['fixed'],
                 intrinsics_files=[f'camera_info/{c}.yaml' for c in cams],
                 marker_type='aruco', aruco_dictionary='DICT_4X4_50',
                 estimate_marker_offset=True, noise_model='fixed', free_distortion=[],
                 min_samples=8, **marker)
        p.update(extra)
        out[name] = os.path.join(bag, f'{name}.yaml')
        with open(out[name], 'w') as f:
            yaml.safe_dump({key: {'ros__parameters': p}}, f)
    return out
