"""
Offline pipeline benchmark on the demo bag: speed, detection recall and false detections.

1. The whole offline pipeline (`collect_samples` + solve, as `armcal calibrate` runs it): wall
   time and CPU time, frames per second, and the ratio of the bag's duration to the time taken.
2. Detection alone on every frame of the bag (not only the still ones the pipeline decodes):
   time per frame, recall on frames where the marker is visible and unoccluded (a detection
   within 1 px of the true projection), and false detections (a detection further than 2 px from
   the truth, or any detection on a frame where the marker is hidden or outside the image).
3. What survives: pooled observations in the samples whose position is more than 1 px from the
   true projection (false detections kept), and how many of those the adjustment gated.

Usage: python bench/pipeline.py [--bag bags/demo] [--params config/demo.yaml]
"""

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _report import machine, table, write_json, write_section  # noqa: E402

from armcal_ros.frontend.image_decode import decode_image_msg  # noqa: E402
from armcal_ros.io.bag import bag_topics, iter_raw  # noqa: E402
from armcal_ros.compose import build_detectors  # noqa: E402
from armcal_ros.io.message_fields import stamp_ns  # noqa: E402
from armcal_ros.offline import collect_samples, solve_and_write  # noqa: E402
from armcal_ros.settings import load_settings  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def detection_pass(bag, settings, truth_frames):
    """Detect on every frame; return timing and recall/false-detection counts."""
    names = list(settings.inputs.camera_names)
    topic_cam = dict(zip(settings.inputs.image_topics, names))
    detectors = build_detectors(settings, names)
    index = {(int(c), int(s)): k for k, (c, s) in
             enumerate(zip(truth_frames['frame_camera'], truth_frames['frame_stamp_ns']))}
    visible = hits = false = frames = 0
    err = []
    t_det = 0.0
    for raw in iter_raw(bag, list(topic_cam)):
        msg = raw.deserialize()
        cam = topic_cam[raw.topic]
        img = decode_image_msg(msg)
        t0 = time.perf_counter()
        dets = detectors[cam].detect(img)
        t_det += time.perf_counter() - t0
        frames += 1
        k = index.get((names.index(cam), stamp_ns(msg.header.stamp)))
        if k is None:
            continue
        occl = int(truth_frames['frame_occlusion'][k])
        uv = truth_frames['frame_uv'][k]
        if occl == 0:
            visible += 1
        for d in dets:
            e = float(np.linalg.norm(d.uv - uv)) if occl == 0 else np.inf
            if e <= 1.0:
                hits += 1
                err.append(e)
            elif e > 2.0:
                false += 1
    return dict(frames=frames, detect_ms=1000 * t_det / max(frames, 1), visible=visible,
                recall=hits / max(visible, 1), false_detections=false,
                median_error_px=float(np.median(err)) if err else float('nan'))


def kept_false(front, gt_dir, result):
    """
    Pooled observations more than 1 px from the truth, and how many the adjustment gated.

    The truth of an observation is the true projection in the frame of that camera nearest to
    the observation's (median) stamp.
    """
    m = np.load(os.path.join(gt_dir, 'markers.npz'))
    names = [str(n) for n in m['camera_names']]
    by_cam = {}
    for k, name in enumerate(names):
        sel = m['frame_camera'] == k
        by_cam[name] = (m['frame_stamp_ns'][sel], m['frame_uv'][sel])
    bad, total, errors = [], 0, []
    for s in front.store.samples:
        for cam, o in s.observations.items():
            total += 1
            stamps, uvs = by_cam[cam]
            k = int(np.argmin(np.abs(stamps - o.stamp_ns)))
            e = float(np.linalg.norm(o.uv[0] - uvs[k]))
            errors.append(e)
            if e > 1.0:
                bad.append((s.id, cam, e))
    adj = result.outcome.result.adjustment
    return dict(observations=total, false_kept_before_gating=len(bad),
                gated_by_adjustment=int((~adj.inliers).sum()), bad=bad,
                median_observation_error_px=float(np.median(errors)),
                p99_observation_error_px=float(np.percentile(errors, 99)))


