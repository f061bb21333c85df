"""
Estimator benchmark: three cameras, robot bias drawn from the paper's correlated prior.

Scenario: bias sigma 1 mm per axis, coherence length 0.3 m, squared-exponential kernel,
0.3 px image noise, N = 100 / 300 / 1000 robot points, five seeds.  Scored by triangulating 500
fresh true points with the estimated cameras (their true projections, noise-free, so the score
measures the cameras alone).  Models: oracle (the true points given as fixed), fixed,
independent, correlated.

Speed, like with like: the `fixed` and `independent` problems (plain least squares, the same DLT
start, the same ftol, N = 100 / 1000 / 3000, one seed) solved by armcal's adjust() and by
library solvers that reach the same minimum: scipy.optimize.least_squares with the analytic
Jacobian, sparse (trf + LSMR) and dense (MINPACK lm) (bench/_scipy_reference.py), scipy with
finite differences (`fixed` only), and Ceres through pycolmap's bundle adjuster (bench/_ceres.py,
skipped without pycolmap).  Each row's final cost and focal lengths are compared with armcal's.

Profile: ``--profile --label NAME`` profiles adjust() at the largest speed size and keeps the
profile per label, so a checkout of an earlier commit (PYTHONPATH=that tree) and this one are
shown side by side.

Usage: python bench/solver.py [--sizes 100 300 1000] [--seeds 5] [--speed-sizes 100 1000 3000]
       python bench/solver.py --speed-only | --accuracy-only | --profile [--label before]
Prints the tables and writes docs/BENCHMARKS.md (sections "solver", "solver-speed",
"solver-profile") and docs/bench/solver.json, solver_speed.json, solver_profile_<label>.json.
Install pycolmap (pip install pycolmap; it brings pyceres) for the Ceres rows: a benchmark-only
dependency, never needed by the package or its tests.
"""

import argparse
import cProfile
import glob
import json
import os
import pstats
import subprocess
import sys
import time

# Single-threaded BLAS, as the engine solves (threaded OpenBLAS on 2 shared cores is erratic).
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402
from scipy.sparse import lil_matrix  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402
import _scipy_reference  # noqa: E402

try:
    import _ceres  # noqa: E402
    CERES_MISSING = ''
except ImportError as exc:   # pycolmap / pyceres absent: the Ceres rows are '-'
    _ceres = None
    CERES_MISSING = f'pycolmap not installed ({exc})'

from armcal_ros.core.adjustment import adjust, SolverSettings  # noqa: E402
from armcal_ros.core.calibration import calibrate  # noqa: E402
from armcal_ros.core.camera import project  # noqa: E402
from armcal_ros.core.evaluation import score_cameras  # noqa: E402
from armcal_ros.core.initialisation import initialise_camera  # noqa: E402
from armcal_ros.core.priors import PriorSettings  # noqa: E402
from armcal_ros.sim.synthetic import make_problem  # noqa: E402

MODELS = ('oracle', 'fixed', 'independent', 'correlated')
PIXEL_SIGMA = 0.3
#: The point prior of the `independent` speed problem (m), as in the accuracy part.
POINT_SIGMA = 0.0002
SPEED_MODELS = ('fixed', 'independent')
SOLVERS = ('armcal', 'armcal lm', 'scipy sparse', 'scipy dense', 'scipy fd', 'ceres')
SOLVER_LABELS = {
    'armcal': 'armcal adjust()',
    'armcal lm': 'armcal adjust(redundancy=False)',
    'scipy sparse': 'scipy trf, analytic sparse J (LSMR)',
    'scipy dense': 'scipy lm, analytic dense J',
    'scipy fd': 'scipy trf, finite differences',
    'ceres': 'Ceres (pycolmap bundle adjuster)',
}
#: LSMR tolerances of the scipy trf rows: at scipy's default (1e-6) the inexact steps stop trf
#: about 1e-6 (relative) above the minimum, which would compare solvers at different minima.
LSMR_OPTIONS = {'atol': 1e-10, 'btol': 1e-10}


