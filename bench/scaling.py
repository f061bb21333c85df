"""
Solve time against the number of robot points, for each noise model, cold and warm.

Problem: the `mixed` scenario of bench/accuracy.py (PUMA 560, three cameras, 0.3 px noise) at
N = 1,000 / 3,000 / 10,000 / 30,000 points.  Cold: the whole calibrate() from nothing (DLT with
RANSAC, `fixed`, then the model).  Warm: what the background loop does on its next solve - the
same session with 1 % more points, started from the previous cameras and global parameters
(the `fixed` stage is skipped).  `correlated` takes its lattice form above 600 points; the
exact dense form is timed where it fits (its LM iteration costs O(N^3)).

Usage: python bench/scaling.py [--sizes 1000 3000 10000 30000] [--threads 1]
Writes docs/BENCHMARKS.md (section "scaling") and docs/bench/scaling.json.
"""

import argparse
import os
import sys
import time


def _threads_from_argv(argv):
    if '--threads' in argv:
        return argv[argv.index('--threads') + 1]
    return '1'


os.environ.setdefault('OPENBLAS_NUM_THREADS', _threads_from_argv(sys.argv))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from _report import machine, table, write_json, write_section  # noqa: E402

from armcal_ros.core.adjustment import Observations, SolverSettings  # noqa: E402
from armcal_ros.core.calibration import calibrate  # noqa: E402
from armcal_ros.core.evaluation import score_cameras  # noqa: E402
from armcal_ros.core.priors import PriorSettings  # noqa: E402
from armcal_ros.sim.robot_points import make_robot_problem  # noqa: E402

MODELS = ('fixed', 'independent', 'correlated', 'correlated (exact)', 'kinematic', 'hybrid')
EXACT_MAX = 1500


def split(prob, n_first):
    """Return (measured, obs, kinematics) of the first ``n_first`` points."""
    keep = prob.obs.point < n_first
    obs = Observations(prob.obs.camera[keep], prob.obs.point[keep], prob.obs.uv[keep])
    return prob.measured[:n_first], obs, prob.kinematics.subset(np.arange(n_first))


def prior_for(model):
    """Return the PriorSettings of a row (hybrid: the mixed field, as auto picks it)."""
    if model == 'correlated (exact)':
        return PriorSettings('correlated', field_form='exact')
    if model == 'hybrid':
        return PriorSettings('hybrid', bias_sigma=0.3e-3, coherence_length=0.15,
                             kinematic_scale=0.5)
    return PriorSettings(model)


def run_size(n, models, seed=0):
    """Time every model at N = n."""
    extra = max(1, n // 100)
    prob = make_robot_problem('mixed', n + extra, seed, n_test=300)
    s = SolverSettings(pixel_sigma=0.3)
    out = {}
    for m in models:
        if m == 'correlated (exact)' and n > EXACT_MAX:
            continue
        ps = prior_for(m)
        measured, obs, kin = split(prob, n)
        t = time.perf_counter()
        cold = calibrate(prob.specs, measured, obs, ps, s, kinematics=kin)
        t_cold = time.perf_counter() - t
        g0 = cold.adjustment.global_parameters
        measured2, obs2, kin2 = split(prob, n + extra)
        t = time.perf_counter()
        # The new points start at the fitted prior's prediction, the old at their estimates.
        new = measured2[n:]
        pred = new + cold.adjustment.predict_offsets(new, kin2.jacobian[n:])
        warm = calibrate(prob.specs, measured2, obs2, ps, s, initial=cold.cameras,
                         kinematics=kin2, globals_init=g0 if _same_size(g0, ps, measured2,
                                                                        kin2) else None,
                         points_init=np.vstack([cold.adjustment.points, pred]))
        t_warm = time.perf_counter() - t
        sc = score_cameras(warm.cameras, prob.truth, prob.test_points)
        out[m] = dict(cold_s=t_cold, warm_s=t_warm,
                      cold_iterations=int(sum(st[2] for st in cold.stages)),
                      warm_iterations=int(sum(st[2] for st in warm.stages)),
                      success=bool(cold.success and warm.success), shape_mm=sc.shape_mm,
                      n_global=0 if g0 is None else int(g0.size))
        print(f'N={n} {m}: cold {t_cold:.2f} s ({out[m]["cold_iterations"]} it), warm '
              f'{t_warm:.2f} s ({out[m]["warm_iterations"]} it)', flush=True)
    return out


def _same_size(g0, ps, measured, kin):
    """Whether a warm start's global vector fits the new problem (the lattice may grow)."""
    if g0 is None:
        return False
    from armcal_ros.core.priors import PointPrior
    pr = PointPrior(measured, ps, kin if ps.model in ('kinematic', 'hybrid') else None)
    return pr.kind == 'global' and pr.n_global == g0.size


def main(argv=None):
    """Run the benchmark, print the table and write it to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--sizes', type=int, nargs='+', default=[1000, 3000, 10000, 30000])
    ap.add_argument('--models', nargs='+', default=list(MODELS))
    ap.add_argument('--threads', default='1', help='BLAS threads (OPENBLAS_NUM_THREADS)')
    args = ap.parse_args(argv)
    results = {}
    for n in args.sizes:
        results[str(n)] = run_size(n, args.models)
    rows = []
    for m in args.models:
        row = [m]
        for n in args.sizes:
            r = results[str(n)].get(m)
            row.append('-' if r is None else f'{r["cold_s"]:.2f} / {r["warm_s"]:.2f}')
        rows.append(row)
    md = ['## Solve time against N (bench/scaling.py)', '',
          'The `mixed` scenario (PUMA 560, three cameras, 0.3 px). Cold: calibrate() from '
          'nothing (DLT + RANSAC, `fixed`, the model); warm: the next background solve - 1 % '
          'more points, started from the previous cameras and global parameters. Seconds, '
          f'cold / warm; one seed. BLAS threads: {os.environ.get("OPENBLAS_NUM_THREADS")}. '
          f'Measured on {machine()} (shared with other work). `hybrid`: s_b 0.3 mm, '
          'L 0.15 m, kinematic scale 0.5 (what `auto` picks on this scenario); `correlated`: '
          'defaults (s_b 1 mm, L 0.3 m), lattice form above 600 points.', '',
          table(['model'] + [f'N = {n}' for n in args.sizes], rows)]
    if '1000' in results and '10000' in results and 'hybrid' in results['10000']:
        h1, h10 = results['1000']['hybrid'], results['10000']['hybrid']
        md += ['', f'Targets: hybrid at N = 10,000 cold **{h10["cold_s"]:.1f} s** (< 10 s), '
               f'warm **{h10["warm_s"]:.2f} s** (< 2 s); growth from 1,000 to 10,000 points '
               f'**{h10["cold_s"] / h1["cold_s"]:.1f} x** cold, '
               f'{h10["warm_s"] / h1["warm_s"]:.1f} x warm (<= 15 x).']
    text = '\n'.join(md)
    print(text)
    write_section('scaling', text)
    write_json('scaling', {'results': results, 'machine': machine(),
                           'blas_threads': os.environ.get('OPENBLAS_NUM_THREADS')})
    return 0


if __name__ == '__main__':
    sys.exit(main())
