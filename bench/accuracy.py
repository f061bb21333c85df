"""
Accuracy of every noise model on a simulated PUMA 560 cell (issue 6).

Point level: joint configurations drawn over a teleoperated arm's ranges whose nominal marker is
in the workspace and inside every image; the true marker comes from the simulator's true robot
(:mod:`armcal_ros.sim.true_robot`, scenarios of :mod:`armcal_ros.sim.cell`), the robot's
measurement is the nominal forward kinematics, the cameras see the true marker (where the links do
not hide it) with 0.3 px noise.  Scored by triangulating 500 fresh true markers with the
estimated cameras (their true, noise-free projections).

Models: oracle (true points, fixed), fixed, independent, correlated and kinematic at their
documented defaults, and the evidence-tuned ones from the ``auto`` search: correlated* and
kinematic* (best hyperparameters of that model), hybrid* (hybrid always needs its field's sigma
and length chosen, see the README), and auto (the chosen model, refined).

Columns: absolute error (mm, robot base frame); abs-mount: the absolute error against the true
markers with the base joint's mounting error removed (the simulator draws joint_1 origin and
offset errors: a rigid motion of the whole arm that neither the images nor the arm can reveal, so
no estimator can remove it - this column shows what the others can); shape (mm, after the best
similarity); camera-centre (mm), focal (%), test reprojection (px), solve time of the model
stage (s; for auto the whole search).

Usage: python bench/accuracy.py [--sizes 300 1000] [--seeds 5] [--scenarios ...]
Writes docs/BENCHMARKS.md (section "accuracy") and docs/bench/accuracy.json.
"""

import argparse
import os
import sys
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from _report import machine, table, write_json, write_section  # noqa: E402

from armcal_ros.core.adjustment import adjust, SolverSettings  # noqa: E402
from armcal_ros.core.calibration import calibrate  # noqa: E402
from armcal_ros.core.evaluation import absolute_error, score_cameras, triangulate  # noqa: E402
from armcal_ros.core.model_selection import select_model  # noqa: E402
from armcal_ros.core.priors import PriorSettings  # noqa: E402
from armcal_ros.sim.robot_points import make_robot_problem  # noqa: E402
from armcal_ros.sim.true_robot import TrueRobot  # noqa: E402

SCENARIOS = ('geometric', 'nongeometric', 'gp-prior', 'mixed')
MODELS = ('oracle', 'fixed', 'independent', 'correlated', 'kinematic', 'correlated*',
          'kinematic*', 'hybrid*', 'auto')
PIXEL_SIGMA = 0.3


def mount_free_truth(prob):
    """Return the true test markers without the base joint's (unobservable) mounting errors."""
    r = prob.robot
    e = r.errors.copy()
    e[:7] = 0.0
    clean = TrueRobot(r.chain, r.point, e, r.periodic_amplitude, r.periodic_phase,
                      r.compliance, r.bias_field, r.gravity)
    return clean.marker(prob.test_q)


def score(cams, prob, truth_mf):
    """Score a list of cameras; returns a dict of numbers."""
    est = {c.name: c for c in cams}
    sc = score_cameras(est, prob.truth, prob.test_points)
    names = [c.name for c in prob.cameras]
    uv = [prob.truth[k].project(prob.test_points) for k in names]
    X = triangulate([est[k] for k in names], uv)
    ok = np.all(np.isfinite(X), axis=1)
    mount_free = 1e3 * absolute_error(X[ok], truth_mf[ok])
    return dict(absolute_mm=sc.absolute_mm, mount_free_mm=mount_free,
                shape_mm=sc.shape_mm, centre_mm=sc.centre_mm, focal_pct=sc.focal_pct,
                reprojection_px=sc.reprojection_px)


