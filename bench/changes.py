"""
Cameras that move: detection, delay and recovery of knocked and refocused cameras.

Sessions from the simulator (300 s; the demo cell under its nongeometric errors, ur5-2cam and
desk-4cam under theirs) with one camera knocked (0.1-2 deg about a random axis, with 2-10 mm)
or refocused (0.5 % and 2 % of focal length) at a random time in the middle third; 5 seeds.
The samples are the dwells at point level (:func:`~armcal_ros.sim.point_level.dwell_observations`,
0.02 px of pooled image noise: what the front end's pooled detections show on these cells,
bench/cells.py), fed in time order to the engine as the offline pipeline does
(``solve_if_grown``), with the `kinematic` model.  Per case: detected (the right camera), the
delay (the changed camera's views and seconds from the change to the declaration), the
changed camera's final error against its new truth (rotation, centre, focal length) beside the
same from a calibration of the post-change samples alone, and the worst unchanged camera's
rotation error beside that of the same session without the change.  False alarms: any declared
change (or arm alarm) on unchanged sessions: the bundled demo bag through the whole pipeline,
the demo cell over 20 seeds, each other cell over 5.

Usage: python bench/changes.py [--seeds 5] [--processes 2] [--table-only]
(``--table-only`` tabulates docs/bench/changes.json again, as measured: no new sessions.)
"""

import argparse
import json
import os
import sys
from multiprocessing import Pool

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

import numpy as np  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from armcal_ros.core.kinematic_prior import KinematicData  # noqa: E402
from armcal_ros.core.priors import PriorSettings  # noqa: E402
from armcal_ros.engine import CalibrationEngine, EngineSettings  # noqa: E402
from armcal_ros.frontend.samples import Observation, Sample  # noqa: E402
from armcal_ros.params import defaults  # noqa: E402
from armcal_ros.sim.cell import CameraChange, simulate_cell  # noqa: E402
from armcal_ros.sim.cells import CELLS  # noqa: E402
from armcal_ros.settings import solver_settings  # noqa: E402
from armcal_ros.sim.point_level import dwell_observations  # noqa: E402

DURATION = 300.0
#: The engine's model: what `auto` chooses on these cells or its runner-up (BENCHMARKS.md,
#: accuracy-bag and cells), without auto's search at every solve.
MODEL = 'kinematic'
PIXEL_SIGMA = 0.02
#: The solver as the node's default parameters build it: the image noise estimated from the
#: residuals (the covariances the change test predicts with are then at the images' noise).
SOLVER = solver_settings(defaults())
CELL_SCENARIOS = {'puma-3cam': 'nongeometric', 'ur5-2cam': 'geometric', 'desk-4cam': 'mixed'}
KNOCKS_DEG = (0.1, 0.25, 0.5, 1.0, 2.0)
FOCUS_PERCENT = (0.5, 2.0)
FALSE_ALARM_SEEDS = {'puma-3cam': 20, 'ur5-2cam': 5, 'desk-4cam': 5}


def samples_of(sim, seed, after_ns=None):
    """Return the session's samples in time order (only those from ``after_ns`` on if given)."""
    obs = dwell_observations(sim, PIXEL_SIGMA, np.random.default_rng([seed, 77]))
    out = []
    for k, t in enumerate(obs.stamp_ns):
        if not obs.uv[k] or (after_ns is not None and t < after_ns):
            continue
        out.append(Sample(obs.nominal[k], {
            n: Observation(uv[None], [0], n_frames=10, spread_px=PIXEL_SIGMA, stamp_ns=int(t))
            for n, uv in obs.uv[k].items()}, stamp_ns=int(t), q=obs.q[k]))
    return out


def run_engine(sim, samples, detect=True):
    """Feed ``samples`` in time order, solving as they double; return the engine."""
    names = [c.name for c in sim.cameras]
    chain, place = sim.chain, np.asarray(sim.settings.marker_offset, float)

    def kinematics(Q, at=place):
        return KinematicData(chain.jacobian_errors(Q, at), chain.error_names)
    eng = CalibrationEngine(EngineSettings(names, PriorSettings(MODEL), SOLVER,
                                           min_samples=20, detect_changes=detect),
                            kinematics_fn=kinematics)
    for c in sim.cameras:
        eng.set_image_size(c.name, c.width, c.height)
    eng.feed(samples)
    eng.solve()
    return eng


