"""
Accuracy of every noise model on a simulated PUMA 560 cell.

Point level: joint configurations drawn over a teleoperated arm's ranges whose nominal marker is
in the workspace and inside every image; the true marker comes from the simulator's true robot
(:mod:`armcal_ros.sim.true_robot`, scenarios of :mod:`armcal_ros.sim.cell`), the robot's
measurement is the nominal forward kinematics, the cameras see the true marker (where the links do
not hide it) with 0.3 px noise.  Scored by triangulating 500 fresh true markers with the
estimated cameras (their true, noise-free projections).

Models: oracle (true points, fixed), fixed, independent, correlated and kinematic at their
documented defaults, and the evidence-tuned ones from the ``auto`` search: correlated*,
kinematic* and hybrid*, each the candidate ``auto`` would choose were that the only model
(``ModelSelection.choice_of``: for hybrid the Occam rule prefers its limits, field off =
kinematic or kinematic part off = correlated, unless the full hybrid gains more than the margin
and its held-out check does not reject it), and auto (the chosen model, refined).  A reference,
not a model: kinematic-true, the kinematic model with the simulator's own geometric error
sigmas as its prior (the right prior, which no estimator is given) and s_n = 0.02 mm: the best
the kinematic parameterisation can do.

Columns: absolute error (mm, robot base frame, against the raw true markers); abs-observable
(mm): the absolute error against the canonical truth, the same for every model.  Some kinematic
errors move the marker, for every joint configuration, by one rigid motion of the base frame:
the base joint's origin errors and offset (the simulator draws them: 0.3 mm and 0.03 deg per
axis, 0.05 deg offset), joint 2's origin translation along and rotation about the base axis,
and the redundant directions that move nothing.  The cameras are fixed in the world, so such
an error is the same data as the cameras moved by the inverse motion: no estimator can see it.
:func:`armcal_ros.core.kinematic_prior.base_motion_gauge` finds that subspace U of the 48
error parameters (the null space of the error Jacobian with the six rigid-motion generators
projected out, over 500 configurations across the URDF limits; 29 dimensions on the PUMA, 19
observable), and the canonical truth is the true arm with its errors replaced by their
minimum-prior-norm representative (the prior-whitened projection onto U removed, prior = the
kinematic model's default sigmas).  Non-geometric errors and bias fields are kept whole.
What is removed is one rigid motion of the whole cell, reported as "removed mm" (RMS over the
test markers).  The oracle, given the true points, sits in the raw frame: n/a there.
shape (mm, after the best similarity); camera-centre (mm), focal (%), test reprojection (px),
solve time of the model stage (s; for auto the whole search).

Seed spread: the five-seed mean of a ratio of shape errors scatters, so the geometric shape
ratio of kinematic-true and kinematic* to the oracle is also measured over ``--floor-seeds``
(20) seeds at N = 1000, with the standard error of the per-seed ratio.

Usage: python bench/accuracy.py [--sizes 300 1000] [--seeds 5] [--scenarios ...]
[--floor-seeds 20] [--no-write].  Writes docs/BENCHMARKS.md (section "accuracy") and
docs/bench/accuracy.json unless --no-write.
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
from armcal_ros.core.kinematic_prior import (base_motion_gauge, KinematicData,  # noqa: E402
                                             kinematic_sigmas)
from armcal_ros.core.model_selection import select_model  # noqa: E402
from armcal_ros.core.priors import PriorSettings  # noqa: E402
from armcal_ros.sim.cell import SimSettings  # noqa: E402
from armcal_ros.sim.robot_points import make_robot_problem  # noqa: E402
from armcal_ros.sim.true_robot import (ERROR_MODELS, geometric_error_sigmas,  # noqa: E402
                                       TrueRobot)

SCENARIOS = ('geometric', 'nongeometric', 'gp-prior', 'mixed')
MODELS = ('oracle', 'kinematic-true', 'fixed', 'independent', 'correlated', 'kinematic',
          'correlated*', 'kinematic*', 'hybrid*', 'auto')
#: References that know part of the truth: excluded from "best model".
REFERENCES = ('oracle', 'kinematic-true')
#: The models (fixed excluded) among which "best" is taken; ESTIMATORS without auto.
ESTIMATORS = tuple(m for m in MODELS if m not in REFERENCES + ('fixed',))
#: The seed-spread check of the geometric shape ratio (``--floor-seeds``).
FLOOR_N = 1000
#: Per-point sigma of the kinematic-true reference (the linearisation error is ~1 um).
TRUE_PRIOR_POINT_SIGMA = 0.02e-3
PIXEL_SIGMA = 0.3


GAUGE_CONFIGURATIONS = 500
_GAUGES = {}


def gauge_of(chain, point):
    """Return the base-motion gauge of ``chain`` with the marker at ``point`` (cached)."""
    key = (id(chain), tuple(point))
    if key not in _GAUGES:
        q = chain.sample_configurations(GAUGE_CONFIGURATIONS, np.random.default_rng(0))
        _GAUGES[key] = base_motion_gauge(chain.jacobian_errors(q, point), chain.fk(q, point),
                                         kinematic_sigmas(chain.error_names))
    return _GAUGES[key]


def observable_truth(prob):
    """Return the canonical true test markers: the unobservable error part removed."""
    r = prob.robot
    canonical = gauge_of(r.chain, r.point).canonical(r.errors)
    clean = TrueRobot(r.chain, r.point, canonical, r.periodic_amplitude, r.periodic_phase,
                      r.compliance, r.bias_field, r.gravity)
    return clean.marker(prob.test_q)


def score(cams, prob, truth_obs):
    """Score a list of cameras; returns a dict of numbers."""
    est = {c.name: c for c in cams}
    sc = score_cameras(est, prob.truth, prob.test_points)
    names = [c.name for c in prob.cameras]
    uv = [prob.truth[k].project(prob.test_points) for k in names]
    X = triangulate([est[k] for k in names], uv)
    ok = np.all(np.isfinite(X), axis=1)
    observable = 1e3 * absolute_error(X[ok], truth_obs[ok])
    return dict(absolute_mm=sc.absolute_mm, abs_observable_mm=observable,
                shape_mm=sc.shape_mm, centre_mm=sc.centre_mm, focal_pct=sc.focal_pct,
                reprojection_px=sc.reprojection_px)


def true_prior(prob, error_model='joint-origin'):
    """Return the kinematic data with the simulator's geometric error sigmas (true prior)."""
    s = SimSettings()
    sigma = geometric_error_sigmas(prob.robot.chain, s.offset_deg, s.translation_mm,
                                   s.rotation_deg, s.tip_translation_mm, error_model)
    return KinematicData(prob.kinematics.jacobian, prob.kinematics.names, sigma)


