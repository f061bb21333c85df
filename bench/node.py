"""
Live node benchmark: CPU, sample latency and the fastest replay that loses no dwell.

The node runs as its own process with the bag's parameter file (bags/demo and config/demo.yaml
by default: 7 min of teleoperation, JointState at 200 Hz, three 640x480 cameras at 15 Hz).  This
script replays the bag in-process (armcal_ros.ros.replay, reliable publishers) and measures:

- CPU of the node process from /proc/<pid>/stat (utime + stime), sampled every second: the
  average over the replay and the peak one-second value, in % of one core (solves included);
- latency from the last image of a dwell to the sample being stored: for each message on
  ~/samples (published when the store takes a sample), the wall time it arrived here minus the
  wall time the replay published the dwell's last image (the last image, any camera, whose stamp
  lies in the ground-truth dwell interval that contains the sample's stamp);
- lost dwells: the ground-truth dwells that got a stored sample offline (the same
  SampleCollector and SampleStore fed in bag order) but none in the node (its ~/samples); the
  highest rate among --rates with none lost.  (Counting samples instead would hide losses: a
  dwell split by a lost joint state gives two samples that the store merges.)

- CameraInfo beside the images: for every image the replay published after a camera's first
  calibration, whether a CameraInfo with the image's stamp arrived on ~/<camera>/camera_info
  (what an exact-time synchronizer needs), and the latency image published -> its CameraInfo
  received;
- shutdown: SIGINT -> the node process gone, seconds (samples saved on the way).

The first rate is also run with solves disabled (min_samples 100000), to separate the front
end's CPU from the solver's, and with the solves on a thread of the node (``solver_process``
false; the node's CPU is then the solves' too); the second rate with ``republish_images`` on.
The node's own CPU and its solver process's (the node's children) are read separately.

Usage: python bench/node.py [--bag bags/demo] [--params config/demo.yaml] [--rates 1 2 4 8]
Writes docs/BENCHMARKS.md (section "node") and docs/bench/node.json.  The first rate is the one
CPU and latency are reported for (1x by default).
"""

import argparse
import os
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402
from _ros import (follow_calibration_diagnostics, interrupt,  # noqa: E402
                  wait_for_diagnostics)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from armcal_ros.compose import build_pipeline  # noqa: E402
from armcal_ros.io.message_fields import stamp_ns  # noqa: E402
from armcal_ros.offline import feed, open_bag  # noqa: E402
from armcal_ros.settings import load_settings  # noqa: E402


#: The bag's image topics, in the order of the cameras (set by main()).
image_topics = []


def offline_samples(bag, settings):
    """Return the stamps of the samples the offline front end stores from ``bag``."""
    pipe = build_pipeline(settings)
    out = []
    for event in open_bag(bag, settings).events():
        out += feed(pipe.collector, event)
    return [s.stamp_ns for s in out + pipe.collector.flush()
            if pipe.engine.add_sample(s).value != 'dropped']


def dwells_covered(stamps, gt):
    """Return the set of ground-truth dwell indices whose interval holds one of ``stamps``."""
    starts, ends = gt['dwell_start_ns'], gt['dwell_end_ns']
    out = set()
    for st in stamps:
        k = np.nonzero((starts <= st) & (st <= ends))[0]
        if len(k):
            out.add(int(k[0]))
    return out


class CpuSampler(threading.Thread):
    """
    Sample a process's CPU time, and its children's, from /proc once a second.

    The children are the node's solver process (``solver_process``); each child's time is
    read while it lives, and a child that ended keeps its last reading.
    """

    def __init__(self, pid):
        super().__init__(daemon=True)
        self.pid, self.tick = pid, os.sysconf('SC_CLK_TCK')
        self.samples = []            # (wall time, own cpu seconds, children's cpu seconds)
        self._children = {}          # pid -> its latest cpu seconds
        self.stop = threading.Event()

    def _stat(self, pid):
        with open(f'/proc/{pid}/stat') as f:
            fields = f.read().rsplit(')', 1)[1].split()
        return int(fields[1]), (int(fields[11]) + int(fields[12])) / self.tick  # ppid, cpu

    def _read_children(self):
        for entry in os.listdir('/proc'):
            if entry.isdigit() and int(entry) != self.pid:
                try:
                    ppid, cpu = self._stat(entry)
                except (OSError, ValueError, IndexError):
                    continue
                if ppid == self.pid:
                    self._children[int(entry)] = cpu
        return sum(self._children.values())

    def run(self):
        while not self.stop.is_set():
            try:
                own = self._stat(self.pid)[1]
            except OSError:
                return
            self.samples.append((time.monotonic(), own, self._read_children()))
            self.stop.wait(1.0)

    def between(self, t0, t1, column=1):
        """Return (average %, peak 1-s %) of one core between t0 and t1 (2: the children)."""
        s = np.array([x for x in self.samples if t0 <= x[0] <= t1])
        if len(s) < 2:
            return float('nan'), float('nan')
        c = s[:, column] if column in (1, 2) else s[:, 1] + s[:, 2]
        rates = np.diff(c) / np.diff(s[:, 0]) * 100.0
        return float((c[-1] - c[0]) / (s[-1, 0] - s[0, 0]) * 100.0), float(rates.max())


