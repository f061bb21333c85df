"""
From joint states or link poses, and images, to samples: the front end every caller shares.

:class:`SampleCollector` takes plain inputs - a joint state as (stamp, names, positions), or with
pose input a measured link pose as (stamp, translation, quaternion), and an image as (camera,
stamp, message-like object) - and returns samples ready for the engine.  Images are held
undecoded until their pairing is known, so only frames taken while the target was still are
decoded and searched for it (for a board, only until a dwell has ``max_views_per_dwell`` views
of it per camera).  Every rejected input is counted by reason (diagnostics) and
reported once through an optional ``log`` callback, never raised: a malformed message, an
unknown joint, a NaN, a time jump or a missing camera costs that input, not the session.

Targets: a sphere or an ArUco tag is one point at ``marker_offset`` on the marker link (a
sample is one 3-D point); a ChArUco board (:class:`~armcal_ros.frontend.samples.BoardTarget`)
gives many corners per sample, with the link pose (measured, or from forward kinematics) that
places them.  Stillness and the dwell radius then apply to the fastest / farthest of the
board's outer corners, so a turn of the board about its centre is not taken for stillness.
"""

import collections
import time
from dataclasses import replace
from typing import Callable, Dict, List, Optional

import numpy as np

from armcal_ros.frontend.image_decode import decode_image_msg, ImageDecodeError
from armcal_ros.frontend.pairing import (DwellPooler, FramePairer, JointStatus, PairStatus)
from armcal_ros.frontend.pose_input import (mean_pose_vector, pose_points, pose_vector_matrix,
                                            PoseHistory)
from armcal_ros.frontend.samples import BoardTarget
from armcal_ros.frontend.static_spots import STATIC_PX, StaticSpotFilter
from armcal_ros.robot.kinematics import KinematicChain


#: Distance (m) of the points whose motion stands for the scene's in a camera riding on the arm.
CAMERA_ON_LINK_REFERENCE_M = 1.0

#: An image this many times larger than the camera's first (and over OVERSIZE_BYTES) is not
#: one of its frames: skipped undecoded and counted (a 50 MB message on a VGA camera's topic
#: would otherwise be decoded and searched for seconds).  Compressed frames vary by a factor of
#: two or three with the scene; a factor of 8 leaves them alone.
OVERSIZE_FACTOR = 8
OVERSIZE_BYTES = 4_000_000


