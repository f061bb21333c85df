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
from _ros import follow_calibration_diagnostics  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from armcal_ros.settings import load_settings  # noqa: E402


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
    replay = subprocess.Popen([sys.executable, '-m', 'armcal_ros.cli', 'replay', args.bag,
                               '--rate', str(args.rate), '--loop', '--quiet'], env=env,
                              cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    abuse.start()
    t0 = time.monotonic()
    last_cpu, last_t = cpu_s(proc.pid), t0
    try:
        while True:
            now = time.monotonic()
            if now - t0 >= wall:
                break
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
        replay.send_signal(signal.SIGINT)
        try:
            replay.wait(30)
        except subprocess.TimeoutExpired:
            replay.kill()
        final = dict(diag)
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
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
    # Memory once the store stopped growing: from the first row with 95 % of the final samples.
    full = [r for r in rows if r['samples'] >= 0.95 * rows[-1]['samples']]
    rss = np.array([r['rss_mb'] for r in full])
    drift = (rss.max() - rss.min()) / rss.min() * 100.0 if len(rss) else float('nan')
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
        f'Memory once the sample store had stopped growing (last {len(full)} minutes): '
        f'{rss.min():.0f}-{rss.max():.0f} MB, a spread of {drift:.1f} % (target: within '
        f'10 %). Restart at {restart.get("cell_h", float("nan")):.1f} cell-hours: '
        f'{restart.get("before")} samples stored before, "{restart.get("restored")}" after. '
        f'The node exited cleanly at the end: {alive}. Bad inputs sent: {abuse.sent}. Final '
        f'input counters: {counters}.',
    ])
    print(text)
    if not args.no_write:
        write_section('soak', text)
        write_json('soak', dict(rows=rows, restart=restart, final=final, sent=abuse.sent,
                                rate=args.rate, cell_hours=args.cell_hours,
                                machine=machine()))


if __name__ == '__main__':
    main()
