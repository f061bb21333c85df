"""
Soak benchmark: the live node fed for hours of a three-camera cell, with abuse mixed in.

The node runs as its own process with the bag's parameter file (bags/demo, config/demo.yaml);
``armcal replay --loop`` plays the bag again and again at ``--rate`` (each pass makes the clock
jump back seven minutes, which the node must ride out), and an abuse publisher mixes in, every
few seconds, one of: a malformed CDR payload on an image topic, an image of the wrong size, a
message of 8 MB on a VGA topic, a joint state with a NaN, one lacking the robot's joints, one
with an extra joint, and a joint state an hour in the future.  Half-way the node is stopped
with SIGINT and started again (it resumes from its output_dir): the samples it had stored must
all come back.

Measured, once a minute: the node's resident memory (VmRSS from /proc), its CPU, and its
/diagnostics (samples, solves, every input counter).  The table gives them at the start, after
each hour of cell time and at the end; the target is memory flat within 10 % once the sample
store has stopped growing, and no stored sample lost at the restart.

Usage: python bench/soak.py [--cell-hours 8] [--rate 4] [--bag bags/demo]
       [--params config/demo.yaml]
Wall time is cell-hours / rate.  Writes docs/BENCHMARKS.md (section "soak") and
docs/bench/soak.json.
"""

import argparse
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402
from _ros import follow_calibration_diagnostics, interrupt  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from armcal_ros.settings import load_settings  # noqa: E402


#: The flood's replay rate: ten times real time, the issue's "10x the rate".
FLOOD_RATE = 10.0


def rss_mb(pid):
    """Return the resident memory of process ``pid`` in MB (VmRSS)."""
    with open(f'/proc/{pid}/status') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0
    return float('nan')