def run_case(scenario, n, seed):
    """Run every model on one problem."""
    prob = make_robot_problem(scenario, n, seed, pixel_sigma=PIXEL_SIGMA)
    truth_mf = mount_free_truth(prob)
    s = SolverSettings(pixel_sigma=PIXEL_SIGMA)
    out = {}
    t = time.perf_counter()
    fixed = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)
    t_fixed = time.perf_counter() - t
    cams0, inl = fixed.adjustment.camera_list(), fixed.adjustment.inliers
    out['fixed'] = dict(score(cams0, prob, truth_mf), time_s=t_fixed)
    orc = calibrate(prob.specs, prob.true_points, prob.obs, PriorSettings('fixed'), s)
    out['oracle'] = dict(score(orc.adjustment.camera_list(), prob, truth_mf),
                         time_s=orc.time_s)
    for m in ('independent', 'correlated', 'kinematic'):
        res = adjust(cams0, prob.measured, prob.obs, PriorSettings(m), s, inliers=inl,
                     kinematics=prob.kinematics if m == 'kinematic' else None)
        out[m] = dict(score(res.camera_list(), prob, truth_mf), time_s=res.time_s,
                      log_evidence=res.log_evidence)
    t = time.perf_counter()
    sel = select_model(cams0, prob.measured, prob.obs, PriorSettings(), s, prob.kinematics,
                       inl)
    t_auto = time.perf_counter() - t
    for m in ('correlated', 'kinematic', 'hybrid'):
        b = sel.best_of(m)
        out[m + '*'] = dict(score(b.cameras, prob, truth_mf), time_s=b.time_s,
                            log_evidence=b.log_evidence, holdout_px=b.holdout_px,
                            label=b.label())
    out['auto'] = dict(score(sel.result.camera_list(), prob, truth_mf), time_s=t_auto,
                       chosen=sel.settings.model, label=sel.best_of(sel.settings.model).label(),
                       reason=sel.reason)
    out['bias_rms_mm'] = 1e3 * float(np.sqrt(np.mean(np.sum(prob.bias ** 2, axis=1))))
    return out


def summarise(results, scenarios, sizes, seeds):
    """Mean over seeds per (scenario, N, model)."""
    summary = {}
    for sc in scenarios:
        for n in sizes:
            cases = [results[f'{sc}/{n}/{k}'] for k in range(seeds)]
            for m in MODELS:
                keys = [k for k, v in cases[0][m].items() if isinstance(v, float)]
                summary[f'{sc}/{n}/{m}'] = {k: float(np.mean([c[m][k] for c in cases]))
                                            for k in keys}
            summary[f'{sc}/{n}/bias_rms_mm'] = float(np.mean([c['bias_rms_mm']
                                                              for c in cases]))
            chosen = [c['auto']['label'] for c in cases]
            summary[f'{sc}/{n}/auto_choices'] = {x: chosen.count(x) for x in set(chosen)}
    return summary


def targets(summary, n):
    """Issue 6 targets at N = n, as (name, value, limit, met) rows."""
    rows = []

    def g(sc, m, k):
        return summary.get(f'{sc}/{n}/{m}', {}).get(k, float('nan'))

    if f'geometric/{n}/fixed' in summary:
        best_abs = min(g('geometric', m, 'absolute_mm') for m in MODELS[2:])
        rows.append(('geometric: best absolute / fixed absolute',
                     best_abs / g('geometric', 'fixed', 'absolute_mm'), 0.5))
        best_mf = min(g('geometric', m, 'mount_free_mm') for m in MODELS[2:])
        rows.append(('geometric: best abs-mount / fixed abs-mount (mount error removed)',
                     best_mf / g('geometric', 'fixed', 'mount_free_mm'), 0.5))
        best_shape = min(g('geometric', m, 'shape_mm') for m in MODELS[2:])
        rows.append(('geometric: best shape / oracle shape',
                     best_shape / g('geometric', 'oracle', 'shape_mm'), 1.5))
    if f'mixed/{n}/fixed' in summary:
        ref = min(g('mixed', 'correlated', 'shape_mm'), g('mixed', 'kinematic', 'shape_mm'))
        rows.append(('mixed: hybrid* shape / better of correlated, kinematic (defaults)',
                     g('mixed', 'hybrid*', 'shape_mm') / ref, 0.9))
        ref = min(g('mixed', 'correlated*', 'shape_mm'), g('mixed', 'kinematic*', 'shape_mm'))
        rows.append(('mixed: hybrid* shape / better of correlated*, kinematic* (tuned)',
                     g('mixed', 'hybrid*', 'shape_mm') / ref, 0.9))
    if f'gp-prior/{n}/fixed' in summary:
        rows.append(('gp-prior: correlated absolute / fixed absolute',
                     g('gp-prior', 'correlated', 'absolute_mm') /
                     g('gp-prior', 'fixed', 'absolute_mm'), 0.75))
    for sc in SCENARIOS:
        if f'{sc}/{n}/fixed' not in summary:
            continue
        ref = min(g(sc, 'correlated', 'shape_mm'), g(sc, 'kinematic', 'shape_mm'))
        rows.append((f'{sc}: hybrid* shape / better of correlated, kinematic',
                     g(sc, 'hybrid*', 'shape_mm') / ref, 1.03))
        best = min(g(sc, m, 'shape_mm') for m in MODELS[2:-1])
        rows.append((f'{sc}: auto shape / best model shape', g(sc, 'auto', 'shape_mm') / best,
                     1.05))
    return [(name, v, lim, bool(v <= lim)) for name, v, lim in rows]


