"""
Time pairing of images with joint states, stillness, and pooling of dwells into samples.

Flow (the node and the offline tool use it the same way)::

    pairer = FramePairer(chain.joint_names, fk)
    pooler = DwellPooler(fk)
    status, ready = pairer.add_joint_state(stamp_ns, names, positions)   # per JointState
    ready = pairer.add_frame(camera, stamp_ns, payload)                  # per image
    for frame in ready:            # frames whose joint history is now known
        if frame.status is PairStatus.STILL:
            detections = detector[frame.camera].detect(decode(frame.payload))
        samples += pooler.add(frame, detections)

A frame is held by the pairer until the joint history covers ``stamp + speed_window`` (joint
states arrive after the image they bracket), so the caller decides what the payload is: an
undecoded message (detect only still frames: cheapest) or detections.

Stillness is expressed as a marker speed (m/s) at the image stamp.  The marker's apparent
error from motion is speed x timing uncertainty (stamp error, unsynchronised exposure); the
default bounds it by 0.1 px of smear for a camera with f = 800 px at 1.5 m and 5 ms of stamp
jitter: 0.1 px * 1.5 m / 800 px / 0.005 s = 0.0375 m/s (see :func:`max_speed_for_smear`).
"""

from dataclasses import dataclass
import enum
import math

import numpy as np

from .samples import Observation, Sample


def max_speed_for_smear(max_smear_px=0.1, focal_px=800.0, distance_m=1.5,
                        timing_uncertainty_s=0.005):
    """
    Return the marker speed (m/s) that moves its image by ``max_smear_px``.

    Over the timing uncertainty: v = max_smear_px * distance_m / (focal_px *
    timing_uncertainty_s).
    """
    for name, value in (('max_smear_px', max_smear_px), ('focal_px', focal_px),
                        ('distance_m', distance_m),
                        ('timing_uncertainty_s', timing_uncertainty_s)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f'{name} must be positive, got {value}')
    return max_smear_px * distance_m / (focal_px * timing_uncertainty_s)


DEFAULT_MAX_MARKER_SPEED = max_speed_for_smear()   # 0.0375 m/s


class JointStatus(enum.Enum):
    """Outcome of :meth:`JointHistory.add` (the caller counts them)."""

    OK = 'ok'
    TIME_JUMP = 'time_jump'          # stamp went back by more than jump_threshold: history reset
    OUT_OF_ORDER = 'out_of_order'    # slightly older than the newest sample: dropped
    DUPLICATE = 'duplicate'          # same stamp as the newest sample: dropped
    NON_FINITE = 'non_finite'        # NaN or inf among the chain's joints: dropped
    MISSING_JOINT = 'missing_joint'  # a chain joint is not in the message: dropped
    MALFORMED = 'malformed'          # names/positions lengths differ, or a joint repeated


class PairStatus(enum.Enum):
    """Outcome of a joint lookup or of pairing a frame."""

    OK = 'ok'                        # interpolation succeeded
    STILL = 'still'                  # paired, marker slower than max_marker_speed
    MOVING = 'moving'                # paired, marker too fast
    EMPTY = 'empty'                  # no joint history yet
    BEFORE_HISTORY = 'before_history'
    AFTER_HISTORY = 'after_history'  # live: wait for newer joint states
    GAP = 'gap'                      # bracketing joint samples too far apart
    STALE = 'stale'                  # pending too long (joint stream stalled): dropped
    TIME_JUMP = 'time_jump'          # the frame belongs to a timeline the clock jumped away from


def _as_int_ns(stamp_ns, name='stamp_ns'):
    try:
        value = int(stamp_ns)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f'{name} must be an integer number of nanoseconds, got '
                         f'{stamp_ns!r}') from exc
    return value