def scipy_fixed(cams0, measured, obs, ftol):
    """
    Solve the fixed-model problem (cameras only, loss 'none') with scipy's TRF.

    The Jacobian by finite differences over its sparsity pattern (what a user without
    derivatives would do); the same objective, start and ftol as armcal.
    """
    nc = len(cams0)
    npc = 14   # fx fy cx cy k1 k2 p1 p2 rvec(3) t(3)
    x0 = np.concatenate([np.concatenate([c.intrinsics(), c.dist[:4], c.rvec, c.translation])
                         for c in cams0])
    groups = [np.flatnonzero(obs.camera == j) for j in range(nc)]
    m = len(obs)
    sparsity = lil_matrix((2 * m, nc * npc), dtype=int)
    for j, idx in enumerate(groups):
        for k in (0, 1):
            for i in idx:
                sparsity[2 * i + k, j * npc:(j + 1) * npc] = 1
    Xo = measured[obs.point]

    def fun(x):
        r = np.empty((m, 2))
        for j, idx in enumerate(groups):
            v = x[j * npc:(j + 1) * npc]
            R = Rotation.from_rotvec(v[8:11]).as_matrix()
            dist = np.array([v[4], v[5], v[6], v[7], 0.0])
            r[idx] = (project(v[:4], dist, R, v[11:14], Xo[idx]) - obs.uv[idx]) / PIXEL_SIGMA
        return r.ravel()

    t0 = time.perf_counter()
    sol = least_squares(fun, x0, method='trf', jac_sparsity=sparsity.tocsr(), x_scale='jac',
                        ftol=ftol, xtol=1e-8, gtol=1e-10, tr_options=LSMR_OPTIONS)
    elapsed = time.perf_counter() - t0
    cams = []
    for j, c0 in enumerate(cams0):
        v = sol.x[j * npc:(j + 1) * npc]
        cam = c0.copy()
        cam.set_intrinsics(v[:4])
        cam.dist = np.array([v[4], v[5], v[6], v[7], 0.0])
        cam.rotation = Rotation.from_rotvec(v[8:11]).as_matrix()
        cam.translation = v[11:14].copy()
        cams.append(cam)
    return elapsed, float(np.sum(sol.fun ** 2)), sol.nfev, sol.njev, cams


def start_cameras(prob):
    """Return the DLT start cameras every solver of the speed comparison starts from."""
    cams0 = []
    for j, spec in enumerate(prob.specs):
        sel = prob.obs.camera == j
        cams0.append(initialise_camera(spec.name, spec.width, spec.height,
                                       prob.measured[prob.obs.point[sel]],
                                       prob.obs.uv[sel], rng=np.random.default_rng(0)).camera)
    return cams0


def run_case(n, seed):
    """Run every model on one problem; return a dict of rows."""
    prob = make_problem(n, seed, bias_sigma=0.001, coherence_length=0.3,
                        pixel_sigma=PIXEL_SIGMA)
    settings = SolverSettings(pixel_sigma=PIXEL_SIGMA)
    out = {}
    for model in MODELS:
        pts = prob.true_points if model == 'oracle' else prob.measured
        prior = PriorSettings('fixed' if model == 'oracle' else model,
                              point_sigma=0.0002, bias_sigma=0.001, coherence_length=0.3)
        res = calibrate(prob.specs, pts, prob.obs, prior, settings)
        sc = score_cameras(res.cameras, prob.truth, prob.test_points)
        adj = res.adjustment
        fit_rms = float(np.sqrt(np.mean([e.rms_px ** 2 for e in adj.cameras.values()])))
        out[model] = dict(absolute_mm=sc.absolute_mm, shape_mm=sc.shape_mm,
                          centre_mm=sc.centre_mm, focal_pct=sc.focal_pct,
                          fit_rms_px=fit_rms, test_reprojection_px=sc.reprojection_px,
                          time_s=res.time_s, iterations=sum(s[2] for s in res.stages),
                          success=bool(res.success))
    return out


def objective(prob, model, cams, X):
    """
    Return armcal's plain objective F at (cams, X), computed the same way for every solver.

    F = sum |pi(c, X) - uv|^2 / s_px^2, plus sum |X - X^|^2 / s_pt^2 for `independent`: one
    function to score every solution, so that a cost difference is a difference of minima and
    not of bookkeeping (scipy's 0.5 |f|^2, Ceres' unscaled pixels).
    """
    F = 0.0
    for j, c in enumerate(cams):
        idx = np.flatnonzero(prob.obs.camera == j)
        d = c.project(X[prob.obs.point[idx]]) - prob.obs.uv[idx]
        F += float(np.sum(d * d)) / PIXEL_SIGMA ** 2
    if model == 'independent':
        F += float(np.sum((X - prob.measured) ** 2)) / POINT_SIGMA ** 2
    return F


