"""
`make demo` before the bag pipeline: calibrate three simulated cameras from noisy robot points.

The robot's points carry a bias drawn from the paper's correlated prior (1 mm, L = 0.3 m) and the
images 0.3 px of noise.  Each noise model is run from scratch (DLT, fixed, model) and the recovered
parameters are printed beside the truth, with the triangulation error on fresh points.
"""

import argparse
import sys

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.evaluation import score_cameras
from armcal_ros.core.priors import PriorSettings
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


def main(argv=None):
    """Command-line entry: ``python -m armcal_ros.demo``."""
    ap = argparse.ArgumentParser(description='armcal_ros point-level demo')
    ap.add_argument('--points', type=int, default=300)
    ap.add_argument('--seed', type=int, default=0)
    args = ap.parse_args(argv)
    return synthetic_demo(args.points, args.seed)


if __name__ == '__main__':
    sys.exit(main())