def run_case(scenario, n, seed, error_model='joint-origin'):
    """Run every model on one problem."""
    prob = make_robot_problem(scenario, n, seed, pixel_sigma=PIXEL_SIGMA,
                              settings=SimSettings(error_model=error_model))
    truth_obs = observable_truth(prob)
    s = SolverSettings(pixel_sigma=PIXEL_SIGMA)
    out = {}
    t = time.perf_counter()
    fixed = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)
    t_fixed = time.perf_counter() - t
    cams0, inl = fixed.adjustment.camera_list(), fixed.adjustment.inliers
    out['fixed'] = dict(score(cams0, prob, truth_obs), time_s=t_fixed)
    orc = calibrate(prob.specs, prob.true_points, prob.obs, PriorSettings('fixed'), s)
    out['oracle'] = dict(score(orc.adjustment.camera_list(), prob, truth_obs),
                         time_s=orc.time_s)
    res = adjust(cams0, prob.measured, prob.obs,
                 PriorSettings('kinematic', point_sigma=TRUE_PRIOR_POINT_SIGMA), s, inliers=inl,
                 kinematics=true_prior(prob, error_model))
    out['kinematic-true'] = dict(score(res.camera_list(), prob, truth_obs), time_s=res.time_s,
                                 log_evidence=res.log_evidence)
    for m in ('independent', 'correlated', 'kinematic'):
        res = adjust(cams0, prob.measured, prob.obs, PriorSettings(m), s, inliers=inl,
                     kinematics=prob.kinematics if m == 'kinematic' else None)
        out[m] = dict(score(res.camera_list(), prob, truth_obs), time_s=res.time_s,
                      log_evidence=res.log_evidence)
    t = time.perf_counter()
    sel = select_model(cams0, prob.measured, prob.obs, PriorSettings(), s, prob.kinematics,
                       inl)
    t_auto = time.perf_counter() - t
    for m in ('correlated', 'kinematic', 'hybrid'):
        b = sel.choice_of(m)
        out[m + '*'] = dict(score(b.cameras, prob, truth_obs), time_s=b.time_s,
                            log_evidence=b.log_evidence, holdout_px=b.holdout_px,
                            label=b.label())
    out['auto'] = dict(score(sel.result.camera_list(), prob, truth_obs), time_s=t_auto,
                       chosen=sel.settings.model, label=sel.choice_of(sel.settings.model).label(),
                       reason=sel.reason, holdout_checks=sel.holdout_checks)
    out['bias_rms_mm'] = 1e3 * float(np.sqrt(np.mean(np.sum(prob.bias ** 2, axis=1))))
    out['removed_mm'] = 1e3 * float(np.sqrt(np.mean(np.sum((prob.test_points - truth_obs) ** 2,
                                                           axis=1))))
    return out


