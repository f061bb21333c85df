"""
Each effect of a real cell alone, through the whole pipeline, for each sphere centre.

bench/realism.py measures the lamp, and everything at once; bench/arm_effects.py each arm and
clock effect alone.  This runs each camera, marker and operator effect of the simulator alone
(`armcal simulate` switches, physically sized: see EFFECTS) on two named cells, and calibrates
each recording (`armcal calibrate`, `auto`, no latency pass: no effect here stamps late) with
each ``sphere_centre``.  Per run: the shape and absolute error against the simulator's cameras
(500 fresh points triangulated) beside the limit (the same recording calibrated with the arm's
true geometry and the ``fixed`` model, ``ground_truth/params_true_geometry.yaml``), and the
observations the solver used against the truth: the true projection in the frame nearest each
observation's stamp - median and 99th-percentile error, the mean shift per camera (the bias
pooling does not remove; median over cameras) and the observations more than 1 px off (false
observations kept), and the still frames the front end found the marker in (its own count:
detections over still frames; a recall with every still frame as the truth's denominator,
occluded ones included).

Then all together: a realistic cell (the lamp, ``--lighting realistic``) with every effect
above but the textured scene and every arm and clock effect of bench/arm_effects.py (late
stamps, lost and jittered joint states, backlash, repeatability, a ring-down after stops),
calibrated as `armcal calibrate` does by default (each camera's stamp latency measured and the
frames paired again at it); and the same with the textured scene as well.  Each of these is
recorded again with the ball glowing alike from every side and every other effect the same:
the lamp-lit error over that one's is what the light costs when everything else is present,
beside the lamp-lit error over the clean recording's (no effect at all).  The per-view fit
(``shaded``) is run only where its use is the advice - the LED, whose bright side turns with
the tool - and on the lamp-lit recording with the textured scene, where the pooled shift
carries the centroid's unsmooth error over the texture (docs/BENCHMARKS.md, "Two more
seeds"): what the per-view fit would give there.

Usage: python bench/realism_effects.py [--seeds 5] [--duration 60] [--processes 2] [--table-only]
       [--only TEXT] (rerun only the effects whose label starts with TEXT, e.g. "all together")
       [--centres C ...] (calibrate with only these centres, the others' runs kept)
"""

import argparse
import json
import os
import sys
import tempfile
from functools import partial as bind
from multiprocessing import Pool

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402

import numpy as np  # noqa: E402
import yaml  # noqa: E402

from armcal_ros.cli import main as armcal  # noqa: E402
from armcal_ros.compare import compare  # noqa: E402
from armcal_ros.engine import lit_centres  # noqa: E402
from armcal_ros.frontend.store import SampleStore  # noqa: E402
from armcal_ros.io.calib_files import read_cameras  # noqa: E402
from armcal_ros.sim.cells import CELLS, realistic_lamp  # noqa: E402
from arm_effects import variants as arm_variants  # noqa: E402

CELL_NAMES = ('puma-3cam', 'ur5-2cam')
CENTRES = ('centroid', 'shaded', 'shaded_pooled')
#: The effect whose advice is the per-view fit (an LED turns with the tool); elsewhere the fit
#: alone is `shaded_pooled`'s first stage and not run on its own, but for TEXTURED_TOGETHER.
PER_VIEW_FIT = 'LED along the tool z, cos fall-off'
#: The lamp-lit recording with every effect and the textured scene, where the pooled shift
#: carries the texture's centroid error: the per-view fit is run there as well.
TEXTURED_TOGETHER = 'all together with the textured scene, 40 DN'
#: Label prefix of the runs with every effect at once (latency measured, realistic light).
TOGETHER = 'all together'
#: In the label of an all-together recording with the ball glowing alike from every side:
#: what the light alone costs is the lamp-lit run's error over this one's.
UNIFORM = 'uniform light'


def centres(label):
    """Return the ``sphere_centre`` values run for the effect ``label``."""
    return CENTRES if label in (PER_VIEW_FIT, TEXTURED_TOGETHER) else ('centroid',
                                                                       'shaded_pooled')