class StampedRing:
    """
    A bounded, time-ordered ring of stamped rows with the input timing rules of the front end.

    Shared by joint histories and pose histories.  :meth:`push` refuses a repeated stamp
    (DUPLICATE) and a slightly older one (OUT_OF_ORDER); a stamp older than the newest by more
    than ``jump_threshold_ns`` (a looping bag, a restarted simulation clock) clears the history,
    is stored and returns TIME_JUMP.  Keeps the newest ``capacity`` rows in a buffer of twice
    that, compacted when full, so appending is amortised O(1) and the stored rows are always one
    contiguous, sorted view.
    """

    def __init__(self, width, capacity=4096, max_gap_ns=50_000_000,
                 jump_threshold_ns=500_000_000):
        if int(capacity) < 2:
            raise ValueError(f'capacity must be >= 2, got {capacity!r}')
        self.capacity = int(capacity)
        self.max_gap_ns = _as_int_ns(max_gap_ns, 'max_gap_ns')
        self.jump_threshold_ns = _as_int_ns(jump_threshold_ns, 'jump_threshold_ns')
        if self.max_gap_ns <= 0 or self.jump_threshold_ns < 0:
            raise ValueError('max_gap_ns must be positive and jump_threshold_ns non-negative')
        self._t = np.zeros(2 * self.capacity, np.int64)
        self._rows = np.zeros((2 * self.capacity, int(width)))
        self._start = self._end = 0

    def __len__(self):
        return self._end - self._start

    @property
    def stamps(self):
        """Return a view of the stored stamps in ns, oldest first."""
        return self._t[self._start:self._end]

    @property
    def rows(self):
        """Return a view of the stored rows, shape (len, width)."""
        return self._rows[self._start:self._end]

    @property
    def first_stamp(self):
        """Oldest stamp (ns) or None."""
        return int(self._t[self._start]) if len(self) else None

    @property
    def last_stamp(self):
        """Newest stamp (ns) or None."""
        return int(self._t[self._end - 1]) if len(self) else None

    def clear(self):
        """Forget every row."""
        self._start = self._end = 0

    def push(self, stamp_ns, row) -> JointStatus:
        """Append one checked row at ``stamp_ns``; return OK, TIME_JUMP or why it was refused."""
        stamp_ns = int(stamp_ns)
        status = JointStatus.OK
        if len(self):
            last = self.last_stamp
            if stamp_ns == last:
                return JointStatus.DUPLICATE
            if stamp_ns < last:
                if last - stamp_ns <= self.jump_threshold_ns:
                    return JointStatus.OUT_OF_ORDER
                self.clear()
                status = JointStatus.TIME_JUMP
        if self._end == self._t.shape[0]:
            keep = self.capacity - 1
            self._t[:keep] = self._t[self._end - keep:self._end]
            self._rows[:keep] = self._rows[self._end - keep:self._end]
            self._start, self._end = 0, keep
        self._t[self._end] = stamp_ns
        self._rows[self._end] = row
        self._end += 1
        if self._end - self._start > self.capacity:
            self._start += 1
        return status


