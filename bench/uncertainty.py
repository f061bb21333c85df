"""
Honest uncertainty: whether the reported standard deviations cover the real errors.

Point level, like bench/accuracy.py: joint configurations drawn over a teleoperated arm's
ranges, the true marker from the simulator's true robot, the robot's measurement its nominal
forward kinematics, the cameras' observations of the true marker with 0.3 px noise.  Scenarios:
the PUMA cell under geometric, nongeometric, gp-prior and mixed errors
(:data:`armcal_ros.sim.cell.SCENARIOS`) and two named cells (:data:`armcal_ros.sim.cells.CELLS`):
``ur5-2cam`` (geometric) and ``desk-4cam`` (mixed).  Models fixed, correlated, kinematic,
hybrid and auto, each with the image noise estimated as the node does by default
(``pixel_sigma: 0``: the model's own variance factor; auto's free network).  "published" is
what the node and the CLI report: for a single model its covariance widened by what the arm
errors it does not describe do to its cameras, under the prior ``auto`` chooses on the same
data (:func:`armcal_ros.core.adjustment.covariance_under`); "model alone" is the adjustment's
own S^-1 at the estimated noise.

Per model, over every camera of every seed: z = (estimate - truth) / reported std for fx, fy,
cx, cy, k1, k2, the camera centre (per axis) and its rotation (per axis, the solver's
R <- exp([w]x) R increments); their RMS (1 for honest standard deviations, above 1 for
overconfident ones) and the fraction within 1 and 2 sigma (68 % and 95 % for a normal).  The
truth is the simulator's, in the robot's own base frame: an arm error no image can see (a
rigid motion of the whole cell) counts as error, and only a prior can widen for it.
Triangulation: 500 fresh true markers (seen by two cameras or more), their exact projections
triangulated with the estimated cameras; "measured" is the RMS 3-D error (mm), "predicted"
the RMS the reported covariance implies (:func:`armcal_ros.core.uncertainty.
triangulation_covariance`).

Usage: python bench/uncertainty.py [--seeds 20] [--n 300] [--scenarios ...] [--models ...]
[--jobs 2] [--no-write].  Writes docs/BENCHMARKS.md (section "uncertainty") and
docs/bench/uncertainty.json unless --no-write.
"""

import argparse
import os
import sys
import time
from multiprocessing import Pool

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402

from _report import machine, table, write_json, write_section  # noqa: E402
from armcal_ros.core.adjustment import SolverSettings  # noqa: E402
from armcal_ros.core.calibration import calibrate  # noqa: E402
from armcal_ros.core.evaluation import triangulate, z_scores  # noqa: E402
from armcal_ros.core.priors import PriorSettings  # noqa: E402
from armcal_ros.core.uncertainty import rms_error_mm, triangulation_covariance  # noqa: E402
from armcal_ros.sim.cells import CELLS  # noqa: E402
from armcal_ros.sim.robot_points import make_robot_problem  # noqa: E402

PIXEL_SIGMA = 0.3
SCENARIOS = ('geometric', 'nongeometric', 'gp-prior', 'mixed', 'ur5-2cam', 'desk-4cam')
MODELS = ('fixed', 'correlated', 'kinematic', 'hybrid', 'auto')
GROUPS = {'fx': ('fx',), 'fy': ('fy',), 'cx': ('cx',), 'cy': ('cy',), 'k1': ('k1',),
          'k2': ('k2',), 'centre': ('Cx', 'Cy', 'Cz'), 'rotation': ('rx', 'ry', 'rz')}


def problem(scenario, n, seed):
    """Return the point-level problem of a PUMA scenario or of a named cell (its scenario)."""
    if scenario in CELLS:
        cell = CELLS[scenario]
        return make_robot_problem(cell.scenario, n, seed, pixel_sigma=PIXEL_SIGMA,
                                  settings=cell.sim_settings())
    return make_robot_problem(scenario, n, seed, pixel_sigma=PIXEL_SIGMA)


def run_case(args):
    """Every model on one (scenario, seed): z-scores and triangulation errors."""
    scenario, n, seed, models = args
    prob = problem(scenario, n, seed)
    truth = prob.truth if isinstance(prob.truth, dict) else {c.name: c for c in prob.truth}
    uv_true = [truth[c.name].project(prob.test_points) for c in prob.specs]
    s = SolverSettings(pixel_sigma=0.5, estimate_noise=True)
    out = {}
    t0 = time.perf_counter()
    auto = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('auto'), s,
                     kinematics=prob.kinematics)
    t_auto = time.perf_counter() - t0
    reference = auto.selection.settings if auto.selection is not None else None
    for m in models:
        variants = {}
        if m == 'auto':
            res, elapsed = auto, t_auto
            variants['published'] = res.adjustment
        else:
            t0 = time.perf_counter()
            res = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings(m), s,
                            kinematics=prob.kinematics, reference=reference)
            elapsed = time.perf_counter() - t0
            alone = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings(m), s,
                              kinematics=prob.kinematics)
            variants['model alone'] = alone.adjustment
            variants['published'] = res.adjustment
        adj = res.adjustment
        if adj is None or not res.success:
            out[m] = dict(failed=res.message)
            continue
        out[m] = dict(sigma_px=res.pixel_sigma, source=res.noise_source,
                      chosen=(res.selection.settings.model if res.selection else m),
                      uncertainty=res.uncertainty, time_s=elapsed)
        for key, a in variants.items():
            if a is None:
                continue
            z = {}
            for name, e in a.cameras.items():
                for k, v in z_scores(e.camera, e.std, truth[name]).items():
                    z.setdefault(k, []).append(float(v))
            cams = a.camera_list()
            pred, _, seen = triangulation_covariance(cams, a.covariance, a.parameter_names,
                                                     prob.test_points)
            uv = [np.where(seen[:, None] >= 2, u, np.nan) for u in uv_true]
            for j, c in enumerate(cams):
                uv[j][~c.in_front(prob.test_points)] = np.nan
            X = triangulate(cams, uv)
            err = np.linalg.norm(X - prob.test_points, axis=1)
            ok = np.isfinite(err) & (seen >= 2)
            out[m][key] = dict(z=z, predicted_mm=rms_error_mm(pred[ok]),
                               measured_mm=float(1e3 * np.sqrt(np.mean(err[ok] ** 2))))
    return scenario, seed, out