def _best(fn, repeats):
    """Call fn() ``repeats`` times; return (best seconds, the last call's other outputs)."""
    best, out = float('inf'), None
    for _ in range(repeats):
        t, *out = fn()
        best = min(best, t)
    return best, out


def _row(prob, model, ref, seconds, iterations, cams, X, note=''):
    """Return one speed row: time, iterations, cost F and its agreement with armcal's."""
    F = objective(prob, model, cams, X)
    f = np.array([[c.fx, c.fy] for c in cams])
    return dict(time_s=seconds, iterations=iterations, cost=F,
                cost_rel=(F - ref['cost']) / ref['cost'],
                max_df_px=float(np.max(np.abs(f - ref['focal']))), note=note)


def speed_case(n, seed, repeats, dense_max_entries):
    """
    Time every solver on the `fixed` and `independent` problems of one seed, like with like.

    The same problem, DLT start, objective and ftol for every solver, each timed as the best of
    ``repeats`` runs; each row is scored with :func:`objective` against armcal's minimum (cost
    and focal lengths).  Returns {model: {solver: row or None}, 'sizes': ...}.
    """
    prob = make_problem(n, seed, bias_sigma=0.001, coherence_length=0.3,
                        pixel_sigma=PIXEL_SIGMA)
    cams0 = start_cameras(prob)
    plain = plain_settings()
    out = {'observations': len(prob.obs)}
    for model in SPEED_MODELS:
        prior = PriorSettings(model, point_sigma=POINT_SIGMA)
        rows = {}

        def ours_once():
            t0 = time.perf_counter()
            res = adjust(cams0, prob.measured, prob.obs, prior, plain)
            return time.perf_counter() - t0, res
        t, (res,) = _best(ours_once, repeats)
        cams = res.camera_list()
        ref = dict(cost=res.cost, focal=np.array([[c.fx, c.fy] for c in cams]))
        rows['armcal'] = _row(prob, model, ref, t, res.iterations, cams, res.points,
                              note=res.status)
        rows['armcal']['cost_reported'] = res.cost

        def lm_once():
            t0 = time.perf_counter()
            r = adjust(cams0, prob.measured, prob.obs, prior, plain, redundancy=False)
            return time.perf_counter() - t0, r
        t, (res,) = _best(lm_once, repeats)
        rows['armcal lm'] = _row(prob, model, ref, t, res.iterations, res.camera_list(),
                                 res.points, note=res.status)

        rp = _scipy_reference.ReferenceProblem(model, cams0, prob.measured, prob.obs,
                                               PIXEL_SIGMA, POINT_SIGMA)
        t, (sol,) = _best(lambda: _scipy_reference.solve(rp, plain.ftol, tr_options=LSMR_OPTIONS),
                          repeats)
        rows['scipy sparse'] = _row(prob, model, ref, t, sol.njev, rp.cameras(sol.x),
                                    rp.points(sol.x), note=f'nfev {sol.nfev}')
        entries = rp.n_rows * rp.size
        if entries <= dense_max_entries:
            t, (sol,) = _best(lambda: _scipy_reference.solve(rp, plain.ftol, dense=True),
                              repeats)
            rows['scipy dense'] = _row(prob, model, ref, t, sol.njev, rp.cameras(sol.x),
                                       rp.points(sol.x), note=f'nfev {sol.nfev}')
        else:
            rows['scipy dense'] = None
        out.setdefault('jacobian', {})[model] = [rp.n_rows, rp.size]
        if model == 'fixed':
            t, (cost, nfev, njev, cams) = _best(
                lambda: scipy_fixed(cams0, prob.measured, prob.obs, plain.ftol), repeats)
            rows['scipy fd'] = _row(prob, model, ref, t, njev, cams, prob.measured,
                                    note=f'nfev {nfev}')
        else:
            rows['scipy fd'] = None
        if _ceres is not None:
            t, (run, summary) = _best(
                lambda: _ceres.solve(model, cams0, prob.measured, prob.obs, PIXEL_SIGMA,
                                     POINT_SIGMA, plain.ftol), repeats)
            cs = summary.ceres_summary
            rows['ceres'] = _row(prob, model, ref, t,
                                 cs.num_successful_steps + cs.num_unsuccessful_steps,
                                 run.cameras(), run.points(), note=cs.message)
            # Ceres' own cost, converted: F = 2 C / s_px^2 (a check of the mapping).
            rows['ceres']['cost_reported'] = 2.0 * cs.final_cost / PIXEL_SIGMA ** 2
            rows['ceres']['linear_solver'] = str(cs.linear_solver_type_used)
        else:
            rows['ceres'] = None
        out[model] = rows
    return out


