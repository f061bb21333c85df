"""
Each camera's stamp latency, measured on a recording with its calibration (core/latency.py).

The calibration is made from frames at rest; the frames in motion, which the front end skips,
time the cameras.  A second pass over the recording keeps every joint state and, per camera,
up to ``MAX_FRAMES`` frames in which the calibrated camera sees the marker move fast enough to
time it (``MIN_IMAGE_SPEED``), detects the marker in them with an intensity-centroid or tag
detector (a motion-blurred ball is not the shaded-ball model; the blur's centroid is the
position at mid-exposure), and fits each camera's delay.  Point markers only (a sphere or a
tag's centre); boards are left out.
"""

from typing import Dict

import numpy as np

from armcal_ros.core.latency import estimate_latency, LatencyEstimate
from armcal_ros.frontend.image_decode import decode_image_msg

#: Frames per camera timed at most (spread over the recording): with image speeds of ~100
#: px/s and ~0.3 px of detection noise in motion, 200 frames give ~0.1 ms.
MAX_FRAMES = 200
#: The marker must move at least this fast in the image (px/s) for a frame to be timed: at
#: 50 px/s a millisecond is 0.05 px, about the detector's noise.
MIN_IMAGE_SPEED = 50.0
#: The pass spaces the frames it keeps by at least this (s), doubled each time a camera has
#: 2 MAX_FRAMES of them (which are then thinned to every other one).
MIN_SPACING_S = 0.05


def measure_latencies(recording, detectors, chain, marker_offset, calibration,
                      bounds=(-0.1, 0.25)) -> Dict[str, LatencyEstimate]:
    """
    Return {camera: LatencyEstimate} for a recording (offline.Recording) and its calibration.

    ``detectors`` {camera: Detector} of the marker's point (an intensity centroid for a
    sphere, a tag's centre: module doc), ``chain`` the robot's KinematicChain,
    ``marker_offset`` (3,) the marker's place on its link (the calibration's estimate where it
    made one), ``calibration`` a core Calibration.  Cameras without enough motion in view get
    a status saying so; {} without detectors or a chain.
    """
    cameras = {n: c.camera for n, c in calibration.cameras.items() if n in (detectors or {})}
    if not detectors or chain is None or not cameras:
        return {}
    names = list(chain.joint_names)
    offset = np.asarray(marker_offset, float).reshape(3)
    js_t, js_q = [], []
    last = {}
    pending = {c: [] for c in cameras}
    spacing = {c: MIN_SPACING_S for c in cameras}

    def q_now():
        """Return (q, dq/dt) from the latest two joint states (stamps increase), or None."""
        if len(js_t) < 2:
            return None
        return js_q[-1], (js_q[-1] - js_q[-2]) / (js_t[-1] - js_t[-2])

    for event in recording.events():
        kind = event[0]
        if kind == 'joints':
            _, stamp_ns, jn, pos = event
            index = {n: i for i, n in enumerate(jn)}
            if any(n not in index for n in names):
                continue
            q = np.array([pos[index[n]] for n in names], float)
            t = stamp_ns * 1e-9
            if not np.all(np.isfinite(q)) or (js_t and t <= js_t[-1]):
                continue
            js_t.append(t)
            js_q.append(q)
        elif kind == 'image' and event[1] in cameras:
            _, cam, stamp_ns, msg = event
            t = stamp_ns * 1e-9
            if t - last.get(cam, -np.inf) < spacing[cam]:
                continue
            state = q_now()
            if state is None:
                continue
            q, dq = state
            h = 0.01
            X = chain.fk(np.stack([q, q + h * dq]), offset)
            uv = cameras[cam].project(X)
            speed = np.hypot(*(uv[1] - uv[0])) / h
            w, hgt = cameras[cam].width, cameras[cam].height
            if not (speed >= MIN_IMAGE_SPEED and 0 <= uv[0, 0] < w and 0 <= uv[0, 1] < hgt):
                continue
            try:
                image = decode_image_msg(msg)
            except Exception:  # a frame that does not decode is not timed; the solve said so
                continue
            dets = detectors[cam].detect(image)
            if dets:
                pending[cam].append((t, dets[0].uv))
                last[cam] = t
                if len(pending[cam]) >= 2 * MAX_FRAMES:
                    # Thin to every other frame and halve the rate: the frames stay spread
                    # over the whole recording, and at most ~2 MAX_FRAMES are decoded per
                    # doubling of its length.
                    pending[cam] = pending[cam][::2]
                    spacing[cam] *= 2.0
    if len(js_t) < 2:
        return {}
    js_t, js_q = np.asarray(js_t), np.asarray(js_q)
    out = {}
    for cam, frames in pending.items():
        if len(frames) > MAX_FRAMES:
            frames = [frames[i] for i in np.linspace(0, len(frames) - 1, MAX_FRAMES).astype(int)]
        t = np.array([f[0] for f in frames])
        uv = np.array([f[1] for f in frames]).reshape(-1, 2)

        def predict(tq, cam=cam):
            inside = (tq >= js_t[0]) & (tq <= js_t[-1])
            Q = np.column_stack([np.interp(tq, js_t, js_q[:, j]) for j in range(len(names))])
            p = cameras[cam].project(chain.fk(Q, offset))
            p[~inside] = np.nan
            return p

        out[cam] = estimate_latency(t, uv, predict, bounds=bounds)
    return out


def latency_report(estimates: Dict[str, LatencyEstimate], applied=None):
    """
    Return the report.json form: {camera: {latency_ms, std_ms, frames, rms_px, status, ...}}.

    ``applied`` {camera: s}: the latencies the final samples were paired with (None: the
    frames were paired as given); each camera then has ``applied_ms``.
    """
    def ms(v):
        return None if v is None or not np.isfinite(v) else round(1e3 * float(v), 3)
    out = {}
    for cam, e in estimates.items():
        out[cam] = dict(latency_ms=ms(e.latency_s), std_ms=ms(e.std_s), frames=e.frames,
                        rms_px=None if not np.isfinite(e.rms_px) else round(e.rms_px, 4),
                        status=e.status, message=e.message)
        if applied is not None:
            out[cam]['applied_ms'] = ms(applied.get(cam, 0.0))
    return out