def summarise(cases, model, variant='published'):
    """Pool one scenario's model over the seeds (``variant``: published or model alone)."""
    runs = [c[model] for c in cases if model in c and variant in c[model]]
    if not runs:
        return None
    row = {}
    every = []
    for g, keys in GROUPS.items():
        v = np.array([x for r in runs for k in keys for x in r[variant]['z'].get(k, [])])
        row[g] = float(np.sqrt(np.mean(v ** 2))) if v.size else float('nan')
        every.append(v)
    v = np.concatenate(every)
    row.update(rms_z=float(np.sqrt(np.mean(v ** 2))), within1=float(np.mean(np.abs(v) < 1)),
               within2=float(np.mean(np.abs(v) < 2)), n_z=int(v.size),
               sigma_px=float(np.median([r['sigma_px'] for r in runs])),
               predicted_mm=float(np.sqrt(np.mean([r[variant]['predicted_mm'] ** 2
                                                   for r in runs]))),
               measured_mm=float(np.sqrt(np.mean([r[variant]['measured_mm'] ** 2
                                                  for r in runs]))),
               seeds=len(runs), failed=sum(1 for c in cases if 'failed' in c.get(model, {})),
               time_s=float(np.mean([r['time_s'] for r in runs])))
    if model == 'auto':
        chosen = [r['chosen'] for r in runs]
        row['chosen'] = {m: chosen.count(m) for m in sorted(set(chosen))}
    return row


def main():
    p = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    p.add_argument('--seeds', type=int, default=20)
    p.add_argument('--n', type=int, default=300)
    p.add_argument('--scenarios', nargs='+', default=list(SCENARIOS))
    p.add_argument('--models', nargs='+', default=list(MODELS))
    p.add_argument('--jobs', type=int, default=2)
    p.add_argument('--no-write', action='store_true')
    args = p.parse_args()
    jobs = [(sc, args.n, seed, args.models) for sc in args.scenarios for seed in range(args.seeds)]
    t0 = time.perf_counter()
    with Pool(args.jobs) as pool:
        results = pool.map(run_case, jobs, chunksize=1)
    by = {}
    for sc, seed, out in results:
        by.setdefault(sc, []).append(out)
    rows, raw = [], {}
    for sc in args.scenarios:
        for m in args.models:
            for variant in ('model alone', 'published'):
                r = summarise(by[sc], m, variant)
                if r is None:
                    continue
                raw.setdefault(sc, {}).setdefault(m, {})[variant] = r
                label = m if m != 'auto' else 'auto (' + ', '.join(
                    f'{k} {v}' for k, v in r['chosen'].items()) + ')'
                rows.append([sc, label, variant, f'{r["sigma_px"]:.3f}'] +
                            [f'{r[g]:.2f}' for g in GROUPS] +
                            [f'{r["rms_z"]:.2f}', f'{100 * r["within1"]:.0f}',
                             f'{100 * r["within2"]:.0f}', f'{r["predicted_mm"]:.3f}',
                             f'{r["measured_mm"]:.3f}'])
    md = [
        '## Uncertainty: reported standard deviations against the truth (bench/uncertainty.py)',
        '',
        f'Point level, N = {args.n} robot points, {args.seeds} seeds per scenario, image noise '
        f'{PIXEL_SIGMA} px, every model with its image noise estimated (the node\'s default; '
        '"sigma px": the median estimate). z = (estimate - truth) / reported std, RMS over '
        'every camera and seed (1: honest; above: overconfident; below: too cautious); '
        '"in 1/2 sigma": % of all z within 1 and 2 (68 and 95 for a normal). Triangulation: '
        'RMS 3-D error (mm) of 500 fresh markers triangulated from their exact projections, '
        'as the reported covariance predicts it and as measured. Truth in the robot\'s own '
        'base frame. "published": what the node and the CLI report (a single model\'s '
        'covariance widened under the prior auto chooses on the same data, where its own '
        'prior leaves arm errors undescribed); "model alone": the adjustment\'s own '
        f'covariance. {time.perf_counter() - t0:.0f} s on {args.jobs} processes.',
        '',
        table(['scenario', 'model', 'covariance', 'sigma px'] + [f'z {g}' for g in GROUPS] +
              ['RMS z', 'in 1 sigma %', 'in 2 sigma %', 'predicted mm', 'measured mm'], rows),
        '',
        f'Measured on {machine()}.',
    ]
    text = '\n'.join(md)
    print(text)
    if not args.no_write:
        write_section('uncertainty', text)
        write_json('uncertainty', dict(rows=raw, seeds=args.seeds, n=args.n,
                                       machine=machine()))


if __name__ == '__main__':
    main()