def is_oversize(nbytes, typical) -> bool:
    """Whether ``nbytes`` cannot be a frame of a camera whose frames are ``typical`` bytes."""
    return typical is not None and nbytes > OVERSIZE_FACTOR * typical and nbytes > OVERSIZE_BYTES


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

    ``chain`` is the robot model for joint input (:meth:`add_joint_state`); None selects pose
    input (:meth:`add_pose`, the measured pose of the marker link in the base frame, whose
    history bridges gaps of at most ``max_pose_gap_s``).  ``board`` makes the target a board
    (samples carry the link pose and the corners); otherwise it is one point at
    ``marker_offset`` in the marker link.

    ``max_views_per_dwell`` (boards only; 0: no cap) is how many views of the board per camera
    a dwell detects: a board's corners need one view (``min_frames`` 1), and searching every
    still frame for it (tens of ms each) would fall behind three live cameras.  Later still
    frames of that camera in the same dwell are counted in ``frames_skipped_dwell_full`` and
    not decoded.  A sphere or a tag is not capped: detecting one costs about a millisecond,
    and its pooling wants several frames.  ``max_fits_per_view`` (0: no cap) caps only a
    costly centre fit (a shaded ball, one to two milliseconds more): a camera's further still
    frames in the dwell are detected without it (their centroids pooled, the fitted frames'
    light shift added; :class:`~armcal_ros.frontend.pairing.DwellPooler` ``max_fits``) and
    counted in ``frames_fit_skipped``.

    ``cameras_on_link`` (eye-in-hand): the cameras move with the link and the target stands
    still; stillness and "the same place" then follow the link's pose as seen from about a
    metre (:data:`CAMERA_ON_LINK_REFERENCE_M`), since a small turn of the camera moves the whole
    scene in the image.

    ``stamp_latency_s`` {camera: s}: how late a camera's driver stamps its images; its frames
    are paired with the joint angles at stamp - latency (and the samples carry that time).

    ``min_frames`` is how many frames of a camera a dwell needs for an observation (None: 1
    for a board, 2 otherwise).  A board's corners come from its markers' decoded ids and a
    local homography fit, and a tag's from its decoded id: one frame is trustworthy.  A glint
    can pass as a sphere in one frame, so a sphere needs two (the median then rejects it).

    ``counts`` holds how many inputs ended where (``joint_states`` or ``poses``, ``frames``,
    ``frames_still``, ``detections``, ``frames_skipped_dwell_full`` and every rejection
    reason), for diagnostics.  ``image_sizes`` records each camera's (width, height) from its
    decoded images.
    """

    def __init__(self, chain: Optional[KinematicChain], marker_offset, camera_names, detectors,
                 max_marker_speed=0.0375, dwell_radius=0.001, log=None,
                 board: Optional[BoardTarget] = None, max_pose_gap_s=0.1, min_frames=None,
                 cameras_on_link=False,
                 max_views_per_dwell=3, still_guard_s=0.0, stamp_latency_s=None,
                 max_fits_per_view=0):
        self.chain = chain
        self.pose_input = chain is None
        self.board = board
        self.marker_offset = np.asarray(marker_offset, float).reshape(3)
        self.camera_names = list(camera_names)
        # How late each camera's driver stamps (s): its frames are paired at stamp - latency.
        self.stamp_latency_ns = {c: int(round(float(s) * 1e9))
                                 for c, s in (stamp_latency_s or {}).items()}
        unknown = sorted(set(self.stamp_latency_ns) - set(self.camera_names))
        if unknown:
            raise ValueError(f'stamp_latency_s: no camera named {unknown}')
        self.detectors = detectors
        missing = [c for c in self.camera_names if c not in detectors]
        if missing:
            raise ValueError(f'detectors: no detector for cameras {missing}')
        if not max_pose_gap_s > 0:
            raise ValueError(f'max_pose_gap_s must be > 0, got {max_pose_gap_s}')
        # The points whose speed and spread decide stillness and dwells, in the link frame.
        if cameras_on_link:
            # The cameras ride on the link: what must be still is the scene in their images.
            # Points at scene distance around the link stand for it (the target's place in the
            # link frame changes from view to view).
            r = CAMERA_ON_LINK_REFERENCE_M
            ref = np.array([[r, 0.0, 0.0], [0.0, r, 0.0], [0.0, 0.0, r], [-r, -r, -r]])
        else:
            ref = (board.reference_points_in_link() if board is not None
                   else self.marker_offset[None, :])
        if self.pose_input:
            def fk(C):
                return pose_points(C, ref)
            history = PoseHistory(max_gap_ns=int(max_pose_gap_s * 1e9))
            self.pairer = FramePairer((), fk, max_marker_speed=max_marker_speed,
                                      history=history,
                                      still_guard_ns=int(round(still_guard_s * 1e9)))
            mean = mean_pose_vector
        else:
            if board is None:
                def fk(Q):
                    return chain.fk(Q, self.marker_offset)
            else:
                def fk(Q):
                    T = chain.fk_pose(Q)
                    return np.einsum('mij,rj->mri', T[:, :3, :3], ref) + T[:, None, :3, 3]
            self.pairer = FramePairer(chain.joint_names, fk, max_marker_speed=max_marker_speed,
                                      still_guard_ns=int(round(still_guard_s * 1e9)))
            mean = None
        if min_frames is None:
            min_frames = 1 if board is not None else 2
        if isinstance(max_views_per_dwell, bool) or not isinstance(max_views_per_dwell, int) \
                or max_views_per_dwell < 0:
            raise ValueError('max_views_per_dwell must be an integer >= 0 (0: no cap), got '
                             f'{max_views_per_dwell!r}')
        self.pooler = DwellPooler(fk, dwell_radius=dwell_radius,
                                  min_frames=min_frames, mean_config=mean,
                                  max_views=max_views_per_dwell if board is not None else 0,
                                  max_fits=max_fits_per_view)
        # A point target carried by the arm moves in the images when the arm moves; eye-in-
        # hand cameras and boards follow other rules.
        self.static_spots = (StaticSpotFilter() if board is None and not cameras_on_link
                             else None)
        self.counts = collections.Counter()
        self.image_sizes: Dict[str, tuple] = {}
        self.log = RateLimitedLog(log)
        #: The robot model's joints that joint states lacked, and the names the last such
        #: message carried: what a wrong URDF or a renamed joint looks like.
        self.missing_joints = frozenset()
        self.seen_joint_names = ()
        self._typical_bytes: Dict[str, int] = {}

    def _count(self, key, message=None):
        self.counts[key] += 1
        if message:
            self.log(key, f'{message} (seen {self.counts[key]} times; skipped)')

    def add_joint_state(self, stamp_ns, names, positions) -> List:
        """Feed one JointState; return the samples completed (usually none)."""
        if self.pose_input:
            self._count('joint_state_unused', 'joint state ignored: this collector takes '
                        'pose input')
            return []
        self.counts['joint_states'] += 1
        try:
            status, ready = self.pairer.add_joint_state(stamp_ns, list(names),
                                                        np.asarray(positions, float))
        except ValueError as exc:
            self._count('joint_state_invalid', f'joint state rejected: {exc}')
            return []
        if status is JointStatus.TIME_JUMP:
            self._count('time_jump', 'joint state time jumped backwards: joint history reset')
        elif status is JointStatus.MISSING_JOINT:
            missing = tuple(getattr(self.pairer.history, 'missing', ()))
            # Replaced, not updated: the node's diagnostics read it from another thread.
            self.missing_joints = self.missing_joints | frozenset(missing)
            self.seen_joint_names = tuple(str(n) for n in names)
            self._count('joint_state_missing_joint',
                        f'joint state rejected: it lacks joint(s) {list(missing)} of the robot '
                        f'model (it has {list(self.seen_joint_names)})')
        elif status is not JointStatus.OK:
            self._count(f'joint_state_{status.value}',
                        f'joint state rejected: {status.value}')
        return self._process(ready)

    def add_pose(self, stamp_ns, translation, quat_xyzw) -> List:
        """
        Feed one measured pose of the marker link (pose input); return the samples completed.

        ``translation`` (3,) metres and ``quat_xyzw`` (4,) unit quaternion, in the base frame.
        """
        if not self.pose_input:
            self._count('pose_unused', 'pose ignored: this collector takes joint states')
            return []
        self.counts['poses'] += 1
        try:
            status, ready = self.pairer.add_pose(stamp_ns, translation, quat_xyzw)
        except (TypeError, ValueError) as exc:
            self._count('pose_invalid', f'pose rejected: {exc}')
            return []
        if status is JointStatus.TIME_JUMP:
            self._count('time_jump', 'pose time jumped backwards: pose history reset')
        elif status is JointStatus.NON_FINITE:
            self._count('pose_invalid', 'pose rejected: it needs a finite translation and a '
                        'unit quaternion')
        elif status is not JointStatus.OK:
            self._count(f'pose_{status.value}', f'pose rejected: {status.value}')
        return self._process(ready)

    def add_image(self, camera, stamp_ns, msg) -> List:
        """Feed one image message (Image or CompressedImage, undecoded); return samples."""
        if camera not in self.detectors:
            self._count('unknown_camera', f'image from unknown camera {camera!r}')
            return []
        self.counts['frames'] += 1
        stamp_ns -= self.stamp_latency_ns.get(camera, 0)
        return self._process(self.pairer.add_frame(camera, stamp_ns, msg))

    def flush(self) -> List:
        """Decide every waiting frame and close the open dwell (end of a bag)."""
        return self._process(self.pairer.flush()) + self._complete(self.pooler.flush())

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
                if self.pooler.needs_detection(frame):
                    fit = self.pooler.needs_fit(frame)
                    if not fit:
                        self.counts['frames_fit_skipped'] += 1
                    dets = self._detect(frame.camera, frame.payload, fit)
                else:
                    self.counts['frames_skipped_dwell_full'] += 1
            else:
                self.counts[f'frames_{frame.status.value}'] += 1
            samples.extend(self.pooler.add(frame, dets))
        return self._complete(samples)

    def _complete(self, samples) -> List:
        """Give pooled samples their link pose (pose input, boards) and board geometry."""
        for s in samples:
            if self.pose_input:
                s.pose = pose_vector_matrix(s.q)[0]
                s.q = None
            elif self.board is not None:
                s.pose = self.chain.fk_pose(s.q)[0]
            if self.board is not None:
                c = self.board.centre_in_link()
                s.point_nominal = s.pose[:3, :3] @ c + s.pose[:3, 3]
        if self.static_spots is not None and samples:
            samples, dropped = self.static_spots.filter(samples)
            for cam in dropped:
                self._count('observations_static',
                            f'{cam}: a view within {STATIC_PX:g} px of one of its last while '
                            'the arm moved (a fixed spot taken for the marker)')
            self.counts['samples_static'] = self.static_spots.counts['samples_static']
        return samples

    def _detect(self, camera, msg, fit=True):
        nbytes = len(getattr(msg, 'data', b''))
        typical = self._typical_bytes.get(camera)
        if is_oversize(nbytes, typical):
            self._count('image_oversize', f'{camera}: image of {nbytes / 1e6:.1f} MB, its '
                        f'images are about {typical / 1e6:.2f} MB')
            return ()
        try:
            image = decode_image_msg(msg)
        except ImageDecodeError as exc:
            self._count('image_decode_error', f'{camera}: image cannot be decoded: {exc}')
            return ()
        except Exception as exc:  # a malformed message must not stop the stream
            self._count('image_malformed', f'{camera}: malformed image message: {exc}')
            return ()
        h, w = image.shape[:2]
        known = self.image_sizes.get(camera)
        if known is not None and known != (w, h):
            # A camera's size is part of its calibration: a frame of another size is a wrong
            # message, or the driver changed resolution (then restart the calibrator).
            self._count('image_size_changed', f'{camera}: image of {w}x{h}, its images are '
                        f'{known[0]}x{known[1]} (a new resolution needs a new calibration: '
                        f'restart the calibrator with a fresh output_dir)')
            return ()
        self.image_sizes[camera] = (w, h)
        if typical is None:
            self._typical_bytes[camera] = max(nbytes, 1)
        try:
            dets = (self.detectors[camera].detect(image) if fit
                    else self.detectors[camera].detect(image, fit=False))
        except Exception as exc:  # noqa: B902 - one frame, not the recording
            # A detector's failure on one frame (a fit started from a degenerate blob) costs
            # that frame, counted and said once, not every sample of the stream after it.
            self._count('detector_error', f'{camera}: the detector failed on a frame '
                        f'(skipped): {type(exc).__name__}: {exc}')
            return ()
        if self.board is not None and len(self.board.points) == 1:
            # A point marker as a one-point target: whatever its id, a detection is point 0.
            dets = [replace(d, id=0) for d in dets]
        if dets:
            self.counts['detections'] += 1
        else:
            self.counts['frames_no_marker'] += 1
        return dets


def why_few_samples(counts, missing_joints=(), seen_joint_names=()) -> str:
    """
    Say from the front end's counts why a recording gave few or no samples (one sentence).

    The commonest causes, checked in the order the pipeline meets them: the arm's stream does
    not fit the robot model (joint names), no images, images and arm never overlapping in time,
    an arm that never held still, a marker that is never found.  Returns '' when the counts
    show none of them.
    """
    js = counts.get('joint_states', 0)
    frames = counts.get('frames', 0)
    missing = counts.get('joint_state_missing_joint', 0)
    if js and missing >= 0.9 * js:
        return (f'{missing} of {js} joint states lack joint(s) {sorted(missing_joints)} named '
                f'in the robot model (they carry {list(seen_joint_names)}): is this the '
                f'robot\'s URDF, and marker_link the right link?')
    if js == 0 and counts.get('poses', 0) == 0:
        return 'no joint state (or pose) was read: check joint_states_topic (or pose_topic)'
    if frames == 0:
        return 'no image was read: check image_topics'
    unpaired = sum(counts.get(f'frames_{k}', 0) for k in
                   ('empty', 'before_history', 'after_history', 'gap', 'stale', 'time_jump'))
    if unpaired >= 0.9 * frames:
        return (f'{unpaired} of {frames} images found no joint states around their stamps: do '
                f'the images and the arm share one clock (header stamps)?')
    still = counts.get('frames_still', 0)
    if still == 0:
        return (f'none of {frames} images was taken while the marker was still (slower than '
                f'max_marker_speed): did the arm pause in view of the cameras?')
    if counts.get('detections', 0) == 0:
        return (f'the marker was found in none of {still} still images: check marker_type and '
                f'its detector parameters (e.g. sphere_min/max_radius_px)')
    return ''
