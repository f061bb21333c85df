"""
A candidate for small camera changes: a split likelihood ratio per camera, measured, not used.

The change monitor (armcal_ros/core/change.py) tests each new view against a prediction whose
width includes the camera's own parameter uncertainty (about 1 px on a young calibration against
0.02 px of image noise), so a 0.5 % focus change or a 0.25 deg knock can go unseen or be seen
late (docs/BENCHMARKS.md, "changes").  This bench measures whether a test that does not lean on
that width separates changed from unchanged sessions:

For each camera, every view after a first calibration (on the first 100 s, `kinematic`) gives
the whitened residual of its leave-one-camera-out prediction, r_i = L_i^T (uv_i - pi(X~_i)) with
L_i L_i^T = (s^2 I + J_x H^-1 J_x^T)^-1 (no parameter term), and its derivative J_i (2 x 7) with
respect to the camera's pose and focal length.  At each split k of the stream, with the W views
before it (A) and the W after it (B),

    Lambda_k = min chi^2(A + B, one camera) - min chi^2(A) - min chi^2(B)   (linear fits)

is chi^2_7 if nothing changed and the residuals were white.  They are not (the arm's errors the
model leaves are smooth in space and the operator moves between regions), so each Lambda is
divided by the median of the camera's Lambdas over the session: an oracle scale (it sees the
future and the change), so the separation below is the most a split test could show.  A second
variant first subtracts from each view's residual a smooth field fitted to the camera's earlier
views after the calibration (Gaussian-process mean, squared-exponential, L = 0.15 m, refitted
every W views on the views before the window pair): what the model leaves in each region.

Reported per cell and case (unchanged, 0.5 % focal, 0.25 deg knock; 4 seeds): for the changed
camera the largest ratio for splits from 10 s before to 15 s after the change, and the largest
ratio of any camera over each unchanged session (a threshold must sit above all of those).

Usage: python bench/change_split.py [--seeds 4] [--processes 2]
Writes docs/BENCHMARKS.md (section "change-split") and docs/bench/change_split.json.
"""

import argparse
import os
import sys
from multiprocessing import Pool

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402
import changes as B  # noqa: E402

import numpy as np  # noqa: E402

from armcal_ros.core.camera import project_with_jacobians  # noqa: E402
from armcal_ros.core.change import fuse, PredictionModel  # noqa: E402
from armcal_ros.sim.cell import CameraChange  # noqa: E402

W = 10
T_CALIBRATE = 100.0
FIELD_LENGTH = 0.15
CASES = (('unchanged', 0.0), ('focus', 0.5), ('knock', 0.25))


def whitened_rows(model, name, samples):
    """Return [(stamp, X (3,), r (2,), J (2, 7))] of camera ``name`` over ``samples``."""
    cam = model.cameras[name]
    out = []
    for s in samples:
        if name not in s.observations:
            continue
        f = fuse(model, s.point_nominal,
                 {n: o.uv[0] for n, o in s.observations.items() if n != name})
        if f is None:
            continue
        pj = project_with_jacobians(cam.intrinsics(), cam.dist, cam.rotation,
                                    cam.translation, f.X[None])
        S = model.sigma_px[name] ** 2 * np.eye(2) + pj.d_point[0] @ f.cov @ pj.d_point[0].T
        Lt = np.linalg.cholesky(np.linalg.inv(S)).T
        Jf = (pj.uv[0] - cam.intrinsics()[2:])[:, None]          # d uv / d (focal scale)
        J = np.hstack([pj.d_pose[0], Jf])
        out.append((s.stamp_ns, f.X, Lt @ (s.observations[name].uv[0] - pj.uv[0]), Lt @ J))
    return out


def field_mean(old, new_X):
    """Return the GP mean at ``new_X`` (M, 3) of the residuals of ``old`` rows, per axis."""
    if len(old) < 5:
        return np.zeros((len(new_X), 2))
    Xo = np.array([x for _, x, _, _ in old])
    R = np.array([r for _, _, r, _ in old])

    def k(a, b):
        d2 = np.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=2)
        return np.exp(-0.5 * d2 / FIELD_LENGTH ** 2)
    var = max(float(np.mean(R ** 2)) - 1.0, 1e-3)            # field variance over noise (1)
    K = var * k(Xo, Xo) + np.eye(len(Xo))
    return var * k(np.asarray(new_X), Xo) @ np.linalg.solve(K, R)


def _chi(rows):
    r = np.concatenate([x[2] for x in rows])
    J = np.vstack([x[3] for x in rows])
    d = np.linalg.lstsq(J, r, rcond=None)[0]
    e = r - J @ d
    return float(e @ e)