def floor_case(n, seed, error_model='joint-origin'):
    """Shape error (mm) of oracle, kinematic-true and kinematic* on one geometric problem."""
    prob = make_robot_problem('geometric', n, seed, pixel_sigma=PIXEL_SIGMA,
                              settings=SimSettings(error_model=error_model))
    s = SolverSettings(pixel_sigma=PIXEL_SIGMA)
    fixed = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)
    cams0, inl = fixed.adjustment.camera_list(), fixed.adjustment.inliers
    orc = calibrate(prob.specs, prob.true_points, prob.obs, PriorSettings('fixed'), s)
    kt = adjust(cams0, prob.measured, prob.obs,
                PriorSettings('kinematic', point_sigma=TRUE_PRIOR_POINT_SIGMA), s, inliers=inl,
                kinematics=true_prior(prob, error_model))
    sel = select_model(cams0, prob.measured, prob.obs, PriorSettings(), s, prob.kinematics,
                       inl, models=['kinematic'], holdout=False)

    def shape(cams):
        return score_cameras({c.name: c for c in cams}, prob.truth, prob.test_points).shape_mm
    return {'oracle': shape(orc.adjustment.camera_list()), 'kinematic-true': shape(
        kt.camera_list()), 'kinematic*': shape(sel.choice_of('kinematic').cameras)}


def floor_table(floor):
    """Markdown lines for the seed-spread check of the geometric shape ratio."""
    o = np.array([c['oracle'] for c in floor])
    lines = ['', f'Spread over seeds of the geometric shape ratio (N = {FLOOR_N}, seeds 0-'
             f'{len(floor) - 1}; the first five are the seeds above): ratio of means, and mean '
             '+- standard error of the per-seed ratio.', '']
    rows = []
    for m in ('kinematic-true', 'kinematic*'):
        v = np.array([c[m] for c in floor])
        r = v / o
        for k, sl in ((5, slice(0, 5)), (len(floor), slice(None))):
            rows.append([m, k, f'{o[sl].mean():.4f}', f'{v[sl].mean():.4f}',
                         f'{v[sl].mean() / o[sl].mean():.3f}',
                         f'{r[sl].mean():.3f} +- {r[sl].std(ddof=1) / np.sqrt(r[sl].size):.3f}'])
    lines.append(table(['model', 'seeds', 'oracle shape mm', 'model shape mm', 'ratio of means',
                        'per-seed ratio'], rows))
    return lines


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
            for k in ('bias_rms_mm', 'removed_mm'):
                summary[f'{sc}/{n}/{k}'] = float(np.mean([c[k] for c in cases]))
            chosen = [c['auto']['label'] for c in cases]
            summary[f'{sc}/{n}/auto_choices'] = {x: chosen.count(x) for x in set(chosen)}
    return summary