def run_rate(bag, params, rate, gt, out_dir, env, cameras, extra=()):
    """Start a node (``extra``: -p overrides), replay at ``rate``, return the measurements."""
    import rclpy
    from geometry_msgs.msg import PointStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile
    from sensor_msgs.msg import CameraInfo

    from armcal_ros.ros.raw_message import header_fields
    from armcal_ros.ros.replay import replay

    node_proc = subprocess.Popen(
        [sys.executable, '-m', 'armcal_ros.ros.node', '--ros-args', '--params-file', params,
         '-p', f'output_dir:={out_dir}', '-p', 'resume:=false']
        + [a for x in extra for a in ('-p', x)], env=env, cwd=ROOT,
        stdout=open(os.path.join(out_dir, f'node_{rate:g}.log'), 'w'), stderr=subprocess.STDOUT)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = rclpy.create_node('armcal_bench', context=ctx)
    samples = []
    node.create_subscription(PointStamped, '/armcal/samples',
                             lambda m: samples.append((time.time(), stamp_ns(m.header.stamp))),
                             100)
    diag = follow_calibration_diagnostics(node)
    infos = {c: [] for c in cameras}         # (wall time received, header stamp ns)

    def on_info(cam):
        def cb(raw):
            sec, nsec, _ = header_fields(raw)
            infos[cam].append((time.time(), sec * 1_000_000_000 + nsec))
        return cb
    for cam in cameras:
        node.create_subscription(CameraInfo, f'/armcal/{cam}/camera_info', on_info(cam),
                                 QoSProfile(depth=500), raw=True)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    spin = threading.Thread(target=executor.spin, daemon=True)
    spin.start()
    published = {}               # image header stamp -> publish wall time
    by_camera = {c: [] for c in cameras}         # camera -> [(publish wall, stamp)]
    topic_camera = dict(zip(image_topics, cameras))

    def on_publish(topic, t_ns, wall, msg):
        if topic != '/joint_states':
            published[stamp_ns(msg.header.stamp)] = max(published.get(
                stamp_ns(msg.header.stamp), 0.0), wall)
            if topic in topic_camera:
                by_camera[topic_camera[topic]].append((wall, stamp_ns(msg.header.stamp)))
    cpu = CpuSampler(node_proc.pid)
    try:
        wait_for_diagnostics(diag)
        cpu.start()
        time.sleep(1.5)
        t0 = time.monotonic()
        stats = replay(node, bag, rate=rate, on_publish=on_publish, discovery_timeout=5.0)
        t1 = time.monotonic()
        time.sleep(3.0)          # the idle flush closes the last dwell
        cpu_avg, cpu_peak = cpu.between(t0 + stats.discovery_s, t1)
        solver_avg, solver_peak = cpu.between(t0 + stats.discovery_s, t1, column=2)
        total_avg, total_peak = cpu.between(t0 + stats.discovery_s, t1, column=3)
        final = dict(diag)
    finally:
        cpu.stop.set()
        t_sig = time.monotonic()
        interrupt(node_proc)
        shutdown_s = time.monotonic() - t_sig
        executor.shutdown()
        spin.join(10)
        node.destroy_node()
        ctx.try_shutdown()
    produced = sum(int(final.get(f'input_sample_{k}', 0))
                   for k in ('added', 'merged', 'replaced', 'dropped'))
    # latency: sample -> its dwell -> the dwell's last published image
    starts, ends = gt['dwell_start_ns'], gt['dwell_end_ns']
    img_stamps = np.array(sorted(published))
    lat = []
    for wall, st in samples:
        k = np.nonzero((starts <= st) & (st <= ends))[0]
        if not len(k):
            continue
        inside = img_stamps[(img_stamps >= starts[k[0]]) & (img_stamps <= ends[k[0]])]
        if len(inside):
            lat.append(wall - published[int(inside[-1])])
    dropped = {k[len('queue_dropped_'):]: int(v) for k, v in final.items()
               if k.startswith('queue_dropped_')}
    # CameraInfo beside every image, from each camera's first calibration on
    info_paired = info_images = 0
    info_lat = []
    for cam in cameras:
        got = {st: wall for wall, st in infos[cam]}
        sent = by_camera[cam]
        first = next((k for k, (_, st) in enumerate(sent) if st in got), None)
        if first is None:
            continue
        for wall, st in sent[first:]:
            info_images += 1
            if st in got:
                info_paired += 1
                info_lat.append(got[st] - wall)
    return dict(rate=rate, wall_s=stats.wall_s, bag_s=stats.bag_s, max_lag_s=stats.max_lag_s,
                cpu_avg=cpu_avg, cpu_peak=cpu_peak, solver_cpu_avg=solver_avg,
                solver_cpu_peak=solver_peak, total_cpu_avg=total_avg, total_cpu_peak=total_peak,
                samples_produced=produced,
                samples_stored=int(final.get('samples', 0)),
                frames=int(final.get('input_frames', 0)),
                joint_states=int(final.get('input_joint_states', 0)),
                published=stats.published, queue_dropped=dropped,
                solves=int(final.get('solves', 0)), extra=list(extra),
                covered=sorted(dwells_covered([st for _, st in samples], gt)),
                latency_s=[float(x) for x in lat], info_images=info_images,
                info_paired=info_paired, info_latency_s=[float(x) for x in info_lat],
                shutdown_s=shutdown_s)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--bag', default=os.path.join(ROOT, 'bags', 'demo'))
    ap.add_argument('--params', default=os.path.join(ROOT, 'config', 'demo.yaml'))
    ap.add_argument('--rates', type=float, nargs='+', default=[1.0, 2.0, 4.0])
    ap.add_argument('--no-write', action='store_true', help='print only')
    args = ap.parse_args()
    env = dict(os.environ, ROS_DOMAIN_ID=str(1 + os.getpid() % 200),
               ROS_AUTOMATIC_DISCOVERY_RANGE='LOCALHOST', PYTHONUNBUFFERED='1')
    tmp = tempfile.mkdtemp(prefix='armcal_bench_node_')
    env.setdefault('ROS_LOG_DIR', os.path.join(tmp, 'log'))
    os.environ.update({k: env[k] for k in ('ROS_DOMAIN_ID', 'ROS_AUTOMATIC_DISCOVERY_RANGE',
                                           'ROS_LOG_DIR')})
    settings = load_settings(args.params)
    gt = np.load(os.path.join(args.bag, 'ground_truth', 'markers.npz'))
    t = time.perf_counter()
    ref_stamps = offline_samples(args.bag, settings)
    ref_dwells = dwells_covered(ref_stamps, gt)
    reference = len(ref_dwells)
    print(f'offline front end: {len(ref_stamps)} samples covering {reference} of '
          f'{len(gt["dwell_start_ns"])} dwells ({time.perf_counter() - t:.0f} s)', flush=True)
    runs = []
    configs = ([(args.rates[0], ['min_samples:=100000'])] + [(r, []) for r in args.rates]
               + [(args.rates[min(1, len(args.rates) - 1)], ['republish_images:=true']),
                  (args.rates[0], ['solver_process:=false'])])
    cameras = list(settings.inputs.camera_names)
    image_topics[:] = list(settings.inputs.image_topics)
    for i, (rate, extra) in enumerate(configs):
        out = os.path.join(tmp, f'run_{i}')
        os.makedirs(out)
        r = run_rate(args.bag, args.params, rate, gt, out, env, cameras, extra)
        r['lost'] = len(ref_dwells - set(r['covered']))
        lat = np.array(r['latency_s'])
        print(f'rate {rate:g}x {extra}: cpu avg {r["cpu_avg"]:.0f} % peak {r["cpu_peak"]:.0f} %, '
              f'solver process {r["solver_cpu_avg"]:.0f} %, '
              f'dwells lost {r["lost"]}/{reference}, latency median '
              f'{np.median(lat) if len(lat) else float("nan"):.3f} s, '
              f'dropped {r["queue_dropped"]}, replay lag {r["max_lag_s"]:.2f} s, CameraInfo '
              f'{r["info_paired"]}/{r["info_images"]}, shutdown {r["shutdown_s"]:.2f} s',
              flush=True)
        runs.append(r)
    ok = [r['rate'] for r in runs if r['lost'] <= 0 and not r['extra']]
    best = max(ok) if ok else None
    first = runs[1]
    front = runs[0]
    thread = runs[-1]
    lat = np.array(first['latency_s'])
    rows = []
    for r in runs:
        la = np.array(r['latency_s'])
        js_sent = r['published'].get(settings.inputs.joint_states_topic, 0)
        img_sent = sum(v for k, v in r['published'].items() if k in settings.inputs.image_topics)
        label = f'{r["rate"]:g}x' + (' (no solves)' if 'min_samples:=100000' in r['extra']
                                     else ' (republish_images)' if 'republish_images:=true'
                                     in r['extra'] else ' (solves in the node)' if r['extra']
                                     else '')
        il = np.array(r['info_latency_s'])
        rows.append([label, f'{r["wall_s"]:.0f}', f'{r["cpu_avg"]:.0f}',
                     f'{r["cpu_peak"]:.0f}', f'{r["solver_cpu_avg"]:.0f}',
                     f'{r["total_cpu_avg"]:.0f}', f'{r["joint_states"]}/{js_sent}',
                     f'{r["frames"]}/{img_sent}', f'{reference - r["lost"]}/{reference}',
                     sum(r['queue_dropped'].values()),
                     f'{np.median(la):.3f}' if len(la) else '-',
                     f'{np.percentile(la, 95):.3f}' if len(la) else '-', r['solves'],
                     f'{r["info_paired"]}/{r["info_images"]}',
                     f'{np.median(il) * 1e3:.1f}' if len(il) else '-',
                     f'{np.percentile(il, 95) * 1e3:.1f}' if len(il) else '-',
                     f'{r["shutdown_s"]:.2f}'])
    text = '\n'.join([
        '## Live node (bench/node.py)',
        '',
        f'The node replaying `{os.path.relpath(args.bag, ROOT)}` with '
        f'`{os.path.relpath(args.params, ROOT)}` through `armcal_ros.ros.replay` (reliable '
        f'publishers, real DDS on this machine); CPU from /proc in % of one core: the node '
        f'process (average, and peak over one second) and its solver process '
        f'(`solver_process`, the default: each solve\'s adjustments run there), and both '
        f'together; the last row solves on a thread of the node (`solver_process: false`). '
        f'Dwells: ground-truth dwells with a stored sample in the node / with one offline '
        f'(same front end and store fed in bag order). Latency: last image of a dwell '
        f'published -> its sample received on `~/samples`, seconds. Machine: '
        f'{machine()}; this machine\'s speed varied up to 2 x between runs of one day, so compare '
        f'rows of one run, and runs of two versions only side by side. '
        f'Images with their CameraInfo: images the replay published after the camera\'s first '
        f'calibration / those for which a CameraInfo with the image\'s stamp arrived (the node '
        f'publishes one per image it receives); its latency: image published -> CameraInfo '
        f'received here.',
        '',
        table(['rate', 'wall s', 'node CPU avg %', 'node CPU peak %', 'solver process CPU avg %',
               'total CPU avg %', 'joint states recv/sent',
               'images recv/sent', 'dwells', 'queue drops', 'latency median s',
               'latency p95 s', 'solves', 'images with their CameraInfo',
               'CameraInfo latency median ms', 'p95 ms', 'SIGINT -> exit s'], rows),
        '',
        f'At {first["rate"]:g}x: the node\'s average CPU {first["cpu_avg"]:.0f} % of one core '
        f'(target under 50 %), peak {first["cpu_peak"]:.0f} %; its solver process '
        f'{first["solver_cpu_avg"]:.0f} %, {first["total_cpu_avg"]:.0f} % together; with the '
        f'solves on a thread of the node {thread["cpu_avg"]:.0f} % and '
        f'{sum(thread["queue_dropped"].values())} inputs dropped (against '
        f'{sum(first["queue_dropped"].values())}); without solves (front end and ROS I/O only) '
        f'{front["cpu_avg"]:.0f} %; latency median '
        f'{np.median(lat) if len(lat) else float("nan"):.3f} s. Highest rate with no dwell '
        f'lost: ' + (f'{best:g}x.' if best is not None else 'none of the rates tried.'),
    ])
    print(text)
    if not args.no_write:
        write_section('node', text)
        for r in runs:      # 17 000 latencies per run: their summary is enough in the file
            il = np.array(r.pop('info_latency_s'))
            r['info_latency_ms'] = dict(
                median=float(np.median(il) * 1e3) if len(il) else None,
                p95=float(np.percentile(il, 95) * 1e3) if len(il) else None)
        write_json('node', dict(reference_dwells=reference, runs=runs, best_rate=best,
                                machine=machine()))


if __name__ == '__main__':
    main()
