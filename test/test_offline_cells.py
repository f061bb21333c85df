"""
End to end on cells unlike the demo's: another arm, other camera names and counts, transports.

``armcal simulate --cell`` writes the bag and the parameters that describe the cell (URDF,
camera names, topics - nothing tuned), ``armcal calibrate`` runs on it, and the cameras are
checked against the simulator's.  Tolerances as in test_offline.py (what a few dozen points with
sub-pixel detections and a ~1 mm robot bias can pin down): focal within 3 %, camera centres
within 40 mm, triangulation within 3 mm absolute and 1 mm in shape; a wrong joint mapping
(joints are published shuffled, with an extra gripper joint), a swapped camera or a wrong
image decoding is off by far more.  On the linkage-error cells the kinematic models must also
beat the ``fixed`` baseline on the same samples, which is what they are for.
"""
import json
import numpy as np
import pytest

from armcal_ros.compare import compare
from armcal_ros.io.calib_files import read_cameras
from helpers.cli import armcal
from armcal_ros.sim.cells import CELLS


def _calibrate(bag, out, model):
    armcal('calibrate', bag, '--params', bag / 'ground_truth' / 'params.yaml', '--output', out,
           '--noise-model', model, '--quiet', '--no-latency')
    _, cams = read_cameras(out)
    est = {c.name: c for c in cams}
    return est, compare(est, bag / 'ground_truth'), json.loads((out / 'report.json').read_text())


@pytest.mark.slow
@pytest.mark.parametrize('cell,duration', [('ur5-2cam', 90), ('desk-4cam', 45),
                                           ('puma-1cam-glints', 60)])
def test_calibrates_a_cell_it_was_not_developed_on(tmp_path, cell, duration):
    bag = tmp_path / 'bag'
    armcal('simulate', '--cell', cell, '--output', bag, '--duration', duration, '--seed', 1,
           '--quiet')
    names = list(CELLS[cell].sim_settings().camera_names)
    est, score, report = _calibrate(bag, tmp_path / 'auto', 'auto')
    assert sorted(est) == sorted(names) and report['accepted']
    for name in names:
        per = score.per_camera[name]
        assert per['focal_pct'] < 3.0 and per['centre_mm'] < 40.0, (name, per)
        assert report['cameras'][name]['rms_px'] < 1.0
    if len(names) >= 2:
        assert score.absolute_mm < 3.0 and score.shape_mm < 1.0, score
    else:
        # one camera: nothing to triangulate; 1 mm at 1.75 m is ~0.5 px at f = 800 px
        assert np.isnan(score.shape_mm) and score.reprojection_px < 2.0, score
        assert 'scatter of the pooled detections' in report['chosen']['auto_reason']
    if CELLS[cell].scenario in ('geometric', 'nongeometric'):
        _, fixed, _ = _calibrate(bag, tmp_path / 'fixed', 'fixed')
        key = 'shape_mm' if len(names) >= 2 else 'reprojection_px'
        assert getattr(score, key) < getattr(fixed, key), (score, fixed)
    if CELLS[cell].scenario == 'geometric' and len(names) >= 2:
        # The limit: the arm's true geometry (the simulator writes it as a URDF) and `fixed`.
        # The true geometry pins the frame too: well under the millimetre the nominal arm is
        # off, and no worse in shape than the nominal arm under `fixed`.
        armcal('calibrate', bag, '--params', bag / 'ground_truth' / 'params_true_geometry.yaml',
               '--output', tmp_path / 'limit', '--quiet', '--no-latency')
        limit = compare({c.name: c for c in read_cameras(tmp_path / 'limit')[1]},
                        bag / 'ground_truth')
        assert limit.absolute_mm < 0.5 and limit.shape_mm < fixed.shape_mm, (limit, fixed)