class JointHistory(StampedRing):
    """
    A bounded, time-ordered ring of joint samples in chain order, with linear interpolation.

    Joints are matched by name (an index map is cached per distinct name tuple, so messages
    whose joint order changes, or which carry extra joints such as a gripper, are handled);
    a message missing a chain joint is refused.  Joint differences larger than pi between two
    neighbouring samples are taken as a wrap of a continuous joint and interpolated the short
    way.
    """

    def __init__(self, joint_names, capacity=4096, max_gap_ns=50_000_000,
                 jump_threshold_ns=500_000_000):
        self.joint_names = tuple(str(n) for n in joint_names)
        if not self.joint_names or len(set(self.joint_names)) != len(self.joint_names):
            raise ValueError(f'joint_names must be non-empty and unique, got {joint_names!r}')
        super().__init__(len(self.joint_names), capacity, max_gap_ns, jump_threshold_ns)
        self._index_maps = {}
        self.missing = ()     # chain joints absent (or repeated) in the last refused message

    @property
    def positions(self):
        """Return a view of the stored joint vectors in chain order, shape (len, n)."""
        return self.rows

    def _index_map(self, names):
        key = tuple(names)
        found = self._index_maps.get(key)
        if found is None:
            where = {}
            for i, name in enumerate(key):
                where.setdefault(name, []).append(i)
            missing = tuple(n for n in self.joint_names if n not in where)
            repeated = tuple(n for n in self.joint_names if len(where.get(n, ())) > 1)
            if missing:
                found = (JointStatus.MISSING_JOINT, missing)
            elif repeated:
                found = (JointStatus.MALFORMED, repeated)
            else:
                found = np.array([where[n][0] for n in self.joint_names], dtype=np.intp)
            if len(self._index_maps) < 64:
                self._index_maps[key] = found
        return found

    def add(self, stamp_ns, names, positions):
        """
        Add one JointState (stamp, names, positions); return a :class:`JointStatus`.

        A stamp older than the newest by more than ``jump_threshold_ns`` (a looping bag, a
        restarted simulation clock) clears the history, stores the sample and returns
        TIME_JUMP; a slightly older one is dropped (OUT_OF_ORDER).
        """
        stamp_ns = _as_int_ns(stamp_ns)
        names = tuple(names)
        positions = np.asarray(positions, dtype=float).reshape(-1)
        if positions.shape[0] != len(names):
            return JointStatus.MALFORMED
        index = self._index_map(names)
        if isinstance(index, tuple):
            status, self.missing = index
            return status
        q = positions[index]
        if not np.all(np.isfinite(q)):
            return JointStatus.NON_FINITE
        return self.push(stamp_ns, q)

    def lookup(self, stamps_ns):
        """
        Interpolate at several stamps: return (statuses (M,) of PairStatus, positions (M, n)).

        Rows whose status is not OK are NaN.
        """
        ts = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        out = np.full((ts.shape[0], len(self.joint_names)), np.nan)
        statuses = np.full(ts.shape[0], PairStatus.OK, dtype=object)
        if not len(self):
            statuses[:] = PairStatus.EMPTY
            return statuses, out
        t, q = self.stamps, self.positions
        hi = np.searchsorted(t, ts, side='left')
        exact = (hi < t.shape[0]) & (t[np.minimum(hi, t.shape[0] - 1)] == ts)
        before = (hi == 0) & ~exact
        after = hi == t.shape[0]
        statuses[before] = PairStatus.BEFORE_HISTORY
        statuses[after] = PairStatus.AFTER_HISTORY
        out[exact] = q[hi[exact]]
        inner = ~(before | after | exact)
        if np.any(inner):
            h = hi[inner]
            lo = h - 1
            gap = t[h] - t[lo]
            a = ((ts[inner] - t[lo]) / gap)[:, None]
            d = q[h] - q[lo]
            d = np.where(np.abs(d) > np.pi, (d + np.pi) % (2 * np.pi) - np.pi, d)
            vals = q[lo] + a * d
            bad_gap = gap > self.max_gap_ns
            vals[bad_gap] = np.nan
            out[inner] = vals
            st = statuses[inner]
            st[bad_gap] = PairStatus.GAP
            statuses[inner] = st
        return statuses, out

    def interpolate(self, stamp_ns):
        """Return (PairStatus, q (n,) or None) at one stamp, by linear interpolation."""
        statuses, q = self.lookup([_as_int_ns(stamp_ns)])
        status = statuses[0]
        return status, (q[0] if status is PairStatus.OK else None)


@dataclass
class PairedFrame:
    """
    A frame whose pairing is decided.

    ``q`` (n,) joint angles at the stamp (or, with pose input, the link pose as a
    configuration vector) and ``point`` (3,) the nominal marker position ((R, 3) reference
    points for an extended target), set when ``status`` is STILL or MOVING; ``speed`` marker
    speed (m/s) or NaN; ``payload``
    whatever the caller handed to :meth:`FramePairer.add_frame`.
    """

    camera: str
    stamp_ns: int
    payload: object
    status: PairStatus
    q: np.ndarray = None
    point: np.ndarray = None
    speed: float = math.nan