def camera_error(est, truth):
    """Return (rotation deg, centre mm, focal %) of ``est`` against ``truth``."""
    ang = np.degrees(np.linalg.norm(Rotation.from_matrix(est.rotation @ truth.rotation.T)
                                    .as_rotvec()))
    return (float(ang), float(1e3 * np.linalg.norm(est.center - truth.center)),
            float(100.0 * (est.fx / truth.fx - 1.0)))


def session(cell, seed, change=None):
    """Simulate one session of ``cell`` (with ``change``, a CameraChange or None)."""
    c = CELLS[cell]
    settings = c.sim_settings(duration=DURATION,
                              camera_changes=(change,) if change is not None else ())
    return simulate_cell(CELL_SCENARIOS[cell], seed, DURATION, settings)


def change_case(args):
    """One knocked or refocused session: detection, delay and errors."""
    cell, seed, kind, size = args
    rng = np.random.default_rng([seed, 31, int(size * 100), kind == 'focus'])
    names = list(CELLS[cell].sim_settings().camera_names)
    cam = names[int(rng.integers(len(names)))]
    t = float(rng.uniform(DURATION / 3, 2 * DURATION / 3))
    change = (CameraChange(cam, t, rotation_deg=size, translation_mm=float(rng.uniform(2, 10)))
              if kind == 'knock' else CameraChange(cam, t, focal_percent=size))
    sim = session(cell, seed, change)
    t_ns = sim.start_ns + int(t * 1e9)
    samples = samples_of(sim, seed)
    # Counted before the run: the store takes the samples and retires views from them.
    views = [s.stamp_ns for s in samples if s.stamp_ns >= t_ns and cam in s.observations]
    eng = run_engine(sim, samples)
    final = {c.name: c for c in sim.final_cameras}
    recs = [r for r in eng.changes.records if r.kind in ('camera', 'arm')]
    # The change point is resolved to the camera's views: one placed at its last view before
    # the change (or within 2 s of it) is this change, declared after it.
    before = [s.stamp_ns for s in samples if s.stamp_ns < t_ns and cam in s.observations]
    earliest = min([t_ns - 2e9] + before[-1:])
    hit = [r for r in recs if r.kind == 'camera' and r.camera == cam and
           r.onset_ns >= earliest and r.detected_ns >= t_ns]
    reports = [r for r in eng.changes.records if r.kind not in ('camera', 'arm')]
    row = dict(cell=cell, seed=seed, kind=kind, size=size, camera=cam, time_s=t,
               detected=bool(hit), others=len(recs) - len(hit), reports=len(reports))
    if hit:
        r = hit[0]
        row.update(delay_views=int(np.searchsorted(views, r.detected_ns, side='right')),
                   delay_s=(r.detected_ns - t_ns) * 1e-9, what=r.what)
    cal = eng.current
    if cal is not None and cam in cal.cameras and cam not in eng.withheld():
        row['error'] = camera_error(cal.cameras[cam].camera, final[cam])
        row['others_error'] = max(camera_error(cal.cameras[n].camera, final[n])[0]
                                  for n in cal.cameras if n != cam)
    post = run_engine(sim, samples_of(sim, seed, after_ns=t_ns), detect=False)
    if post.current is not None and cam in post.current.cameras:
        row['post_only_error'] = camera_error(post.current.cameras[cam].camera, final[cam])
    return row


def unchanged_case(args):
    """One unchanged session: the declared changes (false alarms) and the cameras' errors."""
    cell, seed = args
    sim = session(cell, seed)
    eng = run_engine(sim, samples_of(sim, seed))
    truth = {c.name: c for c in sim.cameras}
    cal = eng.current
    errors = {n: camera_error(c.camera, truth[n]) for n, c in cal.cameras.items()} if cal else {}
    return dict(cell=cell, seed=seed,
                alarms=[r.summary(sim.start_ns) for r in eng.changes.records
                        if r.kind in ('camera', 'arm')],
                reports=[r.summary(sim.start_ns) for r in eng.changes.records
                         if r.kind not in ('camera', 'arm')],
                views=sum(len(s.observations) for s in samples_of(sim, seed)), errors=errors)