def effects(cell):
    """Return [(label, `armcal simulate` options)]: none, each effect alone, all together."""
    lamp = [str(v) for v in realistic_lamp(CELLS[cell].sim_settings())]
    alone = [
        ('none', []),
        ('lamp 1.5 m above, 25 % ambient', ['--lamp', *lamp]),
        ('LED along the tool z, cos fall-off', ['--led', '0', '0', '1']),
        ('read noise 3 DN', ['--read-noise', '3']),
        ('textured scene, 40 DN', ['--clutter', '40']),
        ('auto-exposure steps, 5 s, x1.5', ['--exposure-steps', '5', '1.5']),
        ('lenses: k3 0.1, tangential 0.002', ['--lens-k3', '0.1', '--lens-tangential', '0.002']),
        ('rolling shutter, 20 ms readout', ['--rolling-shutter', '0.02']),
        ('pauses of 0.2-0.5 s', ['--pause', '0.2', '0.5']),
        ('joint states 1 kHz, 1 ms jitter', ['--joint-rate', '1000', '--joint-jitter', '0.001']),
    ]
    cams = list(CELLS[cell].sim_settings().camera_names)
    arm = [a for name, opts, extra in arm_variants(cams) if name == 'all together' and not extra
           for a in opts]
    every = ['--lighting', 'realistic'] + [
        a for label, opts in alone
        if not opts or opts[0] not in ('--lamp', '--led', '--clutter', '--joint-rate')
        for a in opts] + ['--joint-rate', '1000'] + arm
    uniform = every[2:]
    return alone + [
        (f'{TOGETHER}: lamp, every effect but the textured scene, latency measured', every),
        (f'{TOGETHER}: {UNIFORM}, every effect but the textured scene, latency measured',
         uniform),
        (f'{TOGETHER} with the textured scene, 40 DN', every + ['--clutter', '40']),
        (f'{TOGETHER} with the textured scene, 40 DN, {UNIFORM}', uniform + ['--clutter', '40'])]


def uniform_twin(cell, label):
    """Return the label of the uniform-light run beside an all-together ``label`` (or None)."""
    labels = [name for name, _ in effects(cell)]
    k = labels.index(label)
    if not label.startswith(TOGETHER) or UNIFORM in label or k + 1 == len(labels):
        return None
    return labels[k + 1] if UNIFORM in labels[k + 1] else None


def observation_errors(out, gt_dir, centre):
    """Return the solver's observations against the truth (module doc)."""
    store = SampleStore.load(out)
    arrays = store.arrays()
    if centre == 'shaded_pooled':
        # Each camera's centres of the kind the solve took (report.json's light_pooling).
        with open(os.path.join(out, 'report.json')) as f:
            pooling = json.load(f).get('light_pooling') or {}
        arrays = lit_centres(arrays, {k for k, v in pooling.items()
                                      if v['status'] == 'fits_kept'}).arrays
    m = np.load(os.path.join(gt_dir, 'markers.npz'))
    names = [str(n) for n in m['camera_names']]
    stamps = {}
    for s in sorted(store.samples, key=lambda s: s.id):
        for cam, o in s.observations.items():
            stamps.setdefault(cam, []).append(o.stamp_ns)
    errors, shifts = [], []
    for c, cam in enumerate(arrays.camera_names):
        sel = arrays.camera_index == c
        k = names.index(cam)
        fsel = m['frame_camera'] == k
        f_stamp, f_uv = m['frame_stamp_ns'][fsel], m['frame_uv'][fsel]
        near = np.abs(np.asarray(stamps[cam])[:, None] - f_stamp[None, :]).argmin(axis=1)
        e = arrays.uv[sel] - f_uv[near]
        errors.append(np.hypot(e[:, 0], e[:, 1]))
        good = errors[-1] <= 1.0
        if good.any():  # a camera with no observation within 1 px has no shift to report
            shifts.append(float(np.hypot(*e[good].mean(axis=0))))
    errors = np.concatenate(errors)
    return dict(median_px=float(np.median(errors)), p99_px=float(np.percentile(errors, 99)),
                shift_px=float(np.median(shifts)) if shifts else float('nan'),
                false_kept=int(np.sum(errors > 1.0)),
                observations=int(len(errors)))