class FramePairer:
    """
    Pairs camera frames with interpolated joint angles and decides stillness.

    ``fk(Q (M, n)) -> (M, 3)`` gives the nominal marker position for joint vectors in the
    order of ``joint_names``; for an extended target (a board) it may return R reference
    points per joint vector, (M, R, 3), and the fastest of them counts.  The marker speed at
    stamp t is

        v = max(|p(t) - p(t - W)|, |p(t + W) - p(t)|) / W,   W = speed_window_ns,

    over the interpolated joint history: the window averages out joint-encoder noise over the
    few ms between JointState messages, and the max of the two halves still catches the arm
    reversing through t.  A frame is STILL when v <= ``max_marker_speed``; with a
    ``still_guard_ns`` g > 0, the speed over [t - g - W, t - g] must be below it too: a camera
    whose driver stamps its images up to g late (on arrival) exposed them while the arm may
    still have been coming to rest, and those frames would pull the dwell's image mean along
    the approach while its joint mean stays put.

    Frames wait (at most ``max_pending`` of them) until the history reaches t + W.

    ``history`` replaces the joint history by another with its interface (``add``,
    ``lookup``, ``first_stamp``, ``last_stamp``, ``clear``, ``jump_threshold_ns``): with a
    :class:`~armcal_ros.frontend.pose_input.PoseHistory` the pairer takes measured link poses
    (:meth:`add_pose`) and ``fk`` maps pose vectors; ``joint_names`` is then unused.
    """

    def __init__(self, joint_names, fk, max_marker_speed=DEFAULT_MAX_MARKER_SPEED,
                 speed_window_ns=20_000_000, max_gap_ns=50_000_000,
                 jump_threshold_ns=500_000_000, capacity=4096, max_pending=256,
                 batch_ns=100_000_000, history=None, still_guard_ns=0):
        if not callable(fk):
            raise ValueError('fk must be callable: fk(Q (M, n)) -> (M, 3)')
        self.fk = fk
        # Frames are decided in batches once the oldest has waited batch_ns beyond its window:
        # one vectorised FK call per batch instead of one per frame (measured: the per-call
        # overhead was half the offline front end's time).  It delays a sample by <= batch_ns.
        self.batch_ns = _as_int_ns(batch_ns, 'batch_ns')
        self.max_marker_speed = float(max_marker_speed)
        if not (math.isfinite(self.max_marker_speed) and self.max_marker_speed > 0):
            raise ValueError(f'max_marker_speed must be positive (m/s), got {max_marker_speed}')
        self.speed_window_ns = _as_int_ns(speed_window_ns, 'speed_window_ns')
        if self.speed_window_ns <= 0:
            raise ValueError(f'speed_window_ns must be positive, got {speed_window_ns}')
        self.still_guard_ns = _as_int_ns(still_guard_ns, 'still_guard_ns')
        if self.still_guard_ns < 0:
            raise ValueError(f'still_guard_ns must be >= 0, got {still_guard_ns}')
        if int(max_pending) < 1:
            raise ValueError(f'max_pending must be >= 1, got {max_pending!r}')
        self.max_pending = int(max_pending)
        if history is None:
            history = JointHistory(joint_names, capacity=capacity, max_gap_ns=max_gap_ns,
                                   jump_threshold_ns=jump_threshold_ns)
        self.history = history
        self._pending = []

    @property
    def joint_names(self):
        """Chain joint names, the order of ``q`` (empty with pose input)."""
        return getattr(self.history, 'joint_names', ())

    @property
    def n_pending(self):
        """Frames waiting for newer joint states."""
        return len(self._pending)

    def add_joint_state(self, stamp_ns, names, positions):
        """Add a JointState; return (JointStatus, frames that became decidable)."""
        return self._added(stamp_ns, self.history.add(stamp_ns, names, positions))

    def add_pose(self, stamp_ns, translation, quat_xyzw):
        """Add a measured link pose (pose history only); return (JointStatus, frames)."""
        return self._added(stamp_ns, self.history.add(stamp_ns, translation, quat_xyzw))

    def _added(self, stamp_ns, status):
        ready = []
        if status is JointStatus.TIME_JUMP:
            # Frames stamped after the new time belong to the old timeline.
            limit = int(stamp_ns) + self.history.jump_threshold_ns
            keep = []
            for frame in self._pending:
                if frame[1] > limit:
                    ready.append(PairedFrame(frame[0], frame[1], frame[2], PairStatus.TIME_JUMP))
                else:
                    keep.append(frame)
            self._pending = keep
        if status is JointStatus.TIME_JUMP and self._pending:
            ready.extend(self._resolve(final=False))
        elif status is JointStatus.OK and self._batch_ready():
            ready.extend(self._resolve(final=False))
        return status, ready

    def add_frame(self, camera, stamp_ns, payload=None):
        """Queue a frame; return the frames (this one or earlier ones) now decided."""
        self._pending.append((str(camera), _as_int_ns(stamp_ns), payload))
        ready = self._resolve(final=False) if self._batch_ready() else []
        while len(self._pending) > self.max_pending:
            camera, stamp, payload = self._pending.pop(0)
            ready.append(PairedFrame(camera, stamp, payload, PairStatus.STALE))
        return ready

    def _batch_ready(self):
        last = self.history.last_stamp
        if not self._pending or last is None:
            return False
        oldest = min(f[1] for f in self._pending)
        return last >= oldest + self.speed_window_ns + self.batch_ns

    def flush(self):
        """Decide every pending frame with the history as it is (end of a bag)."""
        return self._resolve(final=True)

    def reset(self):
        """Clear the joint history and drop pending frames (returned as STALE)."""
        dropped = [PairedFrame(c, s, p, PairStatus.STALE) for c, s, p in self._pending]
        self._pending = []
        self.history.clear()
        return dropped

    def _resolve(self, final):
        if not self._pending:
            return []
        last = self.history.last_stamp
        w = self.speed_window_ns
        ready, keep = [], []
        for frame in self._pending:
            if not final and (last is None or frame[1] + w > last):
                first = self.history.first_stamp
                if first is not None and frame[1] - w < first:
                    ready.append(PairedFrame(*frame, PairStatus.BEFORE_HISTORY))
                else:
                    keep.append(frame)
            else:
                ready.append(frame)
        self._pending = keep
        decided = [f for f in ready if isinstance(f, tuple)]
        out = [f for f in ready if not isinstance(f, tuple)]
        if decided:
            out.extend(self._pair(decided))
        return out

    def _pair(self, frames):
        w, g = self.speed_window_ns, self.still_guard_ns
        # Per frame: t - W, t, t + W and, with a guard, t - g - W, t - g.
        offsets = [-w, 0, w] + ([-g - w, -g] if g else [])
        stamps = np.array([[s + o for o in offsets] for _, s, _ in frames], dtype=np.int64)
        statuses, q = self.history.lookup(stamps.reshape(-1))
        statuses = statuses.reshape(len(frames), len(offsets))
        q = q.reshape(len(frames), len(offsets), -1)
        good = np.array([all(s is PairStatus.OK for s in row) for row in statuses])
        points = None
        if np.any(good):
            p = np.asarray(self.fk(q[good].reshape(-1, q.shape[2])), dtype=float)
            p = p.reshape(int(np.count_nonzero(good)), len(offsets), -1, 3)
            points = np.full((len(frames),) + p.shape[1:], np.nan)
            points[good] = p
        out = []
        for i, (camera, stamp, payload) in enumerate(frames):
            if not good[i]:
                row = [s for s in statuses[i] if s is not PairStatus.OK]
                status = row[0]
                if PairStatus.GAP in row:
                    status = PairStatus.GAP
                elif statuses[i][0] is PairStatus.BEFORE_HISTORY:
                    status = PairStatus.BEFORE_HISTORY
                out.append(PairedFrame(camera, stamp, payload, status))
                continue
            p0, p1, p2 = points[i][:3]
            speed = max(np.linalg.norm(p1 - p0, axis=1).max(),
                        np.linalg.norm(p2 - p1, axis=1).max()) / (w * 1e-9)
            if g:
                speed = max(speed, np.linalg.norm(points[i][4] - points[i][3], axis=1).max()
                            / (w * 1e-9))
            status = PairStatus.STILL if speed <= self.max_marker_speed else PairStatus.MOVING
            point = p1[0].copy() if len(p1) == 1 else p1.copy()
            out.append(PairedFrame(camera, stamp, payload, status, q=q[i, 1].copy(),
                                   point=point, speed=float(speed)))
        return out


