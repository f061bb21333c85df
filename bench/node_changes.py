"""
Cameras that move, in the live node: what it declares, publishes meanwhile and ends with.

bench/changes_images.py reads its lamp-lit recordings as `armcal calibrate` does, in time
order, all at once.  Here the same recordings (the same seed, length and changes: unchanged;
the second camera knocked by 0.25 deg and 3 mm at mid-session; the last camera's focal length
0.5 % longer at mid-session) are replayed in real time through the node, which runs as its own
process with the cell's parameters (the node's defaults: ``solve_period`` 10 s, ``auto``,
``shaded_pooled``) and sees them over DDS as it would see a cell's drivers: it solves while
the images come, drops what it cannot keep up with, and publishes as it goes.  And each
recording is calibrated offline (``calibrate_bag``, the latency pass included) beside it.

Per recording and run: the changes declared (from the output directory's changes.json),
whether the changed camera was found and when (seconds after the change, on the bag's clock),
the changed camera's CameraInfo withdrawn (K zero) meanwhile - from the first withdrawn one to
the next calibrated one, bag seconds - and, against the truth at the end of the recording, the
changed camera's rotation (deg), centre (mm) and focal length (%) as last published (node) or
written (offline), and the worst unchanged camera's rotation.

Usage: python bench/node_changes.py [--seed 0] [--duration 180] [--rate 1] [--bags DIR]
[--cells puma-3cam ur5-2cam desk-4cam].  Writes docs/BENCHMARKS.md (section "node_changes")
and docs/bench/node_changes.json.
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np
from scipy.spatial.transform import Rotation

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402
from _ros import (follow_calibration_diagnostics, interrupt,  # noqa: E402
                  wait_for_diagnostics)
from changes_images import _cases, FOCUS_PERCENT, KNOCK, record  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from armcal_ros.io.calib_files import read_cameras  # noqa: E402
from armcal_ros.offline import calibrate_bag  # noqa: E402
from armcal_ros.settings import load_settings  # noqa: E402

DEFAULT_CELLS = ('puma-3cam', 'ur5-2cam', 'desk-4cam')


def _angle_deg(Ra, Rb):
    return float(np.degrees(np.linalg.norm(Rotation.from_matrix(Ra @ Rb.T).as_rotvec())))


def camera_errors(rotation, centre, fx, truth):
    """Return (rotation deg, centre mm, focal %) of one camera against its ``truth`` Camera."""
    t_centre = -truth.rotation.T @ truth.translation
    return (_angle_deg(rotation, truth.rotation),
            float(np.linalg.norm(centre - t_centre) * 1e3),
            float((fx / truth.fx - 1.0) * 100.0))


def offline_run(bag, params, out_dir):
    """Calibrate ``bag`` as `armcal calibrate` does; return {camera: (R, centre, fx)}, records."""
    calibrate_bag(bag, load_settings(params), out_dir)
    _, cams = read_cameras(out_dir)
    got = {c.name: (c.rotation, -c.rotation.T @ c.translation, c.fx) for c in cams}
    return got, _records(out_dir)


def _records(out_dir):
    path = os.path.join(out_dir, 'changes.json')
    if not os.path.exists(path):
        return []
    with open(path) as f:
        return json.load(f)['records']


def node_run(bag, params, out_dir, rate, cameras, env):
    """
    Replay ``bag`` at ``rate`` into a node process; return what it published and declared.

    Returns ({camera: (R, centre, fx)} as last published (cameras with no calibrated
    CameraInfo left out), records, {camera: [(stamp ns, calibrated?)]} of its CameraInfo,
    replay statistics, the node's last /diagnostics).
    """
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import CameraInfo

    from armcal_ros.io.message_fields import stamp_ns
    from armcal_ros.ros.replay import replay

    log = open(os.path.join(out_dir, 'node.log'), 'w')
    proc = subprocess.Popen(
        [sys.executable, '-m', 'armcal_ros.ros.node', '--ros-args', '--params-file', params,
         '-p', f'output_dir:={out_dir}', '-p', 'resume:=false'],
        env=env, cwd=ROOT, stdout=log, stderr=subprocess.STDOUT)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('armcal_bench_changes', context=ctx)
    diag = follow_calibration_diagnostics(node)
    infos = {c: [] for c in cameras}
    last_k = {}
    last_pose = {}

    def on_info(cam):
        def cb(msg):
            ok = msg.k[0] != 0.0
            infos[cam].append((stamp_ns(msg.header.stamp), ok))
            last_k[cam] = msg.k[0] if ok else None
        return cb

    def on_pose(cam):
        def cb(msg):
            last_pose[cam] = msg.pose.pose
        return cb
    for cam in cameras:
        node.create_subscription(CameraInfo, f'/armcal/{cam}/camera_info', on_info(cam),
                                 QoSProfile(depth=500))
        node.create_subscription(PoseWithCovarianceStamped, f'/armcal/{cam}/pose',
                                 on_pose(cam), 10)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    try:
        wait_for_diagnostics(diag)
        time.sleep(1.5)
        stats = replay(node, bag, rate=rate, discovery_timeout=5.0)
        # The last dwell closes on the idle flush; a solve due at the end gets its period.
        time.sleep(3.0 + 12.0 / rate)
        final = dict(diag)
    finally:
        interrupt(proc)
        executor.shutdown()
        spin.join(10)
        node.destroy_node()
        ctx.try_shutdown()
        log.close()
    got = {}
    for cam in cameras:
        p = last_pose.get(cam)
        if p is None or last_k.get(cam) is None:
            continue
        q = p.orientation
        # The pose is T_base_camera: its rotation is the camera's R^T, its position the centre.
        R = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix().T
        got[cam] = (R, np.array([p.position.x, p.position.y, p.position.z]), last_k[cam])
    return got, _records(out_dir), infos, stats, final


def views_between(out_dir, camera, t0_ns, t1_ns):
    """Return how many views of ``camera`` the run stored (retired ones too) in [t0, t1]."""
    store = np.load(os.path.join(out_dir, 'samples.npz'))
    k = json.loads(str(store['meta']))['camera_names'].index(camera)
    obs = np.concatenate([store['obs'], store['retired_obs']])
    st = obs[obs[:, 1] == k, 3]
    return int(np.sum((st >= t0_ns) & (st <= t1_ns)))


def summarise(got, records, truth, change, start, out_dir, infos=None):
    """Return one row's figures from a run's cameras, change records and output directory."""
    declared = [r for r in records if r['kind'] in ('camera', 'arm') and
                r['status'] != 'reported']
    reports = [r for r in records if r not in declared]
    out = dict(declared=[dict(camera=r['camera'], what=r['what'],
                              onset_s=(r['onset_ns'] - start) * 1e-9,
                              detected_s=(r['detected_ns'] - start) * 1e-9) for r in declared],
               reports=len(reports), found=False, errors={})
    for name, (R, centre, fx) in got.items():
        out['errors'][name] = camera_errors(R, centre, fx, truth[name])
    if change is not None:
        hit = [d for d in out['declared'] if d['camera'] == change.camera and
               d['detected_s'] >= change.time_s]
        if hit:
            out.update(found=True, delay_s=hit[0]['detected_s'] - change.time_s,
                       what=hit[0]['what'], delay_views=views_between(
                           out_dir, change.camera, start + int(change.time_s * 1e9),
                           start + int(hit[0]['detected_s'] * 1e9)))
        out['false'] = len(out['declared']) - (1 if hit else 0)
        if infos is not None:
            t_change = start + int(change.time_s * 1e9)
            seq = [(s, ok) for s, ok in infos[change.camera] if s >= t_change]
            off = next((s for s, ok in seq if not ok), None)
            if off is not None:
                back = next((s for s, ok in seq if ok and s > off), None)
                out['withdrawn_s'] = ((off - start) * 1e-9,
                                      None if back is None else (back - start) * 1e-9)
    else:
        out['false'] = len(out['declared'])
    return out


def main(argv=None):
    """Run the benchmark, print the table and write it to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--duration', type=float, default=180.0)
    ap.add_argument('--rate', type=float, default=1.0)
    ap.add_argument('--bags', default=None, help='keep the recordings here (default: a '
                    'temporary directory)')
    ap.add_argument('--cells', nargs='*', default=list(DEFAULT_CELLS))
    ap.add_argument('--no-write', action='store_true', help='print only')
    args = ap.parse_args(argv)
    tmp = tempfile.mkdtemp(prefix='armcal_bench_node_changes_')
    bags = args.bags or os.path.join(tmp, 'bags')
    os.makedirs(bags, exist_ok=True)
    env = dict(os.environ, ROS_DOMAIN_ID=str(1 + os.getpid() % 200),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1',
               ROS_LOG_DIR=os.path.join(tmp, 'log'))
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE',
                                           'ROS_LOG_DIR')})
    rows = []
    for k, (name, label, change) in enumerate(c for c in _cases(args.duration)
                                              if c[0] in args.cells):
        bag, params, start = record(name, label, change, args.seed, args.duration, bags)
        _, truth_cams = read_cameras(os.path.join(bag, 'ground_truth'))
        truth = {c.name: c for c in truth_cams}
        cameras = list(load_settings(params).inputs.camera_names)
        base = dict(cell=name, case=label, changed=None if change is None else change.camera)
        t0 = time.perf_counter()
        out = os.path.join(tmp, f'offline_{k}')
        got, recs = offline_run(bag, params, out)
        rows.append(dict(base, run='offline', wall_s=time.perf_counter() - t0,
                         **summarise(got, recs, truth, change, start, out)))
        out = os.path.join(tmp, f'node_{k}')
        os.makedirs(out)
        got, recs, infos, stats, final = node_run(bag, params, out, args.rate, cameras, env)
        sent = sum(v for t, v in stats.published.items() if t != '/joint_states')
        rows.append(dict(base, run=f'node {args.rate:g}x', wall_s=stats.wall_s,
                         images=f'{int(final.get("input_frames", 0))}/{sent}',
                         solves=int(final.get('solves', 0)),
                         rejected=int(final.get('solves_rejected', 0)),
                         **summarise(got, recs, truth, change, start, out, infos)))
        for r in rows[-2:]:
            print(json.dumps(r), flush=True)
    text = render(rows, args)
    print(text)
    if not args.no_write:
        write_section('node_changes', text)
        write_json('node_changes', dict(rows=rows, seed=args.seed, duration=args.duration,
                                        rate=args.rate, machine=machine()))
    return 0