def case(args, only_centres=None):
    """One cell, seed and effect: simulate, then calibrate with each centre (or those given)."""
    cell, seed, duration, label, opts = args
    out = dict(cell=cell, seed=seed, effect=label)
    with tempfile.TemporaryDirectory() as tmp:
        bag = os.path.join(tmp, 'bag')
        assert armcal(['simulate', '--cell', cell, '--seed', str(seed), '--duration',
                       str(duration), '--output', bag, '--no-zstd', '--quiet',
                       '--lighting', 'uniform', *opts]) == 0
        gt = os.path.join(bag, 'ground_truth')
        base = yaml.safe_load(open(os.path.join(gt, 'params.yaml')))
        latency = [] if label.startswith(TOGETHER) else ['--no-latency']
        for centre in centres(label) if only_centres is None else \
                [c for c in only_centres if c in centres(label)]:
            doc = yaml.safe_load(yaml.safe_dump(base))
            doc['armcal']['ros__parameters'].update(marker_lamp=[], sphere_centre=centre)
            params = os.path.join(tmp, f'{centre}.yaml')
            with open(params, 'w') as f:
                yaml.safe_dump(doc, f)
            res = os.path.join(tmp, centre)
            if armcal(['calibrate', bag, '--params', params, '--output', res, '--quiet',
                       *latency]) != 0:
                out[centre] = dict(failed=True)       # its reason is on stderr
                continue
            sc = compare({c.name: c for c in read_cameras(res)[1]}, gt)
            with open(os.path.join(res, 'report.json')) as f:
                counts = json.load(f)['front_end']
            out[centre] = dict(shape_mm=sc.shape_mm, absolute_mm=sc.absolute_mm,
                               still_detected=counts.get('detections', 0) /
                               max(counts.get('frames_still', 0), 1),
                               **observation_errors(res, gt, centre))
            # The limit: the same detections with the arm's true geometry, `fixed`.
            doc = yaml.safe_load(open(os.path.join(gt, 'params_true_geometry.yaml')))
            doc['armcal']['ros__parameters'].update(marker_lamp=[], sphere_centre=centre)
            lim = os.path.join(gt, f'limit_{centre}.yaml')     # beside the true URDF
            with open(lim, 'w') as f:
                yaml.safe_dump(doc, f)
            res = os.path.join(tmp, f'limit_{centre}')
            if armcal(['calibrate', bag, '--params', lim, '--output', res, '--quiet',
                       *latency]) == 0:
                sc = compare({c.name: c for c in read_cameras(res)[1]}, gt)
                out[centre].update(limit_shape_mm=sc.shape_mm, limit_absolute_mm=sc.absolute_mm)
    return out


def stored_runs(duration):
    """Return the stored runs (docs/bench/realism_effects.json), checked to be as long."""
    path = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), 'docs',
                        'bench', 'realism_effects.json')
    if not os.path.exists(path):
        return []
    with open(path) as f:
        stored = json.load(f)
    if stored.get('duration_s', duration) != duration:
        raise SystemExit(f'--only/--centres: the stored runs are {stored["duration_s"]} s '
                         f'long, not --duration {duration}')
    return stored['runs']


def _key(run):
    return run['cell'], run['seed'], run['effect']