def main(argv=None):
    """Run the benchmark, print the tables and write them to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--sizes', type=int, nargs='+', default=[300, 1000])
    ap.add_argument('--seeds', type=int, default=5)
    ap.add_argument('--scenarios', nargs='+', default=list(SCENARIOS))
    args = ap.parse_args(argv)
    results = {}
    for sc in args.scenarios:
        for n in args.sizes:
            for seed in range(args.seeds):
                t0 = time.perf_counter()
                results[f'{sc}/{n}/{seed}'] = run_case(sc, n, seed)
                print(f'{sc} N={n} seed={seed}: {time.perf_counter() - t0:.1f} s, auto chose '
                      f'{results[f"{sc}/{n}/{seed}"]["auto"]["label"]}', flush=True)
    summary = summarise(results, args.scenarios, args.sizes, args.seeds)
    md = ['## Accuracy of the noise models (bench/accuracy.py)', '',
          'PUMA 560 (Corke DH URDF) carrying a sphere marker, three 640x480 cameras (f ~ 800 px, '
          'k1 ~ -0.15) at 1.5-2 m, joint configurations drawn over a teleoperated arm\'s ranges, '
          f'{PIXEL_SIGMA} px image noise, observations dropped where the links hide the marker. '
          'True robot from the simulator (`sim/true_robot.py`): `geometric` = joint offsets '
          '0.05 deg, joint-origin translations 0.3 mm and rotations 0.03 deg per axis, marker '
          'mount 0.2 mm; `nongeometric` adds periodic joint errors (0.01-0.025 deg at 1 and 2 '
          'cycles/turn) and gravity compliance (0.02 deg); `gp-prior` = exact arm plus a field '
          'from the paper\'s prior (1 mm, L = 0.3 m); `mixed` = geometric plus a local field '
          '(0.3 mm, L = 0.15 m). Scored on 500 fresh true markers (triangulated from their '
          f'true projections). Mean of {args.seeds} seeds. Measured on {machine()}, '
          'single-threaded BLAS.', '',
          '`*` = hyperparameters chosen by the Laplace evidence inside the `auto` search '
          '(its candidates, no extra solve); time of a `*` row is that one candidate\'s solve, '
          'of `auto` the whole search (about fifteen adjustments plus the held-out checks). '
          '`abs-mount`: absolute error against the truth with the base joint\'s mounting error '
          '(joint_1 origin and offset, a rigid motion no measurement here can see) removed.', '']
    rows = []
    for sc in args.scenarios:
        for n in args.sizes:
            for m in MODELS:
                v = summary[f'{sc}/{n}/{m}']
                mf = 'n/a' if m == 'oracle' else f'{v["mount_free_mm"]:.3f}'
                rows.append([sc, n, m, f'{v["absolute_mm"]:.3f}', mf,
                             f'{v["shape_mm"]:.3f}', f'{v["centre_mm"]:.2f}',
                             f'{v["focal_pct"]:.3f}', f'{v["reprojection_px"]:.3f}',
                             f'{v["time_s"]:.2f}'])
    md.append(table(['scenario', 'N', 'model', 'absolute mm', 'abs-mount mm', 'shape mm',
                     'centre mm', 'focal %', 'test reproj px', 'time s'], rows))
    md += ['', 'What `auto` chose (count over seeds) and the bias size:', '']
    crow = []
    for sc in args.scenarios:
        for n in args.sizes:
            ch = summary[f'{sc}/{n}/auto_choices']
            crow.append([sc, n, f'{summary[f"{sc}/{n}/bias_rms_mm"]:.2f}',
                         '; '.join(f'{k} x{v}' for k, v in sorted(ch.items()))])
    md.append(table(['scenario', 'N', 'bias RMS mm', 'auto chose'], crow))
    for n in args.sizes:
        t = targets(summary, n)
        if t:
            md += ['', f'Targets of issue 6 at N = {n}:', '',
                   table(['target', 'measured', 'limit', 'met'],
                         [[a, f'{v:.3f}', f'{lim:g}', 'yes' if ok else '**no**']
                          for a, v, lim, ok in t])]
    text = '\n'.join(md)
    print(text)
    write_section('accuracy', text)
    write_json('accuracy', {'summary': summary, 'cases': results, 'machine': machine()})
    return 0


if __name__ == '__main__':
    sys.exit(main())