def _fmt(x, spec):
    return '-' if x is None else format(x, spec)


def render(rows, args):
    """Return the markdown section of ``rows``."""
    body = []
    for r in rows:
        ch = r['changed']
        err = r['errors'].get(ch) if ch else None
        others = [e[0] for n, e in r['errors'].items() if n != ch]
        w = r.get('withdrawn_s')
        withdrawn = '-' if not w else (f'{w[0]:.1f}-' + ('end' if w[1] is None
                                                         else f'{w[1]:.1f}'))
        solves = ('-' if 'solves' not in r else f'{r["solves"]}' +
                  (f' ({r["rejected"]})' if 'rejected' in r else ''))
        body.append([r['cell'], r['case'], r['run'], r.get('images', '-'), solves,
                     ch or '-', ('yes' if r['found'] else 'NO') if ch else '-',
                     r.get('delay_views', '-'), _fmt(r.get('delay_s'), '.1f'),
                     r.get('what', '-'), r['false'],
                     r['reports'],
                     withdrawn,
                     _fmt(err[0] if err else None, '.3f'), _fmt(err[1] if err else None, '.1f'),
                     _fmt(err[2] if err else None, '+.3f'),
                     _fmt(max(others) if others else None, '.3f'),
                     len(r['errors'])])
    return '\n'.join([
        '## Cameras that move, in the live node (bench/node_changes.py)', '',
        f'The recordings of *changes-images* (each cell {args.duration:.0f} s, seed {args.seed}, '
        f'one lamp: unchanged; its second camera knocked by {KNOCK[0]:g} deg and {KNOCK[1]:g} mm '
        f'at mid-session; its last camera\'s focal length {FOCUS_PERCENT:g} % longer at '
        f'mid-session) replayed at {args.rate:g}x over DDS into the node (its own process, the '
        f'cell\'s parameters, the node\'s defaults), and calibrated offline (`calibrate_bag`, '
        f'latency pass included). Images: received by the node / published. Solves: the '
        f'node\'s, (those refused) where counted. Found: the changed '
        f'camera declared changed after the change; delay: its views the run stored and bag '
        f'seconds from the change to the declaration; false: other changes declared; reports: '
        f'disagreements reported, nothing retired. Withdrawn: the changed camera\'s CameraInfo '
        f'published uncalibrated (K zero) from / until (bag seconds; "end": never calibrated '
        f'again). Errors against the truth at the end of the recording, of the changed camera\'s '
        f'last published (node) or written (offline) calibration: rotation, centre, focal '
        f'length; the worst unchanged camera\'s rotation (unchanged recordings: every camera). '
        f'Cameras: those with a calibration at the end. Measured on {machine()}.', '',
        table(['cell', 'case', 'run', 'images', 'solves', 'changed', 'found', 'delay views',
               'delay s', 'called',
               'false', 'reports', 'withdrawn s', 'rotation deg', 'centre mm', 'focal %',
               'unchanged worst rotation deg', 'cameras'], body)])


if __name__ == '__main__':
    sys.exit(main())