def together_summary(res):
    """
    Say what the light costs with every other effect present, per cell and seed.

    The all-together recording's shape error with ``shaded_pooled`` (the default centre) over
    that of the same recording under uniform light with the centroid (the detector the
    uniform ball needs), and over the clean recording's ("none", centroid): median (range)
    over the seeds that have both.
    """
    def shape(cell, seed, effect, centre):
        for r in res:
            if (r['cell'], r['seed'], r['effect']) == (cell, seed, effect):
                got = r.get(centre, {})
                return None if got.get('failed') else got.get('shape_mm')
        return None
    lines = []
    for cell in CELL_NAMES:
        for label, _ in effects(cell):
            twin = uniform_twin(cell, label)
            if twin is None:
                continue
            by_twin, by_clean, fitted = [], [], []
            for seed in sorted({r['seed'] for r in res if r['cell'] == cell}):
                lit = shape(cell, seed, label, 'shaded_pooled')
                fit = shape(cell, seed, label, 'shaded')
                uni = shape(cell, seed, twin, 'centroid')
                clean = shape(cell, seed, 'none', 'centroid')
                if lit is not None and uni:
                    by_twin.append(lit / uni)
                if fit is not None and uni:
                    fitted.append(fit / uni)
                if lit is not None and clean:
                    by_clean.append(lit / clean)

            def say(v):
                return (f'{np.median(v):.2f} x ({min(v):.2f}-{max(v):.2f}, {len(v)} seed(s))'
                        if v else 'n/a')
            also = (f'; with each view\'s fit (`shaded`) {say(fitted)}'
                    if 'shaded' in centres(label) else '')
            lines.append(f'- {cell}, {label[len(TOGETHER):].strip(" :") or "every effect"}: '
                         f'`shaded_pooled` over the same under uniform light {say(by_twin)}; '
                         f'over the clean recording {say(by_clean)} (target: at most 2 x)'
                         f'{also}.')
    return '\n'.join(['Shape error, all together, lamp-lit over uniform (the light\'s cost '
                      'with every other effect present) and over the clean recording:', ''] +
                     lines)


