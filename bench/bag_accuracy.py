"""
Accuracy through the whole pipeline: simulated bags -> detection, pairing, pooling -> every model.

bench/accuracy.py scores the noise models on point-level problems; this script checks that the
same ranking survives the real front end (rendered images, sphere detection, time pairing with
stamp jitter, stillness, dwell pooling).  Cases: the bundled demo bag (`nongeometric`, 420 s) and a
freshly simulated `mixed` bag.  Each bag's samples are collected once and solved with every noise
model; scores are from `armcal_ros.compare` (500 fresh workspace points triangulated from their
true projections).  Both bags light their marker, a matte ball, by one lamp above the cell
(``--lighting realistic``) and run with the node's default centre (``shaded_pooled``).

With ``--uniform`` the same two sessions are simulated again under uniform light (a ball that
glows alike from every side, the condition of every recording before 2026-12-03) and run with
the intensity centroid: like with like, the same trajectories and errors.

Usage: python bench/bag_accuracy.py [--duration 300] [--seed 0] [--uniform]
"""

import argparse
import dataclasses
import os
import sys
import tempfile

# Small dense matrices: OpenBLAS threads only contend on a shared 2-core machine (the auto search
# took 60 s threaded against 4.7 s single-threaded under the same load, measured).
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402
from pipeline import uniform_twin  # noqa: E402

import numpy as np  # noqa: E402

from armcal_ros.compare import compare  # noqa: E402
from armcal_ros.core.evaluation import z_scores  # noqa: E402
from armcal_ros.io.calib_files import read_cameras  # noqa: E402
from armcal_ros.offline import collect_samples, solve_and_write  # noqa: E402
from armcal_ros.settings import load_settings, with_noise_model  # noqa: E402
from armcal_ros.sim.cell import simulate_cell  # noqa: E402
from armcal_ros.sim.cells import CELLS  # noqa: E402
from armcal_ros.sim.output import write_sim_bag  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MODELS = ('fixed', 'independent', 'correlated', 'kinematic', 'hybrid', 'auto')


def all_z(cal, truth):
    """Return the z-scores of every camera's parameters (:func:`z_scores`), as one array."""
    return np.array([v for name, c in cal.cameras.items()
                     for v in z_scores(c.camera, c.std, truth[name]).values()])


def run_bag(label, bag, params, out_dir, centre=None):
    """Collect once, solve with each model; return rows and raw numbers."""
    settings = load_settings(params)
    if centre is not None:
        settings = dataclasses.replace(settings, detector=dataclasses.replace(
            settings.detector, sphere_centre=centre))
    front = collect_samples(bag, settings)
    truth = {c.name: c for c in read_cameras(os.path.join(bag, 'ground_truth'))[1]}
    rows, raw = [], {}
    for model in MODELS:
        res = solve_and_write(front, with_noise_model(settings, model),
                              os.path.join(out_dir, label, model))
        cal = res.outcome.calibration
        est = {k: c.camera for k, c in cal.cameras.items()}
        sc = compare(est, os.path.join(bag, 'ground_truth'))
        chosen = cal.hyperparameters.get('model', model) if model == 'auto' else ''
        raw[model] = dict(absolute_mm=sc.absolute_mm, shape_mm=sc.shape_mm,
                          centre_mm=sc.centre_mm, focal_pct=sc.focal_pct,
                          solve_s=res.outcome.time_s, chosen=chosen,
                          pixel_sigma=cal.hyperparameters.get('pixel_sigma'),
                          reason=cal.hyperparameters.get('auto_reason', ''))
        h = cal.hyperparameters
        z = all_z(cal, truth)
        raw[model].update(rms_z=float(np.sqrt(np.mean(z ** 2))),
                          within2=float(np.mean(np.abs(z) < 2)), uncertainty=h.get('uncertainty'))
        rows.append([label, len(front.store), model + (f' ({chosen})' if chosen else ''),
                     f'{h.get("pixel_sigma", float("nan")):.3f} '
                     f'({h.get("pixel_sigma_source", "given")})',
                     f'{sc.absolute_mm:.3f}', f'{sc.shape_mm:.3f}', f'{sc.centre_mm:.2f}',
                     f'{sc.focal_pct:.3f}', f'{raw[model]["rms_z"]:.2f}',
                     f'{100 * raw[model]["within2"]:.0f}', f'{res.outcome.time_s:.2f}'])
    return rows, raw


