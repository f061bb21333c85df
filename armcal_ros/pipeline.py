"""
From joint states and images to samples: the front end the node and the offline CLI share.

:class:`SampleCollector` takes plain inputs - a joint state as (stamp, names, positions) and an
image as (camera, stamp, message-like object) - and returns samples ready for the engine.  Images
are held undecoded until their pairing is known, so only frames taken while the arm was still are
decoded and searched for the marker.  Every rejected input is counted by reason (diagnostics) and
reported once through an optional ``log`` callback, never raised: a malformed message, an
unknown joint, a NaN, a time jump or a missing camera costs that input, not the session.
"""

import collections
import time
from typing import Callable, Dict, List, Optional

import numpy as np

from armcal_ros.frontend.detectors import make_detector
from armcal_ros.frontend.image_decode import decode_image_msg, ImageDecodeError
from armcal_ros.frontend.pairing import DwellPooler, FramePairer, JointStatus, PairStatus
from armcal_ros.robot.kinematics import KinematicChain


def make_detectors(values, camera_names):
    """One detector per camera (each tracks its own marker position) from parameter values."""
    if values['marker_type'] == 'charuco':
        # The joint-state front end pools one point per target id at the FK marker position;
        # a board's corners need the board path (pose input or a robot_cal_tools folder).
        raise ValueError('parameter marker_type: charuco works with pose input (pose_topic) '
                         'or a robot_cal_tools folder; with joint states use sphere or aruco')
    out = {}
    for name in camera_names:
        if values['marker_type'] == 'sphere':
            out[name] = make_detector('sphere', min_radius_px=values['sphere_min_radius_px'],
                                      max_radius_px=values['sphere_max_radius_px'])
        else:
            mid = values['aruco_id']
            out[name] = make_detector('aruco', dictionary=values['aruco_dictionary'],
                                      marker_id=None if mid < 0 else mid)
    return out


class RateLimitedLog:
    """Call ``log(message)`` at most once per ``period_s`` for each key (first time at once)."""

    def __init__(self, log: Optional[Callable[[str], None]], period_s=10.0,
                 clock=time.monotonic):
        self.log = log
        self.period_s = period_s
        self.clock = clock
        self._last: Dict[str, float] = {}

    def __call__(self, key, message):
        """Log ``message`` unless ``key`` was logged less than ``period_s`` ago."""
        if self.log is None:
            return
        now = self.clock()
        last = self._last.get(key)
        if last is None or now - last >= self.period_s:
            self._last[key] = now
            self.log(message)


class SampleCollector:
    """
    Pair, filter, detect and pool: inputs in, :class:`~armcal_ros.frontend.samples.Sample` out.

    ``counts`` holds how many inputs ended where (``joint_states``, ``frames``,
    ``frames_still``, ``detections``, and every rejection reason), for diagnostics.
    ``image_sizes`` records each camera's (width, height) from its decoded images.
    """

    def __init__(self, chain: KinematicChain, marker_offset, camera_names, detectors,
                 max_marker_speed=0.0375, dwell_radius=0.001, log=None):
        self.chain = chain
        self.marker_offset = np.asarray(marker_offset, float).reshape(3)
        self.camera_names = list(camera_names)
        self.detectors = detectors
        missing = [c for c in self.camera_names if c not in detectors]
        if missing:
            raise ValueError(f'detectors: no detector for cameras {missing}')

        def fk(Q):
            return chain.fk(Q, self.marker_offset)
        self.pairer = FramePairer(chain.joint_names, fk, max_marker_speed=max_marker_speed)
        self.pooler = DwellPooler(fk, dwell_radius=dwell_radius)
        self.counts = collections.Counter()
        self.image_sizes: Dict[str, tuple] = {}
        self.log = RateLimitedLog(log)

    def _count(self, key, message=None):
        self.counts[key] += 1
        if message:
            self.log(key, f'{message} (seen {self.counts[key]} times; skipped)')

    def add_joint_state(self, stamp_ns, names, positions) -> List:
        """Feed one JointState; return the samples completed (usually none)."""
        self.counts['joint_states'] += 1
        try:
            status, ready = self.pairer.add_joint_state(stamp_ns, list(names),
                                                        np.asarray(positions, float))
        except ValueError as exc:
            self._count('joint_state_invalid', f'joint state rejected: {exc}')
            return []
        if status is JointStatus.TIME_JUMP:
            self._count('time_jump', 'joint state time jumped backwards: joint history reset')
        elif status is not JointStatus.OK:
            self._count(f'joint_state_{status.value}',
                        f'joint state rejected: {status.value}')
        return self._process(ready)

    def add_image(self, camera, stamp_ns, msg) -> List:
        """Feed one image message (Image or CompressedImage, undecoded); return samples."""
        if camera not in self.detectors:
            self._count('unknown_camera', f'image from unknown camera {camera!r}')
            return []
        self.counts['frames'] += 1
        return self._process(self.pairer.add_frame(camera, stamp_ns, msg))

    def flush(self) -> List:
        """Decide every waiting frame and close the open dwell (end of a bag)."""
        return self._process(self.pairer.flush()) + self.pooler.flush()

    def reset(self):
        """Drop pending frames, the joint history and the open dwell."""
        self.pairer.reset()
        self.pooler.flush()

    def _process(self, frames) -> List:
        samples = []
        for frame in frames:
            dets = ()
            if frame.status is PairStatus.STILL:
                self.counts['frames_still'] += 1
                dets = self._detect(frame.camera, frame.payload)
            else:
                self.counts[f'frames_{frame.status.value}'] += 1
            samples.extend(self.pooler.add(frame, dets))
        return samples

    def _detect(self, camera, msg):
        try:
            image = decode_image_msg(msg)
        except ImageDecodeError as exc:
            self._count('image_decode_error', f'{camera}: image cannot be decoded: {exc}')
            return ()
        except Exception as exc:  # a malformed message must not stop the stream
            self._count('image_malformed', f'{camera}: malformed image message: {exc}')
            return ()
        h, w = image.shape[:2]
        self.image_sizes[camera] = (w, h)
        dets = self.detectors[camera].detect(image)
        if dets:
            self.counts['detections'] += 1
        else:
            self.counts['frames_no_marker'] += 1
        return dets