def main(argv=None):
    """Run the benchmark, print the table and write it to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--seeds', type=int, default=5)
    ap.add_argument('--duration', type=float, default=60.0)
    ap.add_argument('--processes', type=int, default=2)
    ap.add_argument('--table-only', action='store_true',
                    help='tabulate bench/realism_effects.jsonl as it is (no new runs)')
    ap.add_argument('--only', default=None, metavar='TEXT',
                    help='run only the effects whose label starts with TEXT, keeping the '
                    'other effects\' runs from docs/bench/realism_effects.json')
    ap.add_argument('--centres', nargs='+', default=None, choices=CENTRES, metavar='CENTRE',
                    help='calibrate with only these sphere centres, keeping the other '
                    'centres\' runs of the same recordings from docs/bench/realism_effects.json '
                    '(the recordings are made again from their seeds, so they are the same)')
    args = ap.parse_args(argv)
    # Seed by seed, each result kept as it comes (bench/realism_effects.jsonl): an interrupted
    # run still has whole seeds, and --table-only tabulates what there is.
    partial = os.path.join(os.path.dirname(os.path.abspath(__file__)), 'realism_effects.jsonl')
    if not args.table_only:
        jobs = [(cell, seed, args.duration, label, opts) for seed in range(args.seeds)
                for cell in CELL_NAMES for label, opts in effects(cell)
                if args.only is None or label.startswith(args.only)]
        stored = stored_runs(args.duration) if args.only or args.centres else []
        rerun = {(cell, seed, label) for cell, seed, _, label, _ in jobs}
        with open(partial, 'w') as f:
            for r in stored:
                if _key(r) not in rerun:
                    f.write(json.dumps(r) + '\n')
        kept = {_key(r): r for r in stored} if args.centres else {}
        with Pool(args.processes) as pool:
            for r in pool.imap_unordered(bind(case, only_centres=args.centres), jobs,
                                         chunksize=1):
                # With --centres the other centres' runs of the same recording stand beside.
                r = {**{k: v for k, v in kept.get(_key(r), {}).items()
                        if k in centres(r['effect'])}, **r}
                with open(partial, 'a') as f:
                    f.write(json.dumps(r) + '\n')
    with open(partial) as f:
        res = [json.loads(line) for line in f if line.strip()]
    seeds = sorted({len({r['seed'] for r in res if r['effect'] == e}) for e in
                    {r['effect'] for r in res}})
    rows = []
    for cell in CELL_NAMES:
        for label, _ in effects(cell):
            rs = [r for r in res if (r['cell'], r['effect']) == (cell, label)]
            for centre in centres(label):
                ok = [r[centre] for r in rs if not r[centre].get('failed')]
                failed = len(rs) - len(ok)
                if not ok:
                    rows.append([cell, label, centre, str(len(rs))] + ['failed'] * 9)
                    continue

                def med(key):
                    v = [o[key] for o in ok if key in o]
                    if key == 'shift_px':
                        # Runs recorded before a camera without a kept observation was
                        # left out of the shift carry NaN there; the median is over the
                        # others.  (A NaN error elsewhere is a camera the run lost: shown.)
                        v = [x for x in v if x is not None and np.isfinite(x)]
                    return f'{np.median(v):.3f}' if v else 'n/a'
                rows.append([cell, label, centre, str(len(rs)),
                             med('shape_mm') + (f' ({failed} failed)' if failed else ''),
                             med('limit_shape_mm'), med('absolute_mm'),
                             med('limit_absolute_mm'), med('median_px'),
                             med('p99_px'), med('shift_px'),
                             f'{sum(o["false_kept"] for o in ok)} / '
                             f'{sum(o["observations"] for o in ok)}',
                             f'{100 * np.median([o["still_detected"] for o in ok]):.1f}'
                             if all('still_detected' in o for o in ok) else 'n/a'])
    text = '\n'.join([
        '## Each effect of a real cell alone, for each sphere centre '
        '(bench/realism_effects.py)', '',
        f'{"-".join(map(str, seeds))} seed(s) x {args.duration:.0f} s per cell and effect '
        '(column "seeds"); the same trajectory '
        'and errors with one `armcal simulate` switch each, calibrated with `auto` and each '
        '`sphere_centre` (no latency pass: nothing here stamps late), then all together on a '
        'realistic cell - the lamp, every effect but the textured scene and every arm and '
        'clock effect of *arm-effects* (cameras stamped 30, 80, 0 (50) ms late, joint states '
        'at 1 kHz with 1 ms jitter and 10 % lost, backlash, repeatability, ring-down) - '
        'calibrated as `armcal calibrate` does by default (latency measured, frames paired '
        'again), and with the textured scene as well; each of these also with the ball '
        'glowing alike from every side and every other effect the same ("uniform light"): '
        'the light\'s own cost is the ratio of the two. The per-view fit (`shaded`) is run only '
        'for the LED, where it is the advice, and on the lamp-lit textured recording. Shape '
        'and absolute error against the simulator\'s cameras, and the limit beside them: the '
        'same recording calibrated with the arm\'s true geometry and the `fixed` model '
        '(ground_truth/params_true_geometry.yaml; exact here, both cells\' scenario being '
        'geometric): what the detections alone leave. The solver\'s observations (for '
        '`shaded_pooled`, '
        'after pooling) against the true projection in the nearest frame: median and 99th '
        'percentile error, the mean shift per camera (median over the cameras), and the '
        'observations more than 1 px off over all there were; still detected: the front '
        'end\'s detections over its still frames (occluded ones in the denominator too). '
        'Medians over the seeds; a '
        '"failed" run is one `armcal calibrate` refused (its reason on stderr). '
        f'Measured on {machine()}.', '',
        table(['cell', 'effect', 'sphere_centre', 'seeds', 'shape mm', 'limit shape mm',
               'absolute mm', 'limit absolute mm', 'median px', '99th pct px',
               'mean shift px', 'false kept', 'still detected %'],
              rows), '', together_summary(res)])
    print(text)
    write_section('realism-effects', text)
    write_json('realism_effects', dict(runs=res, duration_s=args.duration, machine=machine()))


if __name__ == '__main__':
    main()
