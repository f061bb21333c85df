"""
Compare a calibration with a simulator's ground truth (used by the demo, tests and benchmarks).

Errors per camera: focal length (%, mean over fx and fy), optical-centre position (mm).  Whole
rig: triangulation of 500 fresh points drawn uniformly in the bounding box of the true marker
positions (the workspace the arm covered), from their true projections, with the estimated
cameras: absolute error in the base frame and shape error after the best similarity (mm).
"""

import os

import numpy as np

from armcal_ros.core.evaluation import score_cameras
from armcal_ros.io.calib_files import read_cameras


def load_truth(gt_dir):
    """Return (true cameras by name, true marker positions (D, 3)) from a ground_truth dir."""
    _, cams = read_cameras(gt_dir)
    markers = np.load(os.path.join(gt_dir, 'markers.npz'))
    return {c.name: c for c in cams}, np.asarray(markers['dwell_true'])


def compare(estimated, gt_dir, n_test=500, seed=0):
    """Score ``estimated`` ({name: Camera}) against the truth in ``gt_dir``; return a Score."""
    truth, markers = load_truth(gt_dir)
    rng = np.random.default_rng(seed)
    lo, hi = markers.min(axis=0), markers.max(axis=0)
    test = rng.uniform(lo, hi, (n_test, 3))
    return score_cameras(estimated, truth, test)


def format_comparison(score, estimated, truth):
    """Return a table of estimate beside truth per camera and the rig's errors."""
    rows = [f'{"camera":<8} {"":<5} {"fx":>8} {"fy":>8} {"cx":>8} {"cy":>8} {"k1":>8} '
            f'{"focal err %":>11} {"centre err mm":>13}']
    for name, t in truth.items():
        if name not in estimated:
            rows.append(f'{name:<8} not calibrated')
            continue
        e = estimated[name]
        per = score.per_camera.get(name, {})
        rows.append(f'{name:<8} {"true":<5} {t.fx:8.1f} {t.fy:8.1f} {t.cx:8.1f} {t.cy:8.1f} '
                    f'{t.dist[0]:8.4f}')
        rows.append(f'{"":<8} {"est":<5} {e.fx:8.1f} {e.fy:8.1f} {e.cx:8.1f} {e.cy:8.1f} '
                    f'{e.dist[0]:8.4f} {per.get("focal_pct", float("nan")):11.3f} '
                    f'{per.get("centre_mm", float("nan")):13.2f}')
    if np.isfinite(score.absolute_mm):
        rows.append(f'triangulation of 500 fresh workspace points: {score.absolute_mm:.3f} mm '
                    f'absolute, {score.shape_mm:.3f} mm shape (after the best similarity)')
    else:
        rows.append('one camera: no triangulation; see the projection error')
    rows.append(f'projection of 500 fresh workspace points, estimated vs true camera: '
                f'{score.reprojection_px:.3f} px RMS')
    return '\n'.join(rows)
