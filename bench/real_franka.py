"""
Real data: a Franka Panda, three static RealSense cameras, an ArUco tag on the gripper.

The fairo eyehandcal set (``test/data/fairo_franka_3cam``, see its README.md): 20 flange
poses, an image per camera at each, the driver's factory intrinsics (rectified images, zero
distortion).  The tag's centre is detected (the detector of ``marker_type: aruco``); the tag's
side and its place on the flange are not recorded.

- ``armcal``: the user's route, ``armcal import-folder`` then ``armcal calibrate`` with the
  intrinsics fixed, one marker point for all cameras estimated from a guess (the flange's
  x/y/z a few centimetres off), the ``fixed`` noise model.
- ``per camera``: the original tool's model on the same observations - each camera solved on
  its own with its own marker point (and the same intrinsics, solver and start).
- the original tool's published result (``reference/calibration.json``): not ground truth.

Leave-one-pose-out: both models are fitted without one pose and predict its tag centre in
every camera that saw it (the error a new pose would see).

Run by ``bench/real_data.py`` beside the robot_cal_tools set (one run, both sections), or
alone: python bench/real_franka.py [--data DIR].  Prints the tables, writes
docs/bench/real_franka.json and the real_franka section of docs/BENCHMARKS.md.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np
import yaml
from scipy.spatial.transform import Rotation

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from armcal_ros.core.adjustment import SolverSettings  # noqa: E402
from armcal_ros.core.board_calibration import (BoardData, calibrate_board,  # noqa: E402
                                               CameraSpec, MountSettings)
from armcal_ros.core.intrinsics_prior import IntrinsicsPrior  # noqa: E402
from armcal_ros.core.priors import PriorSettings  # noqa: E402
from armcal_ros.frontend.detectors import ArucoDetector, tag_corner_points  # noqa: E402
from armcal_ros.io.folder_import import read_capture_folder  # noqa: E402

from _report import machine, table, write_json, write_section  # noqa: E402

DEFAULT_DATA = os.path.join(ROOT, 'test', 'data', 'fairo_franka_3cam')
#: The marker's place guessed from a look at the gripper: on the flange's far side, 5 cm out.
GUESS = (0.05, 0.05, -0.05)
#: The tag's side guessed (m): a hand-sized tag; the fit estimates it.
SIZE_GUESS = 0.05
#: The wrist set's static tag, guessed on the table half a metre in front of the robot.
WRIST_GUESS = (0.5, 0.0, 0.0)


def cli_calibrate(folder, tag_id, guess, eye_in_hand=False):
    """
    Run the user's route: ``armcal import-folder``, the marker added, ``armcal calibrate``.

    Returns (report.json, extrinsics.yaml) as dictionaries.
    """
    tmp = tempfile.mkdtemp()
    bag = os.path.join(tmp, 'bag')
    subprocess.run([sys.executable, '-m', 'armcal_ros.cli', 'import-folder', folder,
                    '--output', bag], check=True, capture_output=True)
    with open(os.path.join(bag, 'params.yaml'), 'a') as f:
        f.write('    marker_type: aruco\n    aruco_dictionary: DICT_4X4_50\n'
                f'    aruco_id: {tag_id}\n    marker_offset: {list(guess)}\n'
                f'    estimate_marker_offset: true\n    eye_in_hand: {str(eye_in_hand).lower()}\n'
                '    noise_model: fixed\n    free_distortion: []\n    min_samples: 8\n')
    out = os.path.join(tmp, 'out')
    proc = subprocess.run([sys.executable, '-m', 'armcal_ros.cli', 'calibrate', bag, '--params',
                           os.path.join(bag, 'params.yaml'), '--output', out, '--quiet'],
                          capture_output=True, text=True)
    if proc.returncode:
        sys.exit(f'armcal calibrate failed on {folder}: {proc.stderr}')
    with open(os.path.join(out, 'report.json')) as f:
        report = json.load(f)
    with open(os.path.join(out, 'extrinsics.yaml')) as f:
        ext = yaml.safe_load(f)
    return report, ext


def detect(folder, mode='centre'):
    """
    Return BoardData of the tag id 0 per view and camera, and the camera names.

    ``mode`` 'centre': the tag's centre (one point); 'corner0': its corner 0 (the original
    tool's point); 'corners': its four corners on a square of side :data:`SIZE_GUESS`.
    """
    det = ArucoDetector('DICT_4X4_50', marker_id=0, corners=mode != 'centre')
    cams = folder.cameras
    view, camera, corner, uv = [], [], [], []
    for v, s in enumerate(folder.samples):
        for j, c in enumerate(cams):
            path = folder.images[c].get(s)
            found = [] if path is None else det.detect(cv2.imread(path, cv2.IMREAD_GRAYSCALE))
            if mode != 'corners':
                found = found[:1]
            for d in found:
                view.append(v)
                camera.append(j)
                corner.append(d.id if mode == 'corners' else 0)
                uv.append(d.uv)
    points = tag_corner_points(SIZE_GUESS) if mode == 'corners' else np.zeros((1, 3))
    return BoardData(folder.poses, points, np.array(view), np.array(camera),
                     np.array(corner, np.int64), np.array(uv).reshape(-1, 2)), cams


def fit(data, folder, cams, keep_cams=None):
    """
    Fit ``data`` for the cameras ``keep_cams`` (indices; default all) with fixed intrinsics.

    A point target starts at :data:`GUESS` on the flange; the tag's corners from hand-eye,
    their side estimated from :data:`SIZE_GUESS`.
    """
    keep = list(range(len(cams))) if keep_cams is None else list(keep_cams)
    sel = np.isin(data.camera, keep)
    remap = -np.ones(len(cams), np.int64)
    remap[keep] = np.arange(len(keep))
    sub = BoardData(data.poses, data.points, data.view[sel], remap[data.camera[sel]],
                    data.corner[sel], data.uv[sel])
    given = {cams[j]: IntrinsicsPrior.from_camera(folder.intrinsics[cams[j]]) for j in keep}
    specs = [CameraSpec(cams[j], 640, 480) for j in keep]
    point = len(data.points) == 1
    seed = None
    if point:
        seed = np.eye(4)
        seed[:3, 3] = GUESS
    return calibrate_board(specs, sub, PriorSettings('fixed'),
                           SolverSettings(free_distortion=(), intrinsics=given),
                           T_link_target=seed,
                           mount=MountSettings(estimate=True, estimate_scale=not point))


def predict(res, data, cams, keep_cams, v=None, ids=None):
    """Prediction errors (px) of view ``v`` (None: all) in the cameras ``keep_cams`` (``ids``)."""
    sel = np.isin(data.camera, keep_cams)
    if v is not None:
        sel &= data.view == v
    if ids is not None:
        sel &= np.isin(data.corner, ids)
    if not sel.any():
        return np.zeros((0,))
    one = BoardData(data.poses, data.points, data.view[sel], data.camera[sel],
                    data.corner[sel], data.uv[sel])
    pred = res.predict_uv(one, cams)
    return np.linalg.norm(pred - one.uv, axis=1)


def outward_residual(res, data, cams):
    """
    Per camera: the fit's mean residual along the tag's diagonals, outward + (px), its se, n.

    For each view with all four corners, the residuals' components along the directions from
    the predicted centre to the predicted corners, averaged: how much larger (+) or smaller
    than the one rigid square each camera sees the tag - a symmetric dilation of the black
    square (blur, exposure) that moves every corner but not the centre.
    """
    pred = res.predict_uv(data, cams)
    r = data.uv - pred
    out = {}
    for j, c in enumerate(cams):
        vals = []
        for v in np.unique(data.view[data.camera == j]):
            m = (data.camera == j) & (data.view == v)
            if m.sum() != 4:
                continue
            d = pred[m] - pred[m].mean(axis=0)
            d /= np.linalg.norm(d, axis=1)[:, None]
            vals.append(float(np.mean(np.sum(r[m] * d, axis=1))))
        vals = np.array(vals)
        out[c] = (float(vals.mean()), float(vals.std(ddof=1) / np.sqrt(len(vals))), len(vals))
    return out


def leave_one_pose_out(joint_data, alone_data, folder, cams, ids=None):
    """
    Return per-camera held-out errors (px): one model of every camera, and each camera alone.

    The joint model is fitted on ``joint_data`` (its errors over the corners ``ids``), the
    per-camera one on ``alone_data``.
    """
    def without(data, v):
        keep = data.view != v
        return BoardData(data.poses, data.points, data.view[keep], data.camera[keep],
                         data.corner[keep], data.uv[keep])
    joint = {c: [] for c in cams}
    alone = {c: [] for c in cams}
    for v in np.unique(joint_data.view):
        res = fit(without(joint_data, v), folder, cams)
        for j, c in enumerate(cams):
            joint[c] += list(predict(res, joint_data, cams, [j], v, ids))
            if ((alone_data.view == v) & (alone_data.camera == j)).any():
                r = fit(without(alone_data, v), folder, cams, [j])
                alone[c] += list(predict(r, alone_data, cams, [j], v))
    return joint, alone


def rms(x):
    """Root mean square, NaN for none."""
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x ** 2))) if x.size else float('nan')


def run(data_dir=DEFAULT_DATA):
    """Measure, print the tables, write the section and JSON; return the section's text."""
    world = os.path.join(data_dir, 'caldata_world_cam')
    if not os.path.isdir(world):
        sys.exit(f'{world} not found')
    with open(os.path.join(data_dir, 'reference', 'calibration.json')) as f:
        ref = json.load(f)
    folder = read_capture_folder(world)
    t0 = time.perf_counter()
    report, _ = cli_calibrate(world, tag_id=0, guess=GUESS)
    t_cli = time.perf_counter() - t0
    wrist, wrist_ext = cli_calibrate(os.path.join(data_dir, 'caldata_wrist_cam'), tag_id=1,
                                     guess=WRIST_GUESS, eye_in_hand=True)
    data, cams = detect(folder)
    per_cam = {c: fit(data, folder, cams, [j]) for j, c in enumerate(cams)}
    joint_lo, alone_lo = leave_one_pose_out(data, data, folder, cams)
    # The tag as a rigid square of estimated side against the original tool's own model (each
    # camera alone with its own point at corner 0), both predicting corner 0 of held-out poses.
    corners, _ = detect(folder, 'corners')
    corner0, _ = detect(folder, 'corner0')
    tag = fit(corners, folder, cams)
    orig = {c: fit(corner0, folder, cams, [j]) for j, c in enumerate(cams)}
    dilation = outward_residual(tag, corners, cams)
    tag_lo, orig_lo = leave_one_pose_out(corners, corner0, folder, cams, ids=[0])
    tag_all_lo, _ = leave_one_pose_out(corners, corner0, folder, cams)
    rows, raw = [], {}
    for j, c in enumerate(cams):
        r = ref[j]
        R_ref = np.array(r['camera_base_ori'])
        t_ref = np.array(r['camera_base_pos'])

        def against(t, q):
            dR = Rotation.from_matrix(R_ref.T @ Rotation.from_quat(q).as_matrix())
            return 1000 * float(np.linalg.norm(np.asarray(t) - t_ref)), \
                float(np.degrees(dR.magnitude()))
        ours = report['cameras'][c]
        d_ours = against(ours['translation'], ours['rotation'])
        pc = per_cam[c].calibration.adjustment.cameras[c]
        tq = pc.camera.pose_in_world()
        d_alone = against(tq[0], tq[1])
        raw[c] = dict(ours=dict(dpos_mm=d_ours[0], drot_deg=d_ours[1], rms_px=ours['rms_px'],
                                n_obs=ours['n_observations'], n_inliers=ours['n_inliers'],
                                loo_px=rms(joint_lo[c])),
                      per_camera=dict(dpos_mm=d_alone[0], drot_deg=d_alone[1],
                                      rms_px=pc.rms_px, loo_px=rms(alone_lo[c]),
                                      marker=list(per_cam[c].T_link_target[:3, 3])),
                      reference=dict(pixel_error_corner0=r['pixel_error'],
                                     n=r['num_marker_seen']))
        rows.append([c, f'{d_ours[0]:.1f}, {d_ours[1]:.2f}', f'{d_alone[0]:.1f}, {d_alone[1]:.2f}',
                     f'{ours["rms_px"]:.2f} ({ours["n_inliers"]}/{ours["n_observations"]})',
                     f'{pc.rms_px:.2f}', f'{r["pixel_error"]:.2f}',
                     f'{rms(joint_lo[c]):.2f}', f'{rms(alone_lo[c]):.2f}'])
    all_joint = [e for c in cams for e in joint_lo[c]]
    all_alone = [e for c in cams for e in alone_lo[c]]
    rows.append(['all', '', '', '', '', '', f'{rms(all_joint):.2f}', f'{rms(all_alone):.2f}'])
    crows = []
    for j, c in enumerate(cams):
        est = tag.calibration.adjustment.cameras.get(c)
        tq = est.camera.pose_in_world()
        dR = Rotation.from_matrix(np.array(ref[j]['camera_base_ori']).T
                                  @ Rotation.from_quat(tq[1]).as_matrix())
        dpos = 1000 * float(np.linalg.norm(tq[0] - np.array(ref[j]['camera_base_pos'])))
        fit_c0 = rms(predict(tag, corners, cams, [j], ids=[0]))
        orig_c0 = rms(predict(orig[c], corner0, cams, [j]))
        raw[c]['corner0_fit_px'] = dict(tag=fit_c0, original_model=orig_c0,
                                        reference=ref[j]['pixel_error'])
        crows.append([c, f'{dpos:.1f}, {np.degrees(dR.magnitude()):.2f}',
                      f'{est.rms_px:.2f} ({est.n_inliers}/{est.n_observations})',
                      f'{fit_c0:.2f}', f'{orig_c0:.2f}', f'{ref[j]["pixel_error"]:.2f}',
                      f'{rms(tag_all_lo[c]):.2f}', f'{rms(tag_lo[c]):.2f}',
                      f'{rms(orig_lo[c]):.2f}'])
    crows.append(['all', '', '', '', '', '',
                  f'{rms([e for c in cams for e in tag_all_lo[c]]):.2f}',
                  f'{rms([e for c in cams for e in tag_lo[c]]):.2f}',
                  f'{rms([e for c in cams for e in orig_lo[c]]):.2f}'])
    raw['tag_corners'] = dict(
        side_m=float(SIZE_GUESS * tag.scale), guess_m=SIZE_GUESS,
        held_out_corner0=rms([e for c in cams for e in tag_lo[c]]),
        held_out_all=rms([e for c in cams for e in tag_all_lo[c]]),
        original_held_out_corner0=rms([e for c in cams for e in orig_lo[c]]),
        outward_residual_px={c: dict(mean=m, se=se, views=k) for c, (m, se, k) in
                             dilation.items()})
    tgt = report['target']
    wc = wrist['cameras']['cam0']
    wx = wrist_ext['cameras']['cam0']
    markers = '; '.join(f'{c} ' + ', '.join(f'{1000 * x:.1f}'
                                            for x in raw[c]['per_camera']['marker'])
                        for c in cams)
    md = [
        '## Real data: Franka Panda, three RealSense cameras, ArUco tag (bench/real_data.py)',
        '',
        'The fairo eyehandcal set: 20 flange poses, a 640x480 image per camera at each, the '
        'factory intrinsics (zero distortion), an ArUco tag (DICT_4X4_50, id 0) of unrecorded '
        'size at an unrecorded place on the gripper; its centre is detected. "armcal": '
        '`armcal import-folder` then `armcal calibrate` with the intrinsics fixed, one marker '
        f'point for all cameras estimated from a guess of {list(GUESS)} m on the flange, '
        'noise model `fixed`. "per camera": the original tool\'s model on the same '
        'observations and solver - each camera on its own with its own marker point. '
        '"reference": the original tool\'s published result (corner 0 of the tag, per camera; '
        'not ground truth, its pixel error is over another point). Leave-one-pose-out: fitted '
        'without a pose, the held-out pose\'s tag centre predicted in every camera that saw '
        'it.',
        '',
        table(['camera', 'armcal vs reference: mm, deg', 'per camera vs reference: mm, deg',
               'armcal RMS px (inliers)', 'per camera RMS px', 'reference px (corner 0)',
               'armcal held-out px', 'per camera held-out px'], rows),
        '',
        'Marker point estimated by armcal (m, in the flange): '
        + ', '.join(f'{x:.4f}' for x in tgt['T_link_target'][:3]) + ' +/- '
        + ', '.join(f'{x:.4f}' for x in tgt['std'][:3])
        + f'; per camera (mm): {markers}. armcal import + calibrate {t_cli:.1f} s.',
        '',
        'The tag as a rigid square of four corners (`aruco_size` a guess of '
        f'{SIZE_GUESS * 1000:.0f} mm with `estimate_aruco_size`; its side comes out '
        f'{SIZE_GUESS * tag.scale * 1000:.1f} mm, the same from guesses of 30 and 80 mm) '
        'against the original tool\'s own model (each camera alone, its own point at corner '
        '0), both held out one pose at a time and predicting corner 0 in every camera; the '
        'tag model\'s prediction of all four corners beside it. The fitted corner 0 is over '
        'every detection of this detector; the reference\'s figure is a mean distance over its '
        '14 detections per camera (a mean is below an RMS of the same errors).',
        '',
        table(['camera', 'tag vs reference: mm, deg', 'tag RMS px (inliers)',
               'tag RMS px, corner 0', 'original model RMS px, corner 0',
               'reference px, corner 0',
               'tag held-out px, 4 corners', 'tag held-out px, corner 0',
               'original model held-out px, corner 0'], crows),
        '',
        'Why the rigid tag does not predict corner 0 better: each camera sees the tag at a '
        'slightly different size. The tag fit\'s mean residual along the tag\'s diagonals '
        '(outward +, px, +/- its standard error over the views) is '
        + ', '.join(f'{c} {m:+.2f} +/- {se:.2f}' for c, (m, se, _) in dilation.items())
        + ': a dilation or erosion of the black square (blur, exposure) that moves every '
        'corner along its diagonal and leaves the centre where it is. The original model\'s '
        'own point per camera absorbs it for corner 0; one rigid square cannot, and the '
        'tag\'s centre, which it does not move, is predicted better by one marker for all '
        'cameras (the first table).',
        '',
        'The wrist set (eye-in-hand: the camera on the flange, tag id 1 static on the table; '
        'the original tool accepts < 2 px and publishes no result for it), `eye_in_hand: true`, '
        f'the tag\'s place guessed at {list(WRIST_GUESS)} m in the base: '
        f'RMS {wc["rms_px"]:.2f} px over {wc["n_inliers"]} of {wc["n_observations"]} detections; '
        'T_flange_camera translation (m) '
        + ', '.join(f'{x:.4f}' for x in wx['translation']) + ', rotation (x, y, z, w) '
        + ', '.join(f'{x:.4f}' for x in wx['rotation']) + '; the tag\'s centre in the base '
        + ', '.join(f'{x:.4f}' for x in wrist['target']['T_link_target'][:3]) + ' m +/- '
        + ', '.join(f'{x:.4f}' for x in wrist['target']['std'][:3]) + '.',
        '',
        f'Measured on {machine()}.',
    ]
    text = '\n'.join(md)
    print(text)
    write_section('real_franka', text)
    write_json('real_franka', dict(cameras=raw, marker=tgt, held_out=dict(
        armcal=rms(all_joint), per_camera=rms(all_alone)), wrist=dict(
            camera=wc, extrinsics=wx, target=wrist['target']), machine=machine()))
    return text


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    p.add_argument('--data', default=DEFAULT_DATA)
    run(p.parse_args().data)


if __name__ == '__main__':
    main()
