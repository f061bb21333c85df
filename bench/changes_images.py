"""
Cameras that move, through the images: change detection on lamp-lit recordings of every cell.

bench/changes.py tests the change detection on point-level samples (pooled image points with
Gaussian noise).  Here each named cell is recorded as a real cell looks (``realistic``: a matte
ball under one lamp) and read by `armcal calibrate`'s pipeline (images, front end, the node's
default centre ``shaded_pooled``, changes followed in time order): once unchanged, once with
its second camera knocked by 0.25 deg and 3 mm at mid-session, once with its last camera's
focal length 0.5 % longer at mid-session - the smallest changes the targets cover.  What the
light does to a detection (a centre pulled towards the lamp, corrected by a shift pooled over
the camera's views) is in these samples and not in bench/changes.py's.

Per recording: the changes declared (camera, onset, what), whether the changed camera was
found, and the delay (its views and seconds from the change to the declaration).

Usage: python bench/changes_images.py [--seed 0] [--duration 180] [--bags DIR] [--cells ...]
(``--bags`` keeps the recordings for a rerun, e.g. of another version on the same bags).
"""

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import textwrap
from multiprocessing import Pool

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import yaml  # noqa: E402
from _report import machine, table, write_json, write_section  # noqa: E402

from armcal_ros.offline import collect_samples  # noqa: E402
from armcal_ros.settings import load_settings  # noqa: E402
from armcal_ros.sim.cell import CameraChange, simulate_cell  # noqa: E402
from armcal_ros.sim.cells import cell_parameters, CELLS  # noqa: E402
from armcal_ros.sim.output import write_sim_bag  # noqa: E402

KNOCK = (0.25, 3.0)          # deg, mm
FOCUS_PERCENT = 0.5


def _cases(duration):
    """Return (cell, case, CameraChange or None) for every recording."""
    out = []
    for name, cell in CELLS.items():
        cams = cell.sim_settings('realistic').camera_names
        out.append((name, 'unchanged', None))
        out.append((name, f'{KNOCK[0]:g} deg knock', CameraChange(
            cams[min(1, len(cams) - 1)], duration / 2, KNOCK[0], KNOCK[1])))
        out.append((name, f'{FOCUS_PERCENT:g} % focal', CameraChange(
            cams[-1], duration / 2, focal_percent=FOCUS_PERCENT)))
    return out


def record(name, label, change, seed, duration, bags):
    """Record (or reuse) one case's bag; return (bag, parameter file, bag start ns)."""
    cell = CELLS[name]
    sim = cell.sim_settings('realistic')
    if change is not None:
        sim = dataclasses.replace(sim, camera_changes=(change,))
    bag = os.path.join(bags, f'{name}-{label.replace(" ", "_")}-{seed}')
    meta = bag + '.json'
    if not os.path.exists(meta):
        res = simulate_cell(cell.scenario, seed, duration, sim)
        write_sim_bag(res, bag, compressed=cell.compressed, encoding=cell.encoding)
        with open(meta, 'w') as f:
            json.dump({'start_ns': int(res.start_ns)}, f)
    with open(meta) as f:
        start = json.load(f)['start_ns']
    params = bag + '.yaml'
    p = cell_parameters(sim, cell.compressed)
    with open(params, 'w') as f:
        yaml.safe_dump({'armcal': {'ros__parameters': p}}, f)
    return bag, params, start