def speed_text(speed, sizes, repeats, dense_max_entries):
    """Return the markdown of the speed comparison (table and notes)."""
    rows = []
    skipped = []
    for n in sizes:
        case = speed[str(n)]
        for model in SPEED_MODELS:
            ours = case[model]['armcal']
            for solver in SOLVERS:
                r = case[model][solver]
                if r is None:
                    if solver == 'scipy fd' and model != 'fixed':
                        continue
                    mark = '-'
                    if solver == 'scipy dense':
                        m, p = case['jacobian'][model]
                        skipped.append(f'N = {n} {model}: J is {m} x {p} '
                                       f'({m * p * 8 / 1e9:.2f} GB), one QR ~{2.0 * m * p * p:.1e}'
                                       f' flops')
                        mark = '- (a)'
                    elif solver == 'ceres':
                        mark = '- (b)'
                    rows.append([n, model, SOLVER_LABELS[solver], mark, '', '', '', '', ''])
                    continue
                its = '' if r['iterations'] is None else f'{r["iterations"]}'
                ratio = r['time_s'] / ours['time_s']
                rows.append([n, model, SOLVER_LABELS[solver], f'{r["time_s"] * 1000:.1f}',
                             '1' if solver == 'armcal' else f'{ratio:.1f}', its,
                             f'{r["cost"]:.6f}',
                             '0' if solver == 'armcal' else f'{r["cost_rel"]:+.1e}',
                             '0' if solver == 'armcal' else f'{r["max_df_px"]:.1e}'])
    notes = [f'(a) not run: MINPACK\'s lm factors the dense J by an unblocked QR every '
             f'iteration, minutes per solve at these sizes (the row runs up to '
             f'{dense_max_entries:.0e} entries of J, --dense-max-entries): '
             + '; '.join(skipped) + '.'] if skipped else []
    if CERES_MISSING:
        notes.append(f'(b) {CERES_MISSING}.')
    md = ['### Solver speed, like with like', '',
          f'The `fixed` (cameras only: fx, fy, cx, cy, k1, k2, p1, p2, rotation, translation per '
          f'camera; points at the robot\'s measured positions) and `independent` (points too, '
          f'each under an isotropic {POINT_SIGMA * 1000:.1f} mm prior) problems of the bench '
          f'(3 cameras, one seed), plain squared loss, {PIXEL_SIGMA} px, from the same DLT '
          f'start, every solver stopping on the relative cost decrease 1e-8 (armcal\'s ftol; '
          f'the other tests tight). Cost: F = sum |r|^2 / s_px^2 (+ sum |X - X^|^2 / s_pt^2), '
          f'computed by one function from each solver\'s final cameras and points; '
          f'"cost diff" is (F - F_armcal) / F_armcal and "max df" the largest focal-length '
          f'difference to armcal (px): the rows are at the same minimum. '
          f'Time: best of {repeats} runs, single-threaded (BLAS and Ceres), '
          f'on a machine doing nothing else. armcal: the whole adjust() call (setup, '
          f'LM, then its camera covariance and leverages); with redundancy=False the same '
          f'without the leverages (the covariance S^-1 stays): the work Ceres\' solve() does. '
          f'scipy: the least_squares() call '
          f'(analytic Jacobian from project_with_jacobians; LSMR at atol = btol = 1e-10, as '
          f'scipy\'s default 1e-6 stops ~1e-6 above the minimum). Ceres: the adjuster\'s '
          f'solve() only (building the reconstruction and its cost functions is not timed); '
          f'COLMAP\'s OPENCV model, no intrinsic held, no gauge fixed, trivial loss, DENSE_SCHUR '
          f'as COLMAP picks for 3 images. Iterations: armcal\'s LM iterations, scipy\'s '
          f'Jacobian evaluations, Ceres\' iterations. Measured on {machine()}.', '',
          table(['N', 'model', 'solver', 'time ms', 'x armcal', 'iterations', 'cost F',
                 'cost diff (rel)', 'max df px'], rows)]
    if notes:
        md += [''] + notes
    return '\n'.join(md)