def main(argv=None):
    """Run the benchmark, print the table and write it to docs/."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    ap.add_argument('--bag', default=os.path.join(ROOT, 'bags', 'demo'))
    ap.add_argument('--params', default=os.path.join(ROOT, 'config', 'demo.yaml'))
    args = ap.parse_args(argv)
    settings = load_settings(args.params)
    topics = bag_topics(args.bag)
    gt = os.path.join(args.bag, 'ground_truth')
    truth_frames = np.load(os.path.join(gt, 'markers.npz'))
    duration = (truth_frames['frame_stamp_ns'].max() - truth_frames['frame_stamp_ns'].min()) / 1e9
    n_frames = sum(topics[t][1] for t in settings.inputs.image_topics if t in topics)

    c0, t0 = time.process_time(), time.perf_counter()
    front = collect_samples(args.bag, settings)
    t_front, c_front = time.perf_counter() - t0, time.process_time() - c0
    c1, t1 = time.process_time(), time.perf_counter()
    res = solve_and_write(front, settings, os.path.join(ROOT, 'out', 'bench_pipeline'))
    t_solve, c_solve = time.perf_counter() - t1, time.process_time() - c1
    det = detection_pass(args.bag, settings, truth_frames)
    kept = kept_false(front, gt, res)

    speed = dict(duration_s=duration, frames=n_frames, front_end_s=t_front,
                 front_end_cpu_s=c_front, solve_s=t_solve, solve_cpu_s=c_solve,
                 fps=n_frames / t_front, realtime_ratio=duration / (t_front + t_solve),
                 realtime_ratio_cpu=duration / (c_front + c_solve), samples=len(front.store))
    rows = [['bag', f'{duration:.0f} s, {n_frames} frames (3 cameras), '
                    f'{topics[settings.inputs.joint_states_topic][1]} joint states'],
            ['front end (read, pair, detect still frames, pool; test each sample for a change, '
             'solving as the samples double)',
             f'{t_front:.1f} s wall, {c_front:.1f} s CPU -> {len(front.store)} samples'],
            [f'solve ({settings.prior.model})', f'{t_solve:.2f} s wall'],
            ['frames per second (whole pipeline)', f'{n_frames / (t_front + t_solve):.0f}'],
            ['x real time (wall / CPU)',
             f'{speed["realtime_ratio"]:.1f} / {speed["realtime_ratio_cpu"]:.1f} '
             f'(target >= 10)'],
            ['sphere detection per frame (every frame)', f'{det["detect_ms"]:.2f} ms'],
            ['recall, visible and unoccluded frames',
             f'{100 * det["recall"]:.2f} % of {det["visible"]} (target >= 95 %)'],
            ['median detection error', f'{det["median_error_px"]:.3f} px'],
            ['false detections, every frame', f'{det["false_detections"]}'],
            ['false observations kept in samples (> 1 px from truth)',
             f'{kept["false_kept_before_gating"]} of {kept["observations"]} (target 0)'],
            ['pooled observation error vs truth, median / 99th percentile',
             f'{kept["median_observation_error_px"]:.3f} / '
             f'{kept["p99_observation_error_px"]:.3f} px'],
            ['observations gated by the adjustment', f'{kept["gated_by_adjustment"]}']]
    md = ['## Offline pipeline (bench/pipeline.py)', '',
          f'The demo bag through `collect_samples` + `solve_and_write` (what `armcal calibrate` '
          f'runs), then the sphere detector on every frame against the simulator\'s truth. '
          f'Measured on {machine()}; wall times are with the other core busy when noted in the '
          f'issue.', '', table(['measure', 'value'], rows)]
    text = '\n'.join(md)
    print(text)
    write_section('pipeline', text)
    write_json('pipeline', dict(speed=speed, detection=det, kept=kept, machine=machine()))
    return 0


if __name__ == '__main__':
    sys.exit(main())
