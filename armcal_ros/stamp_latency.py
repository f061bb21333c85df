"""
Each camera's stamp latency from the frames in motion and a calibration (core/latency.py).

The calibration is made from frames at rest; the frames in motion, which the front end skips,
time the cameras.  :class:`LatencyTimer` is fed the joint states and images as they come (the
node's stream, or a second pass over a recording: :func:`measure_latencies`).  Per camera it
keeps up to about ``2 MAX_FRAMES`` frames spread over the stream in which the marker moves,
detected with an intensity-centroid or tag detector (a motion-blurred ball is not the
shaded-ball model; the blur's centroid is the position at mid-exposure), and the joint states
around each; :meth:`LatencyTimer.estimate` keeps those in which the calibrated camera sees the
marker move fast enough to time it (``MIN_IMAGE_SPEED``) and fits each camera's delay.  Point
markers only (a sphere or a tag's centre); boards are left out.
"""

from collections import deque
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
#: The pass keeps about one frame per this many seconds at first (every n-th frame, n from
#: the camera's frame rate), halving the rate each time a camera has 2 MAX_FRAMES of them
#: (which are then thinned to every other one).
MIN_SPACING_S = 0.05
#: Frames of a camera whose stamps give its frame interval (their median) before any is kept.
RATE_FRAMES = 6