def main(argv=None):
    """Run the benchmark, print the table and write it to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--duration', type=float, default=300.0)
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--uniform', action='store_true',
                    help='also both sessions lit uniformly, with the intensity centroid')
    args = ap.parse_args(argv)
    params = os.path.join(ROOT, 'config', 'demo.yaml')
    rows, raw = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        r, raw['demo (nongeometric)'] = run_bag('demo (nongeometric)',
                                                os.path.join(ROOT, 'bags', 'demo'), params, tmp)
        rows += r
        bag = os.path.join(tmp, 'mixed')
        write_sim_bag(simulate_cell('mixed', seed=args.seed, duration=args.duration,
                                    settings=CELLS['puma-3cam'].sim_settings(
                                        duration=args.duration)), bag)
        label = f'mixed, {args.duration:.0f} s, seed {args.seed}'
        r, raw[label] = run_bag(label, bag, params, tmp)
        rows += r
        if args.uniform:
            # The same sessions under uniform light with the centroid: the earlier condition.
            twin = uniform_twin(os.path.join(ROOT, 'bags', 'demo'), tmp)
            r, raw['demo, uniform light, centroid'] = run_bag(
                'demo, uniform light, centroid', twin, params, tmp, 'centroid')
            rows += r
            bag = os.path.join(tmp, 'mixed-uniform')
            write_sim_bag(simulate_cell('mixed', seed=args.seed, duration=args.duration,
                                        settings=CELLS['puma-3cam'].sim_settings(
                                            'uniform', duration=args.duration)), bag)
            label = f'mixed, {args.duration:.0f} s, seed {args.seed}, uniform light, centroid'
            r, raw[label] = run_bag(label, bag, params, tmp, 'centroid')
            rows += r
    md = ['## Accuracy through the whole pipeline (bench/bag_accuracy.py)', '',
          'Simulated bags through detection, pairing and pooling, then every noise model on the '
          'same samples; scored against the simulator\'s cameras by triangulating 500 fresh '
          'workspace points. Both bags\' marker is a matte ball lit by one lamp 1.5 m above '
          'the workspace (realistic; the default centre, `sphere_centre: shaded_pooled`); '
          'rows marked "uniform light, centroid" are the same sessions simulated with a ball '
          'that glows alike from every side, run with the intensity centroid (the condition '
          'before 2026-12-03). '
          f'Measured on {machine()}, single-threaded BLAS. Every model '
          'estimates the image noise (the node\'s default, `pixel_sigma: 0`): `auto` from the '
          'free network, the others from their own residuals (variance factor, redundancy by '
          'leverage) - the column "noise px" says which value and where from, so the rows '
          'compare like with like; what `auto` chose is below the table.', '',
          table(['bag', 'samples', 'model', 'noise px', 'absolute mm', 'shape mm',
                 'centre mm', 'focal %', 'RMS z', 'in 2 sigma %', 'solve s'], rows),
          '', 'RMS z, in 2 sigma: the published standard deviations against the simulator\'s '
          'cameras (fx, fy, cx, cy, k1, k2, centre and rotation per axis; 1 and 95 % when '
          'honest), as in bench/uncertainty.py. A single model\'s solve time includes the '
          '`auto` search that gives its uncertainty reference (the node runs it on the first '
          'solve and when the samples have grown by half) and its image-noise re-weighting.']
    md += ['', 'What `auto` chose and why:', '']
    for label, case in raw.items():
        md.append(f'- {label}: {case["auto"]["reason"]}')
    md += ['', 'History (2026-11-22, same bags): before hybrid\'s field was limited to local '
           'coherence lengths (at most 1.5 x the samples\' RMS radius, '
           '`model_selection.HYBRID_MAX_L_FRACTION`), `auto` chose a field of L = 0.6 m on the '
           'demo bag (0.3 m RMS radius): 58 more log evidence and better held-out prediction '
           'than the kinematic model, but shape 0.155 mm against its 0.133 mm - a field '
           'correlated across the whole workspace trades with the cameras.']
    text = '\n'.join(md)
    print(text)
    write_section('accuracy-bag', text)
    write_json('bag_accuracy', dict(cases=raw, machine=machine()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