def run_case(args):
    """Record (or reuse) one case's bag, read it as `armcal calibrate` does; return figures."""
    (name, label, change), seed, duration, bags = args
    bag, params, start = record(name, label, change, seed, duration, bags)
    front = collect_samples(bag, load_settings(params))
    recs = [r for r in front.changes.records]
    views = []
    for smp in list(front.store.samples) + [s for _, s in front.store.retired]:
        for cam, o in smp.observations.items():
            views.append((cam, o.stamp_ns))
    out = dict(cell=name, case=label, seed=seed,
               views=len(views), declared=[], reports=[], found=False)
    for r in recs:
        entry = dict(kind=r.kind, camera=r.camera, onset_s=(r.onset_ns - start) * 1e-9,
                     detected_s=(r.detected_ns - start) * 1e-9, what=r.what,
                     summary=r.summary(start))
        if r.kind in ('camera', 'arm') and r.status != 'reported':
            out['declared'].append(entry)
        else:
            out['reports'].append(entry)
    if change is not None:
        t_ns = start + int(change.time_s * 1e9)
        hit = [e for e in out['declared'] if e['camera'] == change.camera
               and e['detected_s'] >= change.time_s]
        if hit:
            e = hit[0]
            det_ns = start + int(e['detected_s'] * 1e9)
            out.update(found=True, delay_s=e['detected_s'] - change.time_s,
                       delay_views=sum(1 for c, s in views
                                       if c == change.camera and t_ns <= s <= det_ns))
        out['changed'] = change.camera
    return out


def main(argv=None):
    """Run the benchmark, print the table and write it to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--duration', type=float, default=180.0)
    ap.add_argument('--bags', default=None, help='keep the recordings here (default: a '
                    'temporary directory)')
    ap.add_argument('--processes', type=int, default=2)
    ap.add_argument('--cells', nargs='*', default=None, help='only these cells')
    args = ap.parse_args(argv)
    tmp = None if args.bags else tempfile.TemporaryDirectory(prefix='armcal_changes_')
    bags = args.bags or tmp.name
    os.makedirs(bags, exist_ok=True)
    jobs = [(c, args.seed, args.duration, bags) for c in _cases(args.duration)
            if args.cells is None or c[0] in args.cells]
    with Pool(args.processes) as pool:
        rows = pool.map(run_case, jobs, chunksize=1)
    text = render(rows, args.seed, args.duration)
    print(text)
    write_section('changes_images', text)
    write_json('changes_images', dict(rows=rows, seed=args.seed, duration=args.duration,
                                      machine=machine()))
    if tmp is not None:
        tmp.cleanup()
    return 0


def render(rows, seed, duration):
    """Return the markdown section of ``rows`` (what :func:`run_case` returns)."""
    body = []
    for r in rows:
        # Every declaration but the changed camera's first after the change is false (a
        # second one of the same camera too: its data were retired again).
        wrong = len(r['declared']) - (1 if r['found'] else 0)
        body.append([r['cell'], r['case'], r['views'],
                     r.get('changed', '-'),
                     ('yes' if r['found'] else 'NO') if 'changed' in r else '-',
                     r.get('delay_views', '-'),
                     f'{r["delay_s"]:.1f}' if 'delay_s' in r else '-',
                     wrong, len(r['reports']),
                     # The whole text is in the JSON; the table cuts at a word.
                     textwrap.shorten('; '.join(e['summary']
                                                for e in r['declared'] + r['reports']),
                                      240, placeholder=' ...') or '-'])
    md = ['## Cameras that move, through the images (bench/changes_images.py)', '',
          f'Each named cell recorded for {duration:.0f} s (seed {seed}) under one '
          'lamp (`realistic`), read by `armcal calibrate`\'s pipeline with the default '
          'parameters (`shaded_pooled` centre, changes followed in time order): unchanged; '
          f'its second camera knocked by {KNOCK[0]:g} deg and {KNOCK[1]:g} mm at mid-session; '
          f'its last camera\'s focal length {FOCUS_PERCENT:g} % longer at mid-session. Found: '
          'the changed camera declared changed after the change; delay: its views and seconds '
          'from the change to the declaration; false: every other change declared (data '
          'retired; a second declaration of the changed camera too); reports: disagreements '
          f'reported, nothing retired. Measured on {machine()}.', '',
          table(['cell', 'case', 'views', 'changed', 'found', 'delay views', 'delay s',
                 'false', 'reports', 'declared and reported'], body)]
    return '\n'.join(md)


if __name__ == '__main__':
    sys.exit(main())