class _Dwell:
    def __init__(self, frame):
        self.anchor = frame.point
        self.first_stamp = self.last_stamp = frame.stamp_ns
        self.qs = []
        self.stamps = []
        self.per_camera = {}      # camera -> list of (stamp, {id: uv}, {id: centroid})

    def add(self, frame, detections):
        self.qs.append(frame.q)
        self.stamps.append(frame.stamp_ns)
        self.last_stamp = max(self.last_stamp, frame.stamp_ns)
        self.first_stamp = min(self.first_stamp, frame.stamp_ns)
        if detections:
            # A centroid-only detection (the fit skipped) has a NaN uv: no fitted centre.
            uvs = {int(d.id): np.asarray(d.uv, dtype=float) for d in detections
                   if np.all(np.isfinite(d.uv))}
            cents = {int(d.id): np.asarray(d.centroid, dtype=float) for d in detections
                     if d.centroid is not None}
            self.per_camera.setdefault(frame.camera, []).append((frame.stamp_ns, uvs, cents))


class DwellPooler:
    """
    Pools consecutive still frames at one place into one :class:`Sample`.

    A dwell is open while STILL frames arrive whose nominal marker position stays within
    ``dwell_radius`` (m) of the dwell's first one, at most ``max_gap_ns`` apart.  It is closed
    (and a sample emitted if it has enough data) by a MOVING frame, a still frame elsewhere, a
    gap, a TIME_JUMP or GAP frame, a dwell longer than ``max_dwell_ns`` (a parked arm still
    yields samples regularly; the store merges them) or :meth:`poll` / :meth:`flush`.

    On closing, per camera and target id: the median of the frames' detections, frames
    further than ``outlier_px`` from it dropped (a spurious detection in one frame), and the
    mean of the rest; kept if at least ``min_frames`` remain.  ``spread_px`` is their RMS
    distance from the mean.  When every kept frame's detection carries an intensity
    ``centroid`` beside its fitted centre, their mean and spread over the same frames go into
    the observation as well (``centroid_uv``, ``centroid_spread_px``; all targets of the
    camera or none).  The sample's ``q`` is the mean joint vector
    (``mean_config(Q (F, n))``, the arithmetic mean by default; pose input passes a rotation-
    aware mean of its pose vectors) and ``point_nominal = fk(q)``.  When ``fk`` returns R > 1
    reference points (an extended target), the dwell radius applies to the farthest of them
    and the sample carries them as ``reference_points`` (``point_nominal`` the first; the
    caller completes the sample).  At most ``max_frames`` frames per camera are kept per dwell.

    ``max_views`` > 0 caps the detection work: once a camera has ``max_views`` frames with
    detections in the open dwell, :meth:`needs_detection` is False for its further still
    frames there, and the caller passes them without detections.  They still extend the dwell
    (its stamps, its joint mean and its gap and length limits) as any frame without a
    detection does, so the sample is the one the first ``max_views`` views give; 0 is no cap.

    ``max_fits`` > 0 caps a costly centre fit the same way (a shaded ball): once a camera has
    ``max_fits`` frames with a fitted centre in the open dwell, :meth:`needs_fit` is False and
    the caller passes centroid-only detections (a NaN ``uv`` beside the ``centroid``).  Such
    a view pools its centroids over all its frames (median, outliers dropped, mean) and its
    light shift (fit - centroid) over the fitted ones (the same, ``min_frames`` of them
    needed): ``uv = mean centroid + mean shift`` - the ball is still in a dwell, so its light
    shift is one value.  Its ``spread_px`` is then the spread that ``n_frames`` frames would
    have for the variance of that sum, ``sqrt(2 (n - 1) (s_c^2 / n + s_s^2 / K))`` with the
    per-axis variances ``s_c^2`` of the n centroids and ``s_s^2`` of the K shifts (an upper
    bound: the fit's and the centroid's shared pixel noise would lower ``s_s``).
    """

    def __init__(self, fk, dwell_radius=0.001, max_gap_ns=500_000_000,
                 max_dwell_ns=10_000_000_000, min_frames=2, outlier_px=2.0, max_frames=200,
                 mean_config=None, max_views=0, max_fits=0):
        if not callable(fk):
            raise ValueError('fk must be callable: fk(Q (M, n)) -> (M, 3)')
        if mean_config is not None and not callable(mean_config):
            raise ValueError('mean_config must be callable: mean_config(Q (F, n)) -> (n,)')
        self.fk = fk
        self.mean_config = mean_config or (lambda Q: np.mean(Q, axis=0))
        self.dwell_radius = float(dwell_radius)
        if not self.dwell_radius > 0:
            raise ValueError(f'dwell_radius must be positive (m), got {dwell_radius}')
        self.max_gap_ns = _as_int_ns(max_gap_ns, 'max_gap_ns')
        self.max_dwell_ns = _as_int_ns(max_dwell_ns, 'max_dwell_ns')
        if self.max_gap_ns <= 0 or self.max_dwell_ns <= 0:
            raise ValueError('max_gap_ns and max_dwell_ns must be positive')
        if int(min_frames) < 1:
            raise ValueError(f'min_frames must be >= 1, got {min_frames!r}')
        self.min_frames = int(min_frames)
        self.outlier_px = float(outlier_px)
        if not self.outlier_px > 0:
            raise ValueError(f'outlier_px must be positive, got {outlier_px}')
        if int(max_frames) < self.min_frames:
            raise ValueError(f'max_frames must be >= min_frames, got {max_frames!r}')
        self.max_frames = int(max_frames)
        if not isinstance(max_views, (int, np.integer)) or isinstance(max_views, bool) or not (
                max_views == 0 or self.min_frames <= max_views):
            raise ValueError(f'max_views must be 0 (no cap) or an integer >= min_frames '
                             f'({self.min_frames}), got {max_views!r}')
        self.max_views = int(max_views)
        if not isinstance(max_fits, (int, np.integer)) or isinstance(max_fits, bool) or not (
                max_fits == 0 or self.min_frames <= max_fits):
            raise ValueError(f'max_fits must be 0 (no cap) or an integer >= min_frames '
                             f'({self.min_frames}), got {max_fits!r}')
        self.max_fits = int(max_fits)
        self._dwell = None

    @property
    def open(self):
        """Return True while a dwell is being accumulated."""
        return self._dwell is not None

    def add(self, frame, detections=()):
        """Feed one :class:`PairedFrame` and its detections; return samples completed."""
        out = []
        if frame.status is not PairStatus.STILL:
            if frame.status in (PairStatus.MOVING, PairStatus.GAP, PairStatus.TIME_JUMP):
                out.extend(self.flush())
            return out
        if self._dwell is not None and not self._joins(frame):
            out.extend(self.flush())
        if self._dwell is None:
            self._dwell = _Dwell(frame)
        frames = self._dwell.per_camera.get(frame.camera, ())
        if len(frames) < self.max_frames:
            if self.max_views and len(frames) >= self.max_views:
                detections = ()
            self._dwell.add(frame, detections)
        return out

    def needs_detection(self, frame):
        """
        Return False when ``frame``'s detections would not be used (the views cap).

        That is a still frame that joins the open dwell, whose camera already has
        ``max_views`` frames with detections there; always True without a cap.
        """
        if not self.max_views or frame.status is not PairStatus.STILL or \
                self._dwell is None or not self._joins(frame):
            return True
        return len(self._dwell.per_camera.get(frame.camera, ())) < self.max_views

    def needs_fit(self, frame):
        """
        Return False when ``frame``'s camera has ``max_fits`` fitted views in the open dwell.

        Only for a still frame that joins the open dwell; always True without a cap.
        """
        if not self.max_fits or frame.status is not PairStatus.STILL or \
                self._dwell is None or not self._joins(frame):
            return True
        fitted = sum(1 for _, uvs, _ in self._dwell.per_camera.get(frame.camera, ()) if uvs)
        return fitted < self.max_fits

    def _joins(self, frame):
        """Return True when the still ``frame`` belongs to the open dwell."""
        dwell = self._dwell
        far = np.linalg.norm(np.reshape(frame.point - dwell.anchor, (-1, 3)),
                             axis=1).max() > self.dwell_radius
        gap = (frame.stamp_ns - dwell.last_stamp > self.max_gap_ns
               or dwell.first_stamp - frame.stamp_ns > self.max_gap_ns)
        too_long = frame.stamp_ns - dwell.first_stamp > self.max_dwell_ns
        return not (far or gap or too_long)

    def poll(self, now_ns):
        """Close the dwell if nothing was added for ``max_gap_ns`` before ``now_ns``."""
        if self._dwell is not None and int(now_ns) - self._dwell.last_stamp > self.max_gap_ns:
            return self.flush()
        return []

    def flush(self):
        """Close the current dwell; return [sample] or [] when it had too little data."""
        dwell, self._dwell = self._dwell, None
        if dwell is None:
            return []
        observations = {}
        for camera, frames in dwell.per_camera.items():
            obs = self._pool_camera(frames)
            if obs is not None:
                observations[camera] = obs
        if not observations:
            return []
        q = np.asarray(self.mean_config(np.asarray(dwell.qs)), dtype=float).reshape(-1)
        points = np.asarray(self.fk(q[None, :]), dtype=float).reshape(-1, 3)
        stamp = int(np.median(np.asarray(dwell.stamps, dtype=np.int64)))
        return [Sample(point_nominal=points[0], observations=observations, stamp_ns=stamp, q=q,
                       reference_points=points if len(points) > 1 else None)]

    def _pool_camera(self, frames):
        if any(set(cents) - set(uvs) for _, uvs, cents in frames):
            return self._pool_camera_shifts(frames)
        ids = sorted({i for _, uvs, _ in frames for i in uvs})
        uv_out, id_out, sq_sum, n_sq = [], [], 0.0, 0
        cent_out, cent_sq = [], 0.0
        frames_used = set()
        for tid in ids:
            rows = [k for k, (_, uvs, _) in enumerate(frames) if tid in uvs]
            pts = np.array([frames[k][1][tid] for k in rows])
            med = np.median(pts, axis=0)
            inlier = np.linalg.norm(pts - med, axis=1) <= self.outlier_px
            if np.count_nonzero(inlier) < self.min_frames:
                continue
            mean = pts[inlier].mean(axis=0)
            sq_sum += float(np.sum((pts[inlier] - mean) ** 2))
            n_sq += int(np.count_nonzero(inlier))
            kept = [k for k, ok in zip(rows, inlier) if ok]
            frames_used.update(kept)
            uv_out.append(mean)
            id_out.append(tid)
            if cent_out is not None and all(tid in frames[k][2] for k in kept):
                cents = np.array([frames[k][2][tid] for k in kept])
                cent_out.append(cents.mean(axis=0))
                cent_sq += float(np.sum((cents - cents.mean(axis=0)) ** 2))
            else:
                cent_out = None
        if not uv_out:
            return None
        stamps = np.array([frames[k][0] for k in sorted(frames_used)], dtype=np.int64)
        return Observation(uv=np.array(uv_out), ids=np.array(id_out), n_frames=len(frames_used),
                           spread_px=math.sqrt(sq_sum / n_sq), stamp_ns=int(np.median(stamps)),
                           centroid_uv=None if cent_out is None else np.array(cent_out),
                           centroid_spread_px=(0.0 if cent_out is None
                                               else math.sqrt(cent_sq / n_sq)))

    def _pool_camera_shifts(self, frames):
        """Pool a view whose frames are partly centroid-only (class docstring, ``max_fits``)."""
        ids = sorted({i for _, _, cents in frames for i in cents})
        uv_out, id_out, cent_out, var_uv, cent_sq, n_all = [], [], [], 0.0, 0.0, 0
        frames_used = set()
        for tid in ids:
            rows = [k for k, (_, _, cents) in enumerate(frames) if tid in cents]
            cents = np.array([frames[k][2][tid] for k in rows])
            inlier = np.linalg.norm(cents - np.median(cents, axis=0), axis=1) <= self.outlier_px
            kept = [k for k, ok in zip(rows, inlier) if ok]
            fitted = [k for k in kept if tid in frames[k][1]]
            if len(kept) < self.min_frames or len(fitted) < self.min_frames:
                continue
            shifts = np.array([frames[k][1][tid] - frames[k][2][tid] for k in fitted])
            near = np.linalg.norm(shifts - np.median(shifts, axis=0), axis=1) <= self.outlier_px
            if np.count_nonzero(near) < self.min_frames:
                continue
            shifts, c = shifts[near], cents[inlier]
            n, m = len(c), len(shifts)
            c_sq = float(np.sum((c - c.mean(axis=0)) ** 2))
            s_sq = float(np.sum((shifts - shifts.mean(axis=0)) ** 2))
            # The per-axis variances of the mean centroid and of the mean shift.
            var_uv += c_sq / (2.0 * max(n - 1, 1) * n) + s_sq / (2.0 * max(m - 1, 1) * m)
            cent_sq += c_sq
            n_all += n
            frames_used.update(kept)
            cent_out.append(c.mean(axis=0))
            uv_out.append(c.mean(axis=0) + shifts.mean(axis=0))
            id_out.append(tid)
        if not uv_out:
            return None
        n = len(frames_used)
        stamps = np.array([frames[k][0] for k in sorted(frames_used)], dtype=np.int64)
        return Observation(uv=np.array(uv_out), ids=np.array(id_out), n_frames=n,
                           spread_px=math.sqrt(2.0 * max(n - 1, 0) * var_uv / len(uv_out)),
                           stamp_ns=int(np.median(stamps)), centroid_uv=np.array(cent_out),
                           centroid_spread_px=math.sqrt(cent_sq / n_all))