def demo_bag_alarms():
    """Return (views tested, change summaries) of `armcal calibrate` on the bundled demo bag."""
    from armcal_ros.offline import collect_samples
    from armcal_ros.settings import load_settings
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    front = collect_samples(os.path.join(root, 'bags', 'demo'),
                            load_settings(os.path.join(root, 'config', 'demo.yaml')))
    views = sum(len(s.observations) for s in front.store.samples)
    recs = front.changes.records
    return (views, [r.summary() for r in recs if r.kind in ('camera', 'arm')],
            [r.summary() for r in recs if r.kind not in ('camera', 'arm')])


def rms_ratio(a, b):
    """Return sqrt(mean(a^2) / mean(b^2)): the ratio of two paired sets' RMS."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    return float(np.sqrt(np.mean(a ** 2) / np.mean(b ** 2)))


def recovery_summary(rows, factor=1.2):
    """
    Say how many cases recover within ``factor`` of the post-only calibration, by statistic.

    Five seeds per case make the ratio of medians a noisy statistic: one seed in which the
    post-change samples happen to place a camera well moves it by 2 x.  The RMS over the
    paired seeds (the mean squared error, what an accuracy is) and the median of the paired
    ratios are given beside it, with a bootstrap interval of the RMS ratio pooled over every
    case (seeds resampled within each case).
    """
    groups = {}
    for r in rows:
        if 'error' in r and 'post_only_error' in r:
            groups.setdefault((r['cell'], r['kind'], r['size']), []).append(
                (r['error'][0], r['post_only_error'][0]))
    if not groups:
        return 'No case has both a recovered and a post-only calibration.'
    stats = {'ratio of medians': lambda e, p: np.median(e) / np.median(p),
             'median of paired ratios': lambda e, p: np.median(e / p),
             'RMS over seeds': lambda e, p: rms_ratio(e, p)}
    parts = []
    for label, fn in stats.items():
        got = [fn(*map(np.asarray, zip(*v))) for v in groups.values()]
        parts.append(f'{label} {sum(g <= factor for g in got)}/{len(got)} '
                     f'(largest {max(got):.2f} x)')
    ratio, low, high = pooled_rms_ratio(list(groups.values()))
    return (f'Cases whose recovered rotation error is within {factor} x of the post-only '
            f'calibration\'s: {"; ".join(parts)}. Over every case the RMS ratio is '
            f'{ratio:.2f} x (95 % bootstrap interval {low:.2f}-{high:.2f}).')


def pooled_rms_ratio(cases, draws=2000):
    """
    Return (ratio, 2.5 %, 97.5 %): the RMS ratio of paired errors pooled over ``cases``.

    ``cases`` is a list of [(a, b), ...] per case; the ratio is sqrt(sum a^2 / sum b^2) over
    every pair, its interval a bootstrap with the pairs resampled within each case.
    """
    rng = np.random.default_rng(0)
    boot = []
    for _ in range(draws):
        a2 = b2 = 0.0
        for v in cases:
            a = np.asarray(v)[rng.integers(len(v), size=len(v))]
            a2, b2 = a2 + np.sum(a[:, 0] ** 2), b2 + np.sum(a[:, 1] ** 2)
        boot.append(np.sqrt(a2 / b2))
    allv = np.asarray([x for v in cases for x in v])
    return (rms_ratio(allv[:, 0], allv[:, 1]), float(np.percentile(boot, 2.5)),
            float(np.percentile(boot, 97.5)))


def unchanged_pairs(rows, quiet):
    """
    Return {(cell, kind, size): [(worst unchanged camera's error, same without the change)]}.

    Both are rotation errors (deg) of the same camera in the same seed's session, with and
    without the change (``quiet``: the unchanged sessions).
    """
    base = {(q['cell'], q['seed']): q for q in quiet}
    groups = {}
    for r in rows:
        b = base.get((r['cell'], r['seed']))
        if 'others_error' in r and b and b['errors']:
            without = max(e[0] for n, e in b['errors'].items() if n != r['camera'])
            groups.setdefault((r['cell'], r['kind'], r['size']), []).append(
                (r['others_error'], without))
    return groups


def unchanged_summary(rows, quiet):
    """
    Say whether the unchanged cameras end worse than without the change, over every case.

    One case's five seeds leave the RMS ratio of the worst unchanged camera's error with and
    without the change a noisy figure; pooled over every case of a cell and over all cells
    (a bootstrap interval with the seeds resampled within each case) it says whether a change
    costs the other cameras accuracy at all.
    """
    groups = unchanged_pairs(rows, quiet)
    if not groups:
        return 'No case has an unchanged camera with and without the change.'

    def pooled(keys):
        ratio, low, high = pooled_rms_ratio([groups[k] for k in keys])
        allv = np.asarray([x for k in keys for x in groups[k]])
        return (f'{ratio:.2f} x (95 % bootstrap interval {low:.2f}-{high:.2f}; worse in '
                f'{int(np.sum(allv[:, 0] > allv[:, 1]))} of {len(allv)} sessions)')
    cells = sorted({k[0] for k in groups}, key=list(CELL_SCENARIOS).index)
    parts = [f'{cell} {pooled([k for k in groups if k[0] == cell])}' for cell in cells]
    return (f'The worst unchanged camera\'s rotation error with the change over the same '
            f'without it, RMS over every case: {pooled(list(groups))}; per cell: '
            f'{"; ".join(parts)}.')


def tabulate(rows, quiet, demo_views, demo_alarms, demo_reports, measured):
    """Return the section's markdown from the sessions' results (``main``'s or stored)."""
    seeds = len({r['seed'] for r in rows})
    groups = unchanged_pairs(rows, quiet)
    table_rows = []
    for cell in CELL_SCENARIOS:
        for kind, sizes in (('knock', KNOCKS_DEG), ('focus', FOCUS_PERCENT)):
            for size in sizes:
                rs = [r for r in rows if (r['cell'], r['kind'], r['size']) == (cell, kind, size)]
                det = [r for r in rs if r['detected']]
                err = [r['error'] for r in rs if 'error' in r]
                post = [r['post_only_error'] for r in rs if 'post_only_error' in r]
                pairs = groups.get((cell, kind, size), [])
                worse = [a - b for a, b in pairs]
                paired = [(r['error'][0], r['post_only_error'][0]) for r in rs
                          if 'error' in r and 'post_only_error' in r]

                def med(v, i, fmt='.3f'):
                    return format(float(np.median([x[i] for x in v])), fmt) if v else 'n/a'
                label = f'{size:g} deg' if kind == 'knock' else f'{size:g} % focal'
                table_rows.append([
                    cell, label, f'{len(det)}/{len(rs)}',
                    f'{sum(r["delay_views"] <= 10 for r in det)}/{len(rs)}',
                    f'{max(r["delay_views"] for r in det)}' if det else 'n/a',
                    f'{np.median([r["delay_s"] for r in det]):.1f}' if det else 'n/a',
                    ', '.join(sorted({r['what'] or 'withheld' for r in det})) or 'n/a',
                    med(err, 0), med(post, 0), med(err, 1, '.1f'), med(post, 1, '.1f'),
                    med(err, 2), med(post, 2),
                    f'{rms_ratio(*zip(*paired)):.2f}' if paired else 'n/a',
                    f'{max(worse):+.3f}' if worse else 'n/a',
                    f'{rms_ratio(*zip(*pairs)):.2f}' if pairs else 'n/a',
                    sum(r['others'] for r in rs), sum(r['reports'] for r in rs)])
    fa_rows = [['the demo bag (`armcal calibrate`: the images through the front end, auto)',
                'nongeometric', 1, demo_views, len(demo_alarms), len(demo_reports),
                '; '.join(demo_alarms + demo_reports)[:300] or '-']]
    for cell, n in FALSE_ALARM_SEEDS.items():
        qs = [q for q in quiet if q['cell'] == cell]
        fa_rows.append([cell, CELL_SCENARIOS[cell], len(qs), sum(q['views'] for q in qs),
                        sum(len(q['alarms']) for q in qs), sum(len(q['reports']) for q in qs),
                        '; '.join(a for q in qs for a in q['alarms'] + q['reports'])[:300]
                        or '-'])
    md = ['## Cameras that move (bench/changes.py)', '',
          f'{DURATION:.0f} s sessions, {seeds} seeds per case, one camera knocked (random '
          'axis, 2-10 mm) or refocused at a random time in the middle third; point-level '
          f'samples ({PIXEL_SIGMA} px pooled noise) fed in time order to the engine '
          f'(`{MODEL}` model, the image noise estimated from the residuals as the node\'s '
          'default parameters do, solving as the samples or one camera\'s views double, change '
          'detection at its defaults: one false alarm per million views). Detected: the right '
          'camera declared changed after the change, its change point no earlier than the '
          'camera\'s last view before it (or 2 s); "within 10": of those, how many within 10 '
          'of its views after the change. '
          'Delay: the changed camera\'s views (worst case) and seconds (median) from the '
          'change to the declaration. Errors of the changed camera against its new truth '
          '(median): after recovery, and from a calibration of the post-change samples alone. '
          '"Rotation / post-only, RMS": the root-mean-square over the seeds of the recovered '
          'camera\'s rotation error divided by the same of the post-only calibration (the '
          'seeds are paired: the same session). '
          '"Unchanged worse by": the worst unchanged camera\'s rotation error minus the same '
          'in the session without the change (worst case, deg); "unchanged RMS": the RMS over '
          'the seeds of that worst error divided by the same without the change. '
          '"Other changes": cameras or '
          'the arm declared changed that were not this one (data retired); "reports": '
          'disagreements reported with nothing retired (no single change explains them, or a '
          f'burst of bad detections). Measured on {measured}.', '',
          table(['cell', 'change', 'detected', 'within 10', 'delay views (max)', 'delay s',
                 'called', 'rotation deg', 'post-only deg', 'centre mm', 'post-only mm',
                 'focal %', 'post-only %', 'rotation / post-only, RMS x',
                 'unchanged worse by deg', 'unchanged RMS x', 'other changes',
                 'reports'], table_rows), '',
          recovery_summary(rows), '',
          unchanged_summary(rows, quiet), '',
          'False alarms on unchanged sessions: changes declared (a camera or the arm, data '
          'retired) and reports (nothing retired):', '',
          table(['cell', 'scenario', 'sessions', 'views tested', 'changes declared',
                 'reports', 'which'], fa_rows)]
    return '\n'.join(md)


def main(argv=None):
    """Run the benchmark, print the tables and write them to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--seeds', type=int, default=5)
    ap.add_argument('--processes', type=int, default=2)
    ap.add_argument('--table-only', action='store_true',
                    help='tabulate docs/bench/changes.json again (no new sessions)')
    args = ap.parse_args(argv)
    if args.table_only:
        with open(os.path.join(ROOT, 'docs', 'bench', 'changes.json')) as f:
            stored = json.load(f)
        rows, quiet, measured = stored['rows'], stored['unchanged'], stored['machine']
        demo_alarms, demo_reports = stored['demo_bag'], stored['demo_bag_reports']
        demo_views = stored.get('demo_bag_views')
        if demo_views is None:      # written before the count was stored: counted again
            demo_views, demo_alarms, demo_reports = demo_bag_alarms()
    else:
        cases = [(cell, seed, 'knock', d) for cell in CELL_SCENARIOS for d in KNOCKS_DEG
                 for seed in range(args.seeds)]
        cases += [(cell, seed, 'focus', p) for cell in CELL_SCENARIOS for p in FOCUS_PERCENT
                  for seed in range(args.seeds)]
        unchanged = [(cell, seed) for cell, n in FALSE_ALARM_SEEDS.items() for seed in range(n)]
        with Pool(args.processes) as pool:
            demo = pool.apply_async(demo_bag_alarms)
            rows = pool.map(change_case, cases, chunksize=1)
            quiet = pool.map(unchanged_case, unchanged, chunksize=1)
            demo_views, demo_alarms, demo_reports = demo.get()
        measured = machine()
    text = tabulate(rows, quiet, demo_views, demo_alarms, demo_reports, measured)
    print(text)
    write_section('changes', text)
    write_json('changes', dict(rows=rows, unchanged=quiet, demo_bag=demo_alarms,
                               demo_bag_reports=demo_reports, demo_bag_views=demo_views,
                               machine=measured))
    return 0


if __name__ == '__main__':
    sys.exit(main())
