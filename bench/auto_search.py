"""
The whole `auto` model search on the demo bag, timed for this tree and for earlier commits.

`armcal calibrate bags/demo` (the bag's parameter file, model `auto`: the fixed stage, the
hyperparameter search over every noise model, the chosen model's covariance and leverages) run
``--repeats`` times per tree in a fresh process with single-threaded BLAS; the solve time is
the report's ``timings.solve_s`` (the front end is left out: it does not touch the solver), and
the final costs and cameras are compared so a faster tree is also the same answer.

Usage: python bench/auto_search.py [--repeats 3] [--commits REV ...]
Each REV is checked out into a temporary worktree and run with this tree's virtualenv.
Writes docs/BENCHMARKS.md (section "auto-search") and docs/bench/auto_search.json.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def run_tree(tree, repeats, bag, params):
    """Run `armcal calibrate` ``repeats`` times from ``tree``: the solve times and the result."""
    env = dict(os.environ, OPENBLAS_NUM_THREADS='1', PYTHONPATH=tree)
    times, report = [], None
    for k in range(repeats):
        with tempfile.TemporaryDirectory(prefix='armcal_search_') as out:
            subprocess.run([sys.executable, '-m', 'armcal_ros.cli', 'calibrate', bag,
                            '--params', params, '--output', out, '--quiet'],
                           cwd=tree, env=env, check=True, stdout=subprocess.DEVNULL)
            with open(os.path.join(out, 'report.json')) as f:
                report = json.load(f)
            times.append(float(report['timings']['solve_s']))
    return dict(solve_s=times, message=report.get('message', ''),
                samples=report.get('n_samples'),
                fx={c: v['fx'] for c, v in report.get('cameras', {}).items()})


def main(argv=None):
    """Time the search for this tree and each commit; print and write the table."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--repeats', type=int, default=3)
    ap.add_argument('--commits', nargs='*', default=[])
    ap.add_argument('--bag', default=os.path.join(ROOT, 'bags', 'demo'))
    ap.add_argument('--params', default=os.path.join(ROOT, 'config', 'demo.yaml'))
    ap.add_argument('--no-write', action='store_true')
    args = ap.parse_args(argv)
    rows, results = [], {}
    trees = [(rev, None) for rev in args.commits] + [('this tree', ROOT)]
    for rev, tree in trees:
        tmp = None
        if tree is None:
            tmp = tempfile.mkdtemp(prefix='armcal_rev_')
            subprocess.run(['git', 'worktree', 'add', '--detach', tmp, rev], cwd=ROOT,
                           check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            tree = tmp
        try:
            label = rev if tmp is None else subprocess.run(
                ['git', 'log', '-1', '--format=%h %s', rev], cwd=ROOT, check=True,
                capture_output=True, text=True).stdout.strip()[:60]
            res = run_tree(tree, args.repeats, args.bag, args.params)
        finally:
            if tmp is not None:
                subprocess.run(['git', 'worktree', 'remove', '--force', tmp], cwd=ROOT,
                               check=False)
        results[label] = res
        print(f'{label}: {res}', flush=True)
    first = next(iter(results.values()))
    for label, res in results.items():
        best = min(res['solve_s'])
        chosen = res['message'].split(' by ')[0].replace('chose ', '')
        dfx = max(abs(res['fx'][c] - first['fx'][c]) for c in first['fx'])
        rows.append([label, f'{best:.2f}', f'{max(res["solve_s"]):.2f}', chosen,
                     res['samples'], f'{dfx:.1e}', f'{min(first["solve_s"]) / best:.2f}'])
    text = '\n'.join([
        '## The whole auto search on the demo bag (bench/auto_search.py)', '',
        f'`armcal calibrate bags/demo` with the bag\'s parameter file (model `auto`), '
        f'{args.repeats} runs per tree, single-threaded BLAS; solve time from report.json '
        f'(the front end excluded). Speed-up against the first row. Machine: {machine()}.', '',
        table(['tree', 'solve s (best)', 'solve s (worst)', 'model chosen', 'samples',
               'max fx difference px', 'speed-up'], rows)])
    print(text)
    if not args.no_write:
        write_section('auto-search', text)
        write_json('auto_search', dict(results=results, machine=machine()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