def ratios(rows):
    """
    Return [(stamp of the split, Lambda / median Lambda)] over the stream ``rows``.

    The median is the session's, all splits: a scale no online test has (it sees the future,
    and a change raises it), so the separation measured with it is an upper bound.
    """
    lams, stamps = [], []
    for k in range(W, len(rows) - W + 1):
        A, Bw = rows[k - W:k], rows[k:k + W]
        lams.append(_chi(A + Bw) - _chi(A) - _chi(Bw))
        stamps.append(rows[k][0])
    if not lams:
        return []
    med = float(np.median(lams))
    return [(t, v / med) for t, v in zip(stamps, lams)]


def case(args):
    """One session: the statistic's largest ratios, both variants, per camera."""
    cell, kind, size, seed = args
    rng = np.random.default_rng([seed, 31, int(size * 100), kind == 'focus'])
    names = list(B.CELLS[cell].sim_settings().camera_names)
    changed = names[int(rng.integers(len(names)))]
    t = float(rng.uniform(B.DURATION / 3, 2 * B.DURATION / 3))
    change = None
    if kind == 'knock':
        change = CameraChange(changed, t, rotation_deg=size,
                              translation_mm=float(rng.uniform(2, 10)))
    elif kind == 'focus':
        change = CameraChange(changed, t, focal_percent=size)
    sim = B.session(cell, seed, change)
    t_ns = sim.start_ns + int(t * 1e9)
    t0 = sim.start_ns + int(T_CALIBRATE * 1e9)
    samples = B.samples_of(sim, seed)
    n_pre = sum(1 for s in samples if s.stamp_ns < t0)
    cal = B.run_engine(sim, B.samples_of(sim, seed)[:n_pre], detect=False).current
    model = PredictionModel({n: c.camera for n, c in cal.cameras.items()},
                            {n: c.sigma_px for n, c in cal.cameras.items()}, 2e-4)
    out = {}
    for name in model.cameras:
        rows = whitened_rows(model, name, samples)
        new = [x for x in rows if x[0] >= t0]
        # The field from the views the calibration was not fitted to and that precede the
        # window pair (refitted every W views): what the model leaves in each region.
        corrected = []
        for k0 in range(0, len(new), W):
            past = new[:max(0, k0 - W)]
            mean = field_mean(past, [x[1] for x in new[k0:k0 + W]])
            corrected += [(s, X, r - m, J) for (s, X, r, J), m in zip(new[k0:k0 + W], mean)]
        res = {}
        for variant, stream in (('split', new), ('field', corrected)):
            rs = ratios(stream)
            near = [v for ts, v in rs if change is not None and t_ns - 10e9 <= ts < t_ns + 15e9]
            res[variant] = dict(max=max((v for _, v in rs), default=float('nan')),
                                near=max(near, default=float('nan')))
        out[name] = res
    return dict(cell=cell, kind=kind, size=size, seed=seed,
                changed=changed if change is not None else None, cameras=out)


def main(argv=None):
    """Run the sessions, print the table and write it to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--seeds', type=int, default=4)
    ap.add_argument('--processes', type=int, default=2)
    args = ap.parse_args(argv)
    cases = [(cell, kind, size, seed) for cell in B.CELL_SCENARIOS for kind, size in CASES
             for seed in range(args.seeds)]
    with Pool(args.processes) as pool:
        results = pool.map(case, cases, chunksize=1)
    rows = []
    for cell in B.CELL_SCENARIOS:
        line = [cell]
        for variant in ('split', 'field'):
            null = [max(c[variant]['max'] for c in r['cameras'].values())
                    for r in results if r['cell'] == cell and r['kind'] == 'unchanged']
            line.append(f'{max(null):.1f}')
            for kind, _ in CASES[1:]:
                hit = [r['cameras'][r['changed']][variant]['near'] for r in results
                       if r['cell'] == cell and r['kind'] == kind]
                line.append(', '.join(f'{v:.0f}' for v in hit))
        rows.append(line)
    text = '\n'.join([
        '## A split test for small camera changes (bench/change_split.py)', '',
        f'Measured to decide the next step for small changes, not used by the node. '
        f'Each cell\'s sessions (300 s, point level as in "changes"), calibrated on the first '
        f'{T_CALIBRATE:.0f} s (`kinematic`); then for every camera the split statistic '
        f'Lambda (one camera against two over {W} + {W} views, pose and focal length, linear) '
        f'divided by its median over the session (an oracle scale: an upper bound on what a '
        f'split test can separate). "unchanged max": the largest '
        f'ratio of any camera over each unchanged session, the worst of {args.seeds} seeds (a '
        f'threshold must sit above it); the change columns: the changed camera\'s largest '
        f'ratio for splits from 10 s before to 15 s after the change, per seed. "field": the '
        f'same after subtracting a smooth residual field fitted to the camera\'s earlier '
        f'views (GP mean, L = {FIELD_LENGTH} m). Machine: {machine()}.', '',
        table(['cell', 'split: unchanged max', 'split: 0.5 % focal', 'split: 0.25 deg knock',
               'field: unchanged max', 'field: 0.5 % focal', 'field: 0.25 deg knock'], rows)])
    print(text)
    write_section('change-split', text)
    write_json('change_split', dict(results=results, machine=machine()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