def targets(summary, n):
    """Return the accuracy targets at N = n, as (name, value, limit, met) rows."""
    rows = []

    def g(sc, m, k):
        return summary.get(f'{sc}/{n}/{m}', {}).get(k, float('nan'))

    if f'geometric/{n}/fixed' in summary:
        best_abs = min(g('geometric', m, 'absolute_mm') for m in ESTIMATORS)
        rows.append(('geometric: best absolute / fixed absolute',
                     best_abs / g('geometric', 'fixed', 'absolute_mm'), 0.5))
        best_obs = min(g('geometric', m, 'abs_observable_mm') for m in ESTIMATORS)
        rows.append(('geometric: best abs-observable / fixed abs-observable (unobservable '
                     'base motion removed)',
                     best_obs / g('geometric', 'fixed', 'abs_observable_mm'), 0.5))
        best_shape = min(g('geometric', m, 'shape_mm') for m in ESTIMATORS)
        rows.append(('geometric: best shape / oracle shape',
                     best_shape / g('geometric', 'oracle', 'shape_mm'), 1.5))
        rows.append(('geometric (reference, not a model): kinematic-true shape / oracle shape',
                     g('geometric', 'kinematic-true', 'shape_mm') /
                     g('geometric', 'oracle', 'shape_mm'), 1.5))
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
        best = min(g(sc, m, 'shape_mm') for m in ESTIMATORS[:-1])
        rows.append((f'{sc}: auto shape / best model shape', g(sc, 'auto', 'shape_mm') / best,
                     1.05))
    return [(name, v, lim, bool(v <= lim)) for name, v, lim in rows]