class LatencyTimer:
    """
    The frames in motion and the joint states around them, kept as they come (module doc).

    ``detectors`` {camera: Detector} of the marker's point, ``chain`` the robot's
    KinematicChain, ``marker_offset`` (3,) the marker's place on its link; ``bounds`` (s) the
    latencies searched.  A frame is kept when the marker moves: its image speed is at least
    :data:`MIN_IMAGE_SPEED` where a calibration of its camera is known (:meth:`set_cameras`),
    otherwise its speed in space at least ``min_marker_speed`` (m/s; the front end's stillness
    bound); :meth:`estimate` applies the image-speed rule with the calibration it is given.
    Every n-th frame of a camera is a candidate, counted in the order the frames come: n
    starts at ``min_spacing_s`` over the camera's frame interval (the median of its first
    :data:`RATE_FRAMES` stamps' intervals) and doubles each time the camera has 2
    ``max_frames`` frames kept (they are then thinned to every other one), so they stay spread
    over the whole stream in bounded memory.  The choice never looks at a frame's stamp: a
    rule such as "at least s after the last frame kept" picks, where s is a whole number of
    frame intervals, the frames whose stamps jitter late, and the estimate is late by a good
    part of the jitter (measured: by 0.2 of the jitter's standard deviation on average, once
    the rate had halved).  Joint states are kept only around kept frames (the whole range of
    ``bounds``).  A joint state more than :data:`JUMP_S` older than the last resets
    everything (a time jump: a bag looped, a simulation restarted).  Not thread-safe: one
    thread feeds and estimates.
    """

    #: Joint states further apart than this (s) bracket no prediction (a gap in the record).
    MAX_GAP_S = 0.1
    #: A joint state older than the last by more than this (s) is a time jump (the front
    #: end's pairing rule); a little older, it is out of order and skipped.
    JUMP_S = 0.5

    def __init__(self, detectors, chain, marker_offset, bounds=(-0.1, 0.25),
                 max_frames=MAX_FRAMES, min_spacing_s=MIN_SPACING_S, min_marker_speed=0.0375):
        lo, hi = (float(b) for b in bounds)
        if not lo < hi:
            raise ValueError(f'bounds must be (low, high) with low < high, got {bounds}')
        if not (max_frames >= 10 and min_spacing_s > 0 and min_marker_speed >= 0):
            raise ValueError(f'max_frames must be >= 10, min_spacing_s > 0 and '
                             f'min_marker_speed >= 0, got {max_frames}, {min_spacing_s}, '
                             f'{min_marker_speed}')
        self.detectors = dict(detectors)
        self.chain = chain
        self.names = list(chain.joint_names)
        self.offset = np.asarray(marker_offset, float).reshape(3)
        self.bounds = (lo, hi)
        self.max_frames = int(max_frames)
        self.min_spacing_s = float(min_spacing_s)
        self.min_marker_speed = float(min_marker_speed)
        self.cameras = {}
        self.reset()

    def reset(self):
        """Forget every frame and joint state."""
        self._recent = deque()
        self._kept_t, self._kept_q = [], []
        self._keep_until = -np.inf
        self._frames = {c: [] for c in self.detectors}
        self._seen = {c: 0 for c in self.detectors}           # frames come, by camera
        self._first_stamps = {c: [] for c in self.detectors}  # the first RATE_FRAMES
        self._stride0 = {}                                   # the first n, by camera
        self._stride = {}

    def set_cameras(self, cameras):
        """Use {camera: Camera} (a calibration's) to choose the frames from now on."""
        self.cameras = {n: c for n, c in dict(cameras).items() if n in self.detectors}

    def forget(self, camera):
        """Drop one camera's frames (it moved: they time a camera that is no longer there)."""
        if camera in self._frames:
            self._frames[camera] = []
            if camera in self._stride0:
                self._stride[camera] = self._stride0[camera]

    def frames(self, camera) -> int:
        """Return how many frames of ``camera`` are kept."""
        return len(self._frames.get(camera, ()))

    def add_joint_state(self, stamp_ns, names, positions):
        """Feed one joint state (names in any order; one lacking a joint or a number: skipped)."""
        index = {n: i for i, n in enumerate(names)}
        if any(n not in index for n in self.names):
            return
        q = np.array([positions[index[n]] for n in self.names], float)
        t = stamp_ns * 1e-9
        if not np.all(np.isfinite(q)):
            return
        if self._recent and t <= self._recent[-1][0]:
            if t >= self._recent[-1][0] - self.JUMP_S:
                return                          # out of order or repeated: skipped
            self.reset()
        self._recent.append((t, q))
        lo, hi = self.bounds
        while self._recent and self._recent[0][0] < t - hi - 0.05:
            self._recent.popleft()
        if t <= self._keep_until:
            self._keep(t, q)

    def _keep(self, t, q):
        if not self._kept_t or t > self._kept_t[-1]:
            self._kept_t.append(t)
            self._kept_q.append(q)

    def add_image(self, camera, stamp_ns, msg):
        """Feed one image message (undecoded) of ``camera`` at its stamp as the driver gave it."""
        if camera not in self.detectors:
            return
        t = stamp_ns * 1e-9
        if not self._candidate(camera, t) or len(self._recent) < 2:
            return
        (t0, q0), (t1, q1) = self._recent[-2], self._recent[-1]
        dq = (q1 - q0) / (t1 - t0)
        h = 0.01
        X = self.chain.fk(np.stack([q1, q1 + h * dq]), self.offset)
        cam = self.cameras.get(camera)
        if cam is not None:
            uv = cam.project(X)
            speed = np.hypot(*(uv[1] - uv[0])) / h
            if not (speed >= MIN_IMAGE_SPEED and 0 <= uv[0, 0] < cam.width and
                    0 <= uv[0, 1] < cam.height):
                return
        elif not np.linalg.norm(X[1] - X[0]) / h >= self.min_marker_speed:
            return
        try:
            image = decode_image_msg(msg)
        except Exception:  # a frame that does not decode is not timed; the front end says so
            return
        dets = self.detectors[camera].detect(image)
        if not dets:
            return
        # The joint states over the whole range of bounds, with a margin for the velocity's
        # finite difference: those before the frame now, those after it as they come.
        lo, hi = self.bounds
        for tj, qj in self._recent:
            if tj >= t - hi - 0.03:
                self._keep(tj, qj)
        self._keep_until = max(self._keep_until, t - lo + 0.03)
        frames = self._frames[camera]
        frames.append((t, np.asarray(dets[0].uv, float).reshape(2)))
        if len(frames) >= 2 * self.max_frames:
            # Thin to every other frame and halve the rate: the frames stay spread over the
            # whole stream, and at most ~2 max_frames are decoded per doubling of its length.
            self._frames[camera] = frames[::2]
            self._stride[camera] *= 2
            self._prune()

    def _candidate(self, camera, t):
        """Count a frame of ``camera`` stamped ``t``; return True if it is one to time."""
        k = self._seen[camera]
        self._seen[camera] = k + 1
        stride = self._stride.get(camera)
        if stride is None:
            first = self._first_stamps[camera]
            first.append(t)
            if len(first) < RATE_FRAMES:
                return False
            interval = float(np.median(np.diff(np.sort(first))))
            stride = max(1, int(round(self.min_spacing_s / interval))) if interval > 0 else 1
            self._stride0[camera] = self._stride[camera] = stride
            self._seen[camera] = 0
            return False
        return k % stride == 0

    def _prune(self):
        """Keep only the joint states around some camera's kept frames."""
        if not self._kept_t:
            return
        kt = np.asarray(self._kept_t)
        lo, hi = self.bounds
        keep = np.zeros(kt.size, bool)
        for frames in self._frames.values():
            for t, _ in frames:
                a, b = np.searchsorted(kt, [t - hi - 0.03, t - lo + 0.03])
                keep[a:b] = True
        keep[kt >= self._keep_until - (hi - lo) - 0.06] = True       # the frames to come
        self._kept_t = list(kt[keep])
        self._kept_q = [q for q, k in zip(self._kept_q, keep) if k]

    def estimate(self, calibration, marker_offset=None) -> Dict[str, LatencyEstimate]:
        """
        Return {camera: LatencyEstimate} of the frames kept, with ``calibration`` (core).

        ``marker_offset`` (3,) replaces the one given at construction (the calibration's
        estimate where it made one).  Only the cameras of the calibration with a detector.
        """
        offset = self.offset if marker_offset is None else \
            np.asarray(marker_offset, float).reshape(3)
        cameras = {n: c.camera for n, c in calibration.cameras.items() if n in self.detectors}
        if len(self._kept_t) < 2 or not cameras:
            return {}
        kt = np.asarray(self._kept_t)
        # The marker at each joint state, once: a prediction interpolates it in time.  The
        # search evaluates a few hundred delays per camera, and forward kinematics at each was
        # most of the node's CPU with a calibration (measured: a quarter of its samples on the
        # demo bag).  Between joint states 5-10 ms apart, the marker's straight chord and the
        # arc of the interpolated joint angles differ by micrometres.
        kx = self.chain.fk(np.asarray(self._kept_q), offset)
        out = {}
        for cam, camera in cameras.items():
            def predict(tq, camera=camera):
                tq = np.asarray(tq, float)
                # A prediction needs joint states on both sides within MAX_GAP_S.
                k = np.clip(np.searchsorted(kt, tq), 1, kt.size - 1)
                inside = (tq >= kt[0]) & (tq <= kt[-1]) & (kt[k] - kt[k - 1] <= self.MAX_GAP_S)
                X = np.column_stack([np.interp(tq, kt, kx[:, j]) for j in range(3)])
                p = camera.project(X)
                p[~inside] = np.nan
                return p

            frames = self._frames[cam]
            if not frames:
                out[cam] = estimate_latency(np.zeros(0), np.zeros((0, 2)), predict,
                                            bounds=self.bounds)
                continue
            t = np.array([f[0] for f in frames])
            uv = np.array([f[1] for f in frames]).reshape(-1, 2)
            # The image-speed rule with this calibration (frames kept before one was known).
            h = 0.01
            p0, p1 = predict(t), predict(t + h)
            speed = np.hypot(*(p1 - p0).T) / h
            moving = (speed >= MIN_IMAGE_SPEED) & (p0[:, 0] >= 0) & (p0[:, 0] < camera.width) \
                & (p0[:, 1] >= 0) & (p0[:, 1] < camera.height)
            t, uv = t[moving], uv[moving]
            if len(t) > self.max_frames:
                pick = np.linspace(0, len(t) - 1, self.max_frames).astype(int)
                t, uv = t[pick], uv[pick]
            out[cam] = estimate_latency(t, uv, predict, bounds=self.bounds)
        return out


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
    detectors = {n: d for n, d in (detectors or {}).items() if n in calibration.cameras}
    if not detectors or chain is None:
        return {}
    timer = LatencyTimer(detectors, chain, marker_offset, bounds)
    timer.set_cameras({n: c.camera for n, c in calibration.cameras.items()})
    for event in recording.events():
        if event[0] == 'joints':
            timer.add_joint_state(*event[1:])
        elif event[0] == 'image':
            timer.add_image(*event[1:])
    return timer.estimate(calibration)


#: A measured stamp latency is worth pairing with when it differs from the one given
#: (image_stamp_latency) by more than this (s) and three of its standard deviations: at the
#: front end's speed bound (0.0375 m/s) 2 ms is 0.05 px at f = 800 px and 1.5 m.
LATENCY_APPLY_S = 0.002


def latency_differs(estimate: LatencyEstimate, given_s: float) -> bool:
    """Return True when ``estimate`` is sure and off ``given_s`` (:data:`LATENCY_APPLY_S`)."""
    return bool(estimate.ok and abs(estimate.latency_s - given_s) >
                max(LATENCY_APPLY_S, 3 * estimate.std_s))


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
