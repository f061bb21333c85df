"""
``make demo``: calibrate the bundled demo bag and print the result beside its ground truth.

The bag (bags/demo) is seven minutes of simulated teleoperation of a PUMA 560 with geometric and
non-geometric errors, seen by three cameras; ``config/demo.yaml`` is its parameter file.  The
whole pipeline runs (decode, detect, pair, pool, adjust) and the recovered cameras are compared
with the simulator's: focal error (%), camera-centre error (mm), and the triangulation error of
fresh workspace points (mm).  ``--synthetic`` runs the point-level demo instead (no bag: three
simulated cameras and biased robot points, every noise model).
"""

import argparse
import os
import sys

from armcal_ros.compare import compare, format_comparison, load_truth
from armcal_ros.params import number_arg
from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.evaluation import score_cameras
from armcal_ros.core.priors import PriorSettings
from armcal_ros.offline import collect_samples, format_table, solve_and_write
from armcal_ros.settings import load_settings, with_noise_model
from armcal_ros.sim.synthetic import make_problem


def synthetic_demo(n_points=300, seed=0, out=sys.stdout):
    """Run the point-level demo and print the comparison; return 0 on success."""
    prob = make_problem(n_points, seed)
    print(f'Synthetic cell: 3 cameras, {n_points} robot points, bias 1 mm (L = 0.3 m), '
          f'0.3 px image noise, seed {seed}\n', file=out)
    fmt = '{:<12} {:<6} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>9}'
    ok = True
    for model in ('fixed', 'independent', 'correlated'):
        res = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings(model),
                        SolverSettings(pixel_sigma=0.3))
        ok &= res.success
        sc = score_cameras(res.cameras, prob.truth, prob.test_points)
        print(f'== {model}: {res.status} in {res.time_s:.2f} s; triangulation error on 500 '
              f'fresh points {sc.absolute_mm:.2f} mm absolute, {sc.shape_mm:.2f} mm shape',
              file=out)
        print(fmt.format('camera', '', 'fx', 'fy', 'cx', 'cy', 'k1', 'k2', 'centre mm'),
              file=out)
        for cam in prob.cameras:
            est = res.adjustment.cameras[cam.name]
            e = est.camera
            print(fmt.format(cam.name, 'true', f'{cam.fx:.1f}', f'{cam.fy:.1f}', f'{cam.cx:.1f}',
                             f'{cam.cy:.1f}', f'{cam.dist[0]:.4f}', f'{cam.dist[1]:.4f}', ''),
                  file=out)
            err = 1000 * ((e.center - cam.center) ** 2).sum() ** 0.5
            print(fmt.format('', 'est', f'{e.fx:.1f}', f'{e.fy:.1f}', f'{e.cx:.1f}',
                             f'{e.cy:.1f}', f'{e.dist[0]:.4f}', f'{e.dist[1]:.4f}',
                             f'{err:.2f}'), file=out)
            print(fmt.format('', '+/-', f'{est.std["fx"]:.1f}', f'{est.std["fy"]:.1f}',
                             f'{est.std["cx"]:.1f}', f'{est.std["cy"]:.1f}',
                             f'{est.std["k1"]:.4f}', f'{est.std["k2"]:.4f}', ''), file=out)
        print(file=out)
    return 0 if ok else 1


ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def bag_demo(bag, params, output, noise_models, out=sys.stdout):
    """Run the front end on ``bag`` once, solve with each noise model, compare with the truth."""
    gt = os.path.join(bag, 'ground_truth')
    truth, _ = load_truth(gt)
    settings = load_settings(params)

    live = sys.stderr.isatty()      # '\r' updates only on a terminal, never into a log

    def progress(i, n):
        if live:
            print(f'\r  reading {bag}: {i}/{n} messages', end='', file=sys.stderr, flush=True)
    if not live:
        print(f'  reading {bag} ...', file=sys.stderr, flush=True)
    front = collect_samples(bag, settings, progress)
    if live:
        print('', file=sys.stderr)
    print(f'Front end: {front.messages} messages in {front.time_s:.1f} s -> '
          f'{len(front.store)} samples\n', file=out)
    summary = []
    for model in noise_models:
        dest = os.path.join(output, model)
        res = solve_and_write(front, with_noise_model(settings, model), dest)
        est = {k: c.camera for k, c in res.outcome.calibration.cameras.items()}
        score = compare(est, gt)
        print(f'== {model}  (solve {res.outcome.time_s:.1f} s; files in {dest})', file=out)
        print(format_table(res.report), file=out)
        print(format_comparison(score, est, truth), file=out)
        print(file=out)
        summary.append((model, score, res.outcome.time_s))
    if len(summary) > 1:
        print(f'{"model":<12} {"absolute mm":>12} {"shape mm":>9} {"centre mm":>10} '
              f'{"focal %":>8} {"solve s":>8}', file=out)
        for model, s, t in summary:
            print(f'{model:<12} {s.absolute_mm:12.3f} {s.shape_mm:9.3f} {s.centre_mm:10.2f} '
                  f'{s.focal_pct:8.3f} {t:8.2f}', file=out)
    return 0


def add_arguments(ap):
    """Arguments of ``armcal demo``."""
    ap.add_argument('--bag', default=os.path.join(ROOT, 'bags', 'demo'))
    ap.add_argument('--params', default=os.path.join(ROOT, 'config', 'demo.yaml'))
    ap.add_argument('--output', default=os.path.join(ROOT, 'out', 'demo'))
    ap.add_argument('--noise-model', nargs='+',
                    default=['fixed', 'correlated', 'kinematic', 'auto'],
                    help='noise models to compare (the front end runs once)')
    ap.add_argument('--synthetic', action='store_true',
                    help='point-level demo without a bag (every noise model)')
    ap.add_argument('--points', type=number_arg(int, 10, 100000), default=300,
                    help='points of the synthetic demo')
    ap.add_argument('--seed', type=number_arg(int, 0, 2 ** 32 - 1), default=0,
                    help='seed of the synthetic demo')


def run(args):
    """Run ``armcal demo``; return the exit status."""
    if args.synthetic:
        return synthetic_demo(args.points, args.seed)
    return bag_demo(args.bag, args.params, args.output, args.noise_model)


def main(argv=None):
    """Command-line entry: ``python -m armcal_ros.demo``."""
    ap = argparse.ArgumentParser(description='armcal_ros demo')
    add_arguments(ap)
    return run(ap.parse_args(argv))


if __name__ == '__main__':
    sys.exit(main())