def main(argv=None):
    """Run the benchmark, print the tables and write them to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--sizes', type=int, nargs='+', default=[300, 1000])
    ap.add_argument('--seeds', type=int, default=5)
    ap.add_argument('--scenarios', nargs='+', default=list(SCENARIOS))
    ap.add_argument('--floor-seeds', type=int, default=20,
                    help='seeds of the geometric shape-ratio spread check (0: skip)')
    ap.add_argument('--error-model', default='joint-origin', choices=ERROR_MODELS,
                    help='the simulator\'s geometric errors (sim/true_robot.py); dh = the '
                         'prototype\'s, written to the section accuracy-dh')
    ap.add_argument('--no-write', action='store_true',
                    help='print the tables only; leave docs/ untouched')
    args = ap.parse_args(argv)
    results = {}
    floor = []
    for seed in range(args.floor_seeds if 'geometric' in args.scenarios else 0):
        floor.append(floor_case(FLOOR_N, seed, args.error_model))
        print(f'floor seed={seed}: ' + ', '.join(f'{k} {v:.4f}' for k, v in floor[-1].items()),
              flush=True)
    for sc in args.scenarios:
        for n in args.sizes:
            for seed in range(args.seeds):
                t0 = time.perf_counter()
                results[f'{sc}/{n}/{seed}'] = run_case(sc, n, seed, args.error_model)
                a = results[f'{sc}/{n}/{seed}']['auto']
                checks = '; '.join(
                    f'{c["complex"]} vs {c["simpler"]}: {c["excess_px2"]:+.4f} +- '
                    f'{c["se_px2"]:.4f} px^2' + (' REJECTED' if c['rejected'] else '')
                    for c in a['holdout_checks'])
                print(f'{sc} N={n} seed={seed}: {time.perf_counter() - t0:.1f} s, auto chose '
                      f'{a["label"]}; held-out checks: {checks}', flush=True)
    summary = summarise(results, args.scenarios, args.sizes, args.seeds)
    dh = args.error_model == 'dh'
    md = ['## Accuracy of the noise models (bench/accuracy.py)' +
          (', the prototype\'s DH error model (`--error-model dh`)' if dh else ''), '']
    if dh:
        md += [DH_INTRO, '']
    md += ['PUMA 560 (Corke DH URDF) carrying a sphere marker, three 640x480 cameras (f ~ 800 px, '
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
           '(its candidates, no extra solve; the candidate `auto` would choose were that the '
           'only model, so for `hybrid*` the Occam rule prefers its limits, field off = '
           'kinematic or kinematic part off = correlated, unless the full hybrid gains more '
           'than 3 in log evidence and does not predict held-out points worse than that limit '
           'by more than one standard error of the paired difference over five folds); time of '
           'a `*` row is that one candidate\'s solve, of `auto` the whole search (about '
           'twenty-five adjustments plus the held-out fits: one fold for the best candidate of '
           'each model, all five for the pair the Occam check compares). `kinematic-true` is '
           'a reference, not a model: the kinematic model with the '
           'simulator\'s own geometric error sigmas as its prior (the true prior of the '
           'geometric scenario) and s_n = 0.02 mm, the best this parameterisation can do. '
           '`abs-observable`: absolute error against the canonical truth, whose kinematic errors '
           'have their unobservable part removed: the component (minimum prior norm, '
           '`core.kinematic_prior.base_motion_gauge`) in the 29-dimensional subspace of the 48 '
           'error parameters that moves the marker by one rigid motion of the base frame for '
           'every joint configuration (base joint origin and offset, joint 2 translation along '
           'and rotation about the base axis, redundant directions). Such an error is the same '
           'data as the cameras moved the other way, so no estimator can see it; `removed mm` '
           'below is the size of that rigid motion. Same truth for every model; n/a for the '
           'oracle, which is given the true points and so the raw frame.', '']
    rows = []
    for sc in args.scenarios:
        for n in args.sizes:
            for m in MODELS:
                v = summary[f'{sc}/{n}/{m}']
                mf = 'n/a' if m == 'oracle' else f'{v["abs_observable_mm"]:.3f}'
                rows.append([sc, n, m, f'{v["absolute_mm"]:.3f}', mf,
                             f'{v["shape_mm"]:.3f}', f'{v["centre_mm"]:.2f}',
                             f'{v["focal_pct"]:.3f}', f'{v["reprojection_px"]:.3f}',
                             f'{v["time_s"]:.2f}'])
    md.append(table(['scenario', 'N', 'model', 'absolute mm', 'abs-observable mm', 'shape mm',
                     'centre mm', 'focal %', 'test reproj px', 'time s'], rows))
    md += ['', 'What `auto` chose (count over seeds), the bias size and the unobservable '
           'rigid motion removed from the truth for `abs-observable`:', '']
    crow = []
    for sc in args.scenarios:
        for n in args.sizes:
            ch = summary[f'{sc}/{n}/auto_choices']
            crow.append([sc, n, f'{summary[f"{sc}/{n}/bias_rms_mm"]:.2f}',
                         f'{summary[f"{sc}/{n}/removed_mm"]:.2f}',
                         '; '.join(f'{k} x{v}' for k, v in sorted(ch.items()))])
    md.append(table(['scenario', 'N', 'bias RMS mm', 'removed mm', 'auto chose'], crow))
    for n in args.sizes:
        t = targets(summary, n)
        if t:
            md += ['', f'Accuracy targets at N = {n}:', '',
                   table(['target', 'measured', 'limit', 'met'],
                         [[a, f'{v:.3f}', f'{lim:g}', 'yes' if ok else '**no**']
                          for a, v, lim, ok in t])]
    if len(floor) >= 5:
        md += floor_table(floor)
    if dh:
        md += ['', DH_NOTES]
    else:
        md += WHY_MISSED
    text = '\n'.join(md)
    print(text)
    if args.no_write:
        return 0
    name = 'accuracy-dh' if dh else 'accuracy'
    write_section(name, text)
    write_json(name.replace('-', '_'), {'summary': summary, 'cases': results, 'floor': floor,
                                        'error_model': args.error_model, 'machine': machine()})
    return 0


#: Commentary of the default (joint-origin) run: why two targets are missed.
WHY_MISSED = [
    '', 'Why targets are missed, and what was tried (measured):', '',
    '- `geometric: best absolute / fixed absolute`: against the raw truth every model '
    'carries the unobservable rigid motion (`removed mm`), the same for all of them, so '
    'the ratio cannot approach 0.5; against the canonical truth (`abs-observable`, the '
    'fair comparison) the kinematic models are well under it.',
    '- `geometric: best shape / oracle shape`: `kinematic-true` (the kinematic model '
    'with the simulator\'s own error sigmas as its prior and s_n = 0.02 mm, i.e. the '
    'right prior, which no estimator is given) sits at the same ratio as `kinematic*`, '
    'and the kinematic model noise-free reaches 0.0003 mm: what is left is the variance '
    'of the 19 observable kinematic parameters estimated from the same images, not model '
    'error or a poor choice of hyperparameters. The five-seed mean is also at the mercy '
    'of the seeds: the per-seed ratio scatters by about 0.4 (standard error about 0.17 '
    'for five seeds; the spread table above), and over twenty seeds both stay clearly '
    'under 1.5.',
    '- `hybrid*` against the better of correlated and kinematic (met since hybrid\'s '
    'field is limited to local coherence lengths): `hybrid*` equals `kinematic*` (its '
    'field-off limit) unless a field gains more than the Occam margin in evidence. Before '
    'the limit (`model_selection.HYBRID_MAX_L_FRACTION`: L at most 1.5 x the samples\' '
    'RMS radius, 0.30 m here), seed 0 of `nongeometric` at N = 1000 took a field of '
    'L = 0.6 m that gained 4.3 in log evidence and even predicted held-out points '
    'slightly better (0.4332 against 0.4336 px RMS on paired folds), yet cost shape '
    '(0.183 against 0.168 mm; the row was 1.039): a field correlated across the whole '
    'workspace is close to a global smooth deformation, which trades with the cameras. '
    'The held-out check in the Occam rule (a more complex candidate must not predict '
    'held-out points worse than the simpler one it replaces by more than one standard '
    'error of the paired difference over five folds) overturned no choice here; it is '
    'kept as a safeguard (it rejects a kinematic model fed joint states that do not '
    'belong to the samples; `auto` takes about 2-3 s longer at N = 1000).',
    '- Not a target, but visible: `kinematic*` on `gp-prior`. The arm is exact there and '
    'the bias is a position field the kinematic model cannot represent; its evidence '
    'asks for ever wider kinematic sigmas to absorb it (up to the search bound, 8 x the '
    'defaults, on one seed), and so loose a prior lets the frame drift by tens of '
    'millimetres. It stays 240-680 log-evidence units below `correlated*` at N = 1000, '
    'so `auto` never chooses it.',
    '- The error model: with the prototype\'s DH errors instead (section below, '
    '`--error-model dh`) the shape target is met and the raw absolute ratio falls, but '
    'not to 0.5.']

DH_INTRO = ('The same benchmark with the simulator\'s `dh` error model, the errors of the '
            'estimator\'s first numpy prototype (per joint 0.05 deg angle offset, 0.3 mm in the '
            'link lengths a and d, 0.03 deg in the twist alpha; the first joint\'s origin is the '
            'base frame and carries none; marker mount 0.2 mm) instead of the default 6-DoF '
            'joint-origin errors (0.3 mm and 0.03 deg on every axis of every joint origin, the '
            'first included). Same seeds, cameras and configurations; only the error '
            'components differ. It separates what the estimators do from what the error model '
            'lets any estimator do: the default draws a larger rigid motion of the base, which '
            'no image can see, and error directions (y translations, y and z rotations) that '
            'add to what the kinematic model must estimate. `kinematic-true` has the DH sigmas '
            'as its prior here.')
DH_NOTES = ('With DH errors the unobservable part is the first joint\'s offset and joint 2\'s '
            'translation along the base axis (`removed mm` above), smaller than with the '
            'default errors; the raw absolute ratio of the best model is bounded below by it, '
            'since every model carries it. Compare the targets with those of the default run '
            'in the section *accuracy*.')


if __name__ == '__main__':
    sys.exit(main())