def cpu_s(pid):
    """Return the CPU seconds (user + system) process ``pid`` has used."""
    with open(f'/proc/{pid}/stat') as f:
        fields = f.read().rsplit(')', 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')


class Abuse(threading.Thread):
    """Publish one bad input every ``period`` seconds, in turn."""

    def __init__(self, node, settings, period):
        super().__init__(daemon=True)
        from sensor_msgs.msg import Image, JointState
        self.node, self.period = node, period
        self.stop = threading.Event()
        self.sent = {}
        self.js = node.create_publisher(JointState, settings.inputs.joint_states_topic, 10)
        self.img = node.create_publisher(Image, settings.inputs.image_topics[0], 5)
        self.Image, self.JointState = Image, JointState
        self.names = None

    def joint_names(self, names):
        """Set the robot's joint names (the bad joint states are variations of them)."""
        self.names = list(names)

    def run(self):
        """Publish until stopped."""
        kinds = ['malformed_cdr', 'wrong_size', 'oversize', 'nan_joint', 'missing_joints',
                 'extra_joint', 'future_stamp']
        k = 0
        while not self.stop.wait(self.period):
            kind = kinds[k % len(kinds)]
            k += 1
            now = time.time_ns()
            stamp = dict(sec=now // 1_000_000_000, nanosec=now % 1_000_000_000)
            if kind == 'malformed_cdr':
                self.img.publish(b'\x00\x01\x00\x00' + os.urandom(64))
            elif kind in ('wrong_size', 'oversize'):
                w, h = (64, 48) if kind == 'wrong_size' else (4000, 2000)
                m = self.Image(width=w, height=h, step=w, encoding='mono8', data=bytes(w * h))
                m.header.stamp.sec, m.header.stamp.nanosec = stamp['sec'], stamp['nanosec']
                self.img.publish(m)
            elif self.names:
                names, q = list(self.names), [0.0] * len(self.names)
                if kind == 'nan_joint':
                    q[0] = float('nan')
                elif kind == 'missing_joints':
                    names, q = ['not_a_joint'], [0.0]
                elif kind == 'extra_joint':
                    names, q = names + ['gripper'], q + [0.0]
                m = self.JointState(name=names, position=q)
                t = now + (3600 * 10 ** 9 if kind == 'future_stamp' else 0)
                m.header.stamp.sec, m.header.stamp.nanosec = t // 10 ** 9, t % 10 ** 9
                self.js.publish(m)
            self.sent[kind] = self.sent.get(kind, 0) + 1


def start_node(params, out_dir, env, log):
    """Start the node (resuming from ``out_dir``); return the process."""
    return subprocess.Popen(
        [sys.executable, '-m', 'armcal_ros.ros.node', '--ros-args', '--params-file', params,
         '-p', f'output_dir:={out_dir}', '-p', 'resume:=true'], env=env, cwd=ROOT,
        stdout=open(log, 'a'), stderr=subprocess.STDOUT)


def main():
    """Run the soak and write its table."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--bag', default=os.path.join(ROOT, 'bags', 'demo'))
    ap.add_argument('--params', default=os.path.join(ROOT, 'config', 'demo.yaml'))
    ap.add_argument('--cell-hours', type=float, default=8.0)
    ap.add_argument('--rate', type=float, default=4.0)
    ap.add_argument('--abuse-period', type=float, default=5.0, help='seconds of wall time')
    ap.add_argument('--flood-s', type=float, default=120.0,
                    help='seconds of wall time at 10x, three quarters through (0: none)')
    ap.add_argument('--no-write', action='store_true')
    args = ap.parse_args()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    from armcal_ros.io.bag import iter_messages

    settings = load_settings(args.params)
    tmp = tempfile.mkdtemp(prefix='armcal_soak_')
    out_dir = os.path.join(tmp, 'out')
    env = dict(os.environ, ROS_DOMAIN_ID=str(1 + os.getpid() % 200),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1',
               ROS_HOME=os.path.join(tmp, 'ros_home'), ROS_LOG_DIR=os.path.join(tmp, 'log'))
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE',
                                           'ROS_LOG_DIR')})
    log = os.path.join(tmp, 'node.log')
    wall = args.cell_hours * 3600.0 / args.rate
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('armcal_soak', context=ctx)
    diag = follow_calibration_diagnostics(node)
    abuse = Abuse(node, settings, args.abuse_period)
    for topic, _, _, msg in iter_messages(args.bag, [settings.inputs.joint_states_topic]):
        abuse.joint_names(msg.name)
        break
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    threading.Thread(target=executor.spin, daemon=True).start()

    proc = start_node(args.params, out_dir, env, log)
    rows, restart = [], {}
    deadline = time.monotonic() + 60
    while not diag and time.monotonic() < deadline:
        time.sleep(0.2)
    if not diag:
        raise RuntimeError(f'the node did not come up (see {log})')

    def start_replay(rate):
        return subprocess.Popen([sys.executable, '-m', 'armcal_ros.cli', 'replay', args.bag,
                                 '--rate', str(rate), '--loop', '--quiet'], env=env,
                                cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def stop_replay(p):
        p.send_signal(signal.SIGINT)
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()

    replay = start_replay(args.rate)
    abuse.start()
    t0 = time.monotonic()
    last_cpu, last_t = cpu_s(proc.pid), t0
    flood = {}
    try:
        while True:
            now = time.monotonic()
            if now - t0 >= wall:
                break
            if restart and not flood and now - t0 >= 0.75 * wall and args.flood_s > 0:
                # A flood: the bag at 10x for a while; the node must count what it cannot
                # take, skip it, and keep calibrating.
                stop_replay(replay)
                before = dict(diag)
                c0 = cpu_s(proc.pid)
                replay = start_replay(FLOOD_RATE)
                time.sleep(args.flood_s)
                stop_replay(replay)
                during = dict(diag)
                replay = start_replay(args.rate)
                time.sleep(min(120.0, args.flood_s))
                after = dict(diag)

                def delta(k, a, b):
                    return int(float(b.get(k, 0))) - int(float(a.get(k, 0)))
                keys = sorted(k for k in during if k.startswith(('input_', 'queue_dropped_',
                                                                 'sample_')))
                flood = dict(cell_h=(now - t0) * args.rate / 3600.0, wall_s=args.flood_s,
                             rate=FLOOD_RATE, alive=proc.poll() is None,
                             cpu_pct=100.0 * (cpu_s(proc.pid) - c0) / args.flood_s,
                             counts={k: delta(k, before, during) for k in keys
                                     if delta(k, before, during)},
                             solves_during=delta('solves', before, during),
                             solves_after=delta('solves', during, after),
                             samples=int(float(after.get('samples', 0))))
                print(f'flood: {flood}', flush=True)
                last_cpu, last_t = cpu_s(proc.pid), time.monotonic()
            if not restart and now - t0 >= wall / 2:
                # Half-way: stop and start again; every stored sample must come back.
                before = int(diag.get('samples', 0))
                proc.send_signal(signal.SIGINT)
                proc.wait(30)
                diag.clear()
                proc = start_node(args.params, out_dir, env, log)
                t_r = time.monotonic()
                while 'restored' not in diag and time.monotonic() - t_r < 60:
                    time.sleep(0.2)
                restart = dict(before=before, restored=diag.get('restored', ''),
                               after=int(diag.get('samples', 0)),
                               cell_h=(now - t0) * args.rate / 3600.0)
                last_cpu, last_t = cpu_s(proc.pid), time.monotonic()
            time.sleep(60.0 - (time.monotonic() - t0) % 60.0)
            c, t = cpu_s(proc.pid), time.monotonic()
            rows.append(dict(cell_h=(t - t0) * args.rate / 3600.0, rss_mb=rss_mb(proc.pid),
                             cpu_pct=100.0 * (c - last_cpu) / (t - last_t),
                             samples=int(diag.get('samples', 0)),
                             solves=int(diag.get('solves', 0)),
                             counts={k: v for k, v in diag.items()
                                     if k.startswith(('input_', 'queue_dropped_'))}))
            last_cpu, last_t = c, t
            print(f'{rows[-1]["cell_h"]:.2f} cell-h: RSS {rows[-1]["rss_mb"]:.0f} MB, CPU '
                  f'{rows[-1]["cpu_pct"]:.0f} %, samples {rows[-1]["samples"]}, solves '
                  f'{rows[-1]["solves"]}', flush=True)
    finally:
        abuse.stop.set()
        stop_replay(replay)
        final = dict(diag)
        interrupt(proc)
        executor.shutdown()
        node.destroy_node()
        ctx.try_shutdown()
    alive = proc.returncode == 0
    pick = [rows[0]] + [r for r in rows if abs(r['cell_h'] - round(r['cell_h'])) <
                        args.rate / 120.0 and round(r['cell_h']) >= 1] + [rows[-1]]
    seen, table_rows = set(), []
    for r in pick:
        key = round(r['cell_h'], 1)
        if key in seen:
            continue
        seen.add(key)
        table_rows.append([f'{r["cell_h"]:.1f}', f'{r["rss_mb"]:.0f}', f'{r["cpu_pct"]:.0f}',
                           r['samples'], r['solves']])
    # Memory once warm: per node process (before and after the restart), from one cell-hour
    # after its start with the sample store full (95 % of its final size), to its end.
    t_restart = restart.get('cell_h', float('inf'))
    windows = []
    for lo, hi in ((0.0, t_restart), (t_restart, float('inf'))):
        seg = [r for r in rows if lo <= r['cell_h'] < hi]
        if not seg:
            continue
        warm = [r for r in seg if r['cell_h'] >= lo + 1.0 and
                r['samples'] >= 0.95 * seg[-1]['samples']]
        if len(warm) >= 2:
            rss = np.array([r['rss_mb'] for r in warm])
            windows.append(dict(first_h=warm[0]['cell_h'], last_h=warm[-1]['cell_h'],
                                lo=float(rss.min()), hi=float(rss.max()),
                                start=float(rss[0]), end=float(rss[-1]),
                                spread=float((rss.max() - rss.min()) / rss.min() * 100.0)))
    flat = '; '.join(f'{w["first_h"]:.1f}-{w["last_h"]:.1f} cell-hours: {w["lo"]:.0f}-'
                     f'{w["hi"]:.0f} MB ({w["start"]:.0f} at its start, {w["end"]:.0f} at its '
                     f'end), a spread of {w["spread"]:.1f} %' for w in windows) or 'n/a'
    counters = {k: v for k, v in final.items() if k.startswith(('input_', 'queue_dropped_'))
                and str(v) not in ('0', '0.0')}
    text = '\n'.join([
        '## Soak (bench/soak.py)',
        '',
        f'The node fed `{os.path.relpath(args.bag, ROOT)}` looped at {args.rate:g}x for '
        f'{args.cell_hours:g} cell-hours ({wall / 3600.0:.1f} h of wall time), one bad input '
        f'every {args.abuse_period:g} s (malformed CDR, an image of the wrong size, 8 MB on a '
        f'VGA topic, a NaN joint, missing joints, an extra joint, a stamp an hour ahead; each '
        f'pass of the bag also jumps the clock back), stopped with SIGINT and restarted '
        f'half-way. Memory is VmRSS of the node process; CPU in % of one core over the minute '
        f'before. Machine: {machine()}.',
        '',
        table(['cell hours', 'RSS MB', 'CPU %', 'samples', 'solves'], table_rows),
        '',
        f'Memory of each node process from one cell-hour after its start (the sample store '
        f'full) to its end: {flat} (target: within 10 %). The node returns the heap\'s free '
        f'pages to the system after each solve (malloc_trim) and pins glibc\'s mmap '
        f'threshold (armcal_ros/ros/memory.py). '
        f'Restart at {restart.get("cell_h", float("nan")):.1f} cell-hours: '
        f'{restart.get("before")} samples stored before, "{restart.get("restored")}" after. '
        f'The node exited cleanly at the end: {alive}. Bad inputs sent: {abuse.sent}. Final '
        f'input counters: {counters}.',
        '',
        (f'Flood at {flood["cell_h"]:.1f} cell-hours: the bag at {flood["rate"]:g}x for '
         f'{flood["wall_s"]:.0f} s of wall time ({flood["cpu_pct"]:.0f} % of a core). What the '
         f'node counted meanwhile: {flood["counts"]}. Solves during it: '
         f'{flood["solves_during"]}, in the {min(120.0, flood["wall_s"]):.0f} s after it: '
         f'{flood["solves_after"]}; samples after it: {flood["samples"]}; the node alive '
         f'throughout: {flood["alive"]}.') if flood else 'No flood was run.',
        '',
        'Before the heap was trimmed after each solve, the same soak (4 cell-hours, '
        '2026-12-02) grew 234 -> 322 MB, 30 % over the hours with the store full, while '
        'tracemalloc showed the Python objects flat (14.2-14.6 MB traced over four passes of '
        'the bag in one process; in the node, 107-160 MB of traced objects, falling, while its '
        'RSS rose 464 -> 591 MB): the growth was freed C-heap pages that glibc kept resident. '
        'One malloc_trim(0) a minute on the running node took it from 220-243 MB back to '
        '184-200 MB each time, and the after-trim figure levelled off within a cell-hour.',
    ])
    print(text)
    if not args.no_write:
        write_section('soak', text)
        write_json('soak', dict(rows=rows, restart=restart, final=final, sent=abuse.sent,
                                windows=windows, flood=flood,
                                rate=args.rate, cell_hours=args.cell_hours,
                                machine=machine()))


if __name__ == '__main__':
    main()