def run_speed(sizes, seed, repeats, dense_max_entries):
    """Run the speed comparison for ``sizes``; return (results by size, markdown)."""
    speed = {}
    for n in sizes:
        t0 = time.perf_counter()
        speed[str(n)] = speed_case(n, seed, repeats, dense_max_entries)
        print(f'speed N={n} done in {time.perf_counter() - t0:.1f} s', flush=True)
    return speed, speed_text(speed, sizes, repeats, dense_max_entries)


def plain_settings():
    """Return armcal's settings for the speed problem: plain squared loss, no gating."""
    return SolverSettings(pixel_sigma=PIXEL_SIGMA, loss='none', gate_min_px=1e9)


def _package_label():
    """Name the armcal_ros being measured: its tree's commit, and whether it has edits."""
    import armcal_ros
    tree = os.path.dirname(os.path.dirname(os.path.abspath(armcal_ros.__file__)))

    def git(*a):
        return subprocess.run(['git', *a], cwd=tree, capture_output=True, text=True).stdout
    rev = git('rev-parse', '--short', 'HEAD').strip() or 'unknown'
    dirty = bool(git('status', '--porcelain', '--', 'armcal_ros').strip())
    return rev + (' + edits' if dirty else '')


def profile_case(n, seed, top=8):
    """
    Profile one adjust() per model on the speed problem of size ``n``: the top entries.

    cProfile's own time per function (tottime), sorted, with its share of the call; one warm
    call first, so imports and caches are not counted.  Run once per tree (``--label``) to
    put the profile before and after a change side by side.
    """
    prob = make_problem(n, seed, bias_sigma=0.001, coherence_length=0.3,
                        pixel_sigma=PIXEL_SIGMA)
    cams0 = start_cameras(prob)
    plain = plain_settings()
    out = {}
    for model in SPEED_MODELS:
        prior = PriorSettings(model, point_sigma=POINT_SIGMA)
        adjust(cams0, prob.measured, prob.obs, prior, plain)
        pr = cProfile.Profile()
        pr.enable()
        res = adjust(cams0, prob.measured, prob.obs, prior, plain)
        pr.disable()
        st = pstats.Stats(pr)
        entries = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:top]
        out[model] = dict(total_s=st.total_tt, iterations=res.iterations, top=[
            dict(function=f'{os.path.basename(f)}:{line} {name}', calls=v[1], tottime_s=v[2])
            for (f, line, name), v in entries])
    return out


def profile_text(profiles, n):
    """Return the markdown of every stored profile (one table per model, trees side by side)."""
    md = [f'### Where adjust() spends its time (bench/solver.py --profile, N = {n})', '',
          'cProfile of one warm adjust() call per model (armcal\'s plain problem of the speed '
          'table), the top entries by own time; each tree measured with `--profile --label` '
          'from a checkout of it. cProfile\'s overhead inflates the totals.']
    for model in SPEED_MODELS:
        for label, prof in profiles.items():
            p = prof['profile'][model]
            rows = [[e['function'], e['calls'], f'{e["tottime_s"] * 1000:.1f}',
                     f'{100.0 * e["tottime_s"] / p["total_s"]:.0f} %'] for e in p['top']]
            md += ['', f'`{model}`, {label} ({prof["package"]}, {prof["machine"]}): '
                   f'{p["total_s"] * 1000:.0f} ms in {p["iterations"]} iterations', '',
                   table(['function', 'calls', 'own ms', 'share'], rows)]
    return '\n'.join(md)


def main(argv=None):
    """Run the benchmark, print the tables and write them to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--sizes', type=int, nargs='+', default=[100, 300, 1000])
    ap.add_argument('--seeds', type=int, default=5)
    ap.add_argument('--speed-sizes', type=int, nargs='+', default=[100, 1000, 3000])
    ap.add_argument('--speed-seed', type=int, default=0)
    ap.add_argument('--repeats', type=int, default=5, help='timing: best of this many runs')
    ap.add_argument('--dense-max-entries', type=float, default=3e6,
                    help='run the dense-Jacobian scipy row only up to this many entries of J')
    ap.add_argument('--speed-only', action='store_true',
                    help='run only the speed comparison (section "solver-speed")')
    ap.add_argument('--no-write', action='store_true', help='print only; write nothing')
    ap.add_argument('--accuracy-only', action='store_true',
                    help='run only the accuracy part (section "solver")')
    ap.add_argument('--profile', action='store_true',
                    help='profile adjust() at the largest speed size (section "solver-profile")')
    ap.add_argument('--label', default='after',
                    help='with --profile: the name of this tree\'s profile (e.g. before)')
    args = ap.parse_args(argv)
    if args.profile:
        n = max(args.speed_sizes)
        prof = dict(profile=profile_case(n, args.speed_seed), package=_package_label(),
                    machine=machine(), n=n)
        path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                            'docs', 'bench', f'solver_profile_{args.label}.json')
        if not args.no_write:
            write_json(f'solver_profile_{args.label}', prof)
        profiles = {}
        for f in sorted(glob.glob(path.replace(f'_{args.label}.json', '_*.json'))):
            with open(f) as fh:
                profiles[os.path.basename(f)[len('solver_profile_'):-5]] = json.load(fh)
        profiles[args.label] = prof
        profiles = dict(sorted(profiles.items(), key=lambda kv: kv[0] != 'before'))
        text = profile_text(profiles, n)
        print(text)
        if not args.no_write:
            write_section('solver-profile', text)
        return 0
    if args.speed_only or not args.accuracy_only:
        speed, text = run_speed(args.speed_sizes, args.speed_seed, args.repeats,
                                args.dense_max_entries)
        print(text)
        if not args.no_write:
            write_section('solver-speed', '## Solver speed (bench/solver.py --speed-only)\n\n'
                          + text)
            write_json('solver_speed', {'speed': speed, 'machine': machine()})
        if args.speed_only:
            return 0
    results = {}
    for n in args.sizes:
        for seed in range(args.seeds):
            t0 = time.perf_counter()
            results[f'{n}/{seed}'] = run_case(n, seed)
            print(f'N={n} seed={seed} done in {time.perf_counter() - t0:.1f} s', flush=True)
    rows = []
    summary = {}
    for n in args.sizes:
        cases = [results[f'{n}/{s}'] for s in range(args.seeds)]
        for model in MODELS:
            mean = {k: float(np.mean([c[model][k] for c in cases]))
                    for k in cases[0][model] if k != 'success'}
            mean['solved'] = sum(c[model]['success'] for c in cases)
            summary[f'{n}/{model}'] = mean
            rows.append([n, model, f'{mean["absolute_mm"]:.3f}', f'{mean["shape_mm"]:.3f}',
                         f'{mean["centre_mm"]:.2f}', f'{mean["focal_pct"]:.3f}',
                         f'{mean["fit_rms_px"]:.3f}', f'{mean["test_reprojection_px"]:.3f}',
                         f'{mean["time_s"]:.2f}', f'{mean["solved"]}/{len(cases)}'])
    ratio300 = (summary['300/correlated']['absolute_mm'] / summary['300/fixed']['absolute_mm']
                if '300/fixed' in summary else float('nan'))
    md = ['## Estimator (bench/solver.py)', '',
          f'Three cameras (640x480, f ~ 800 px, k1 ~ -0.15) at 1.5-2 m; robot bias drawn from the '
          f'correlated prior (1 mm per axis, L = 0.3 m); {PIXEL_SIGMA} px image noise; mean of '
          f'{args.seeds} seeds. Errors from triangulating 500 fresh true points with the '
          f'estimated cameras. fit rms: the adjustment\'s own inlier residual; test reproj: '
          f'true points projected by the estimated vs true cameras. Time: the whole calibrate() '
          f'(DLT, fixed, then the model); BLAS single-threaded. Measured on {machine()}.', '',
          table(['N', 'model', 'absolute mm', 'shape mm', 'centre mm', 'focal %', 'fit rms px',
                 'test reproj px', 'time s', 'solved'], rows), '',
          f'Correlated / fixed absolute error at N = 300: **{ratio300:.2f}** (target <= 0.75).',
          '', 'Speed against scipy and Ceres on the same problems: section "solver-speed" '
          '(`--speed-only`).']
    text = '\n'.join(md)
    print(text)
    if not args.no_write:
        write_section('solver', text)
        write_json('solver', {'summary': summary, 'cases': results, 'machine': machine()})
    return 0


if __name__ == '__main__':
    sys.exit(main())
