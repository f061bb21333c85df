"""
Following a cell that changes: the engine's record of declared changes and recalibrations.

:class:`~armcal_ros.core.change.ChangeMonitor` tests each new sample against the current
calibration.  This module keeps what the engine needs around it:

- the *epochs*: a change starts a new one; the changed camera's observations from before it are
  retired in the store (kept, tagged, no longer its views; the engine solves them as the
  camera as it was, ``CalibrationEngine._epoch_cameras``), every other camera and the arm keep
  theirs;
- the cameras being recalibrated: a camera that moved is withheld (its calibration no longer
  describes it) until it has ``recalibration_samples`` new observations and a solve that
  includes them has been accepted; it is then started from a PnP of its new observations with
  its old intrinsics, and its new views, refitted against the calibration it left, say what
  changed (the pose by so many degrees and millimetres, or the lens: the focal length);
- the events, for /diagnostics, report.json and a restart (``changes.json`` beside the
  calibration).

docs/ARCHITECTURE.md, "When a camera moves", has the flow and the reasons for the defaults.
"""

import json
import os
from collections import deque
from dataclasses import asdict, dataclass, field
from typing import Dict, List, Optional, Tuple

import numpy as np

from armcal_ros.core.change import (ARM_SIGMA_FLOOR, ChangeEvent, ChangeMonitor,
                                    ChangeSettings, CONFIRM_OBSERVATIONS, joint_subset,
                                    ONSET_SLACK, PredictionModel, reference_scales,
                                    size_change, View)
from armcal_ros.core.evaluation import similarity_fit
from armcal_ros.core.kinematic_prior import rigid_motion_jacobian
from armcal_ros.io.calib_files import atomic_write_text

CHANGES_FILE = 'changes.json'
#: Samples of the calibration's own that calibrate the monitor's scale: the median of a few
#: hundred is within a few per cent, and the cost stays a fraction of a second.
REFERENCE_SAMPLES = 300
#: Views of a recalibrated camera after which its change is no longer re-measured: the size's
#: precision then no longer limits anything (a few hundredths of a degree).
SIZING_VIEWS = 200
#: New views whose light-shift errors (:meth:`ChangeTracker._as_solved`) size what the pooled
#: shift adds to a new view's noise: 20 views' 2-D errors give the variance within about a
#: quarter (40 degrees of freedom), and a region newly visited shows within a few views.
SHIFT_ERROR_VIEWS = 20
#: Views a newer calibration's monitor tests quietly beside a climbing one before it takes
#: over (:meth:`ChangeTracker.adopt`): as many as a suspect camera is judged on.
PENDING_VIEWS = CONFIRM_OBSERVATIONS + ONSET_SLACK
#: Samples a later solve must have added, and kept, before an arm prediction's error at
#: places it was not fitted to is measured (ArmPrediction.forward_error): 6 points give the
#: RMS of 18 coordinates, within about a sixth.
MIN_FORWARD_SAMPLES = 6


def earlier_self(camera: str, epoch: int) -> str:
    """Return the name ``camera``'s views retired at the start of ``epoch`` are solved under."""
    return f'{camera}#{int(epoch)}'


def of_earlier_self(name: str) -> Optional[Tuple[str, int]]:
    """Return (camera, epoch) of an :func:`earlier_self` name; None for any other name."""
    camera, sep, tag = name.rpartition('#')
    return (camera, int(tag)) if sep and camera and tag.isdigit() else None


@dataclass
class ChangeRecord:
    """One declared change and what became of it (JSON-serialisable)."""

    kind: str                      # 'camera', 'arm' or 'unexplained'
    camera: Optional[str]
    epoch: int
    onset_ns: int
    detected_ns: int
    statistic: float
    threshold: float
    samples: int
    evidence: Dict[str, float] = field(default_factory=dict)
    retired: int = 0               # observations retired
    status: str = 'recalibrating'  # 'recalibrating', 'recalibrated', 'reported'
    what: str = ''                 # 'pose', 'lens', 'arm or marker'
    rotation_deg: float = float('nan')
    translation_mm: float = float('nan')
    focal_percent: float = float('nan')
    new_observations: int = 0

    def summary(self, start_ns=0, needed=None):
        """Return one line for a log or /diagnostics (``needed``: the views to recalibrate)."""
        t = (self.onset_ns - start_ns) * 1e-9
        if self.kind == 'disagreement':
            return (f'{self.camera}: views from t = {t:.1f} s disagreed with its calibration, '
                    'but no new pose explains them (bad detections?); nothing changed')
        if self.kind == 'arm' and self.status == 'restarted':
            return (f'the arm or marker changed at t = {t:.1f} s (every camera disagreed with '
                    f'the arm, not with each other, twice in a row): {self.retired} older '
                    'observations retired, samples restarted')
        if self.kind == 'arm':
            return (f'the cameras disagreed with the arm at t = {t:.1f} s, not with each other '
                    '(a new tool or marker, a re-homed joint?); watching')
        if self.kind == 'unexplained':
            return (f'views from t = {t:.1f} s disagreed with the calibration and no single '
                    f'change explains them (first seen by {self.camera}); watching')
        head = f'{self.camera} changed at t = {t:.1f} s'
        if self.status == 'recalibrating':
            of = f' of {needed}' if needed else ''
            return f'{head}: recalibrating ({self.new_observations}{of} new views)'
        size = (f'{self.rotation_deg:.2f} deg / {self.translation_mm:.1f} mm, focal '
                f'{self.focal_percent:+.2f} %')
        return f'{head}: {self.what} ({size}), recalibrated'


def _json_safe(d):
    return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in d.items()}


class ChangeTracker:
    """The engine's change detection state (thread safety: the engine's lock)."""

    def __init__(self, settings: ChangeSettings = None, recalibration_samples=20,
                 enabled=True):
        # Checked where they enter (EngineSettings.validate).
        self.settings = settings or ChangeSettings()
        self.recalibration_samples = int(recalibration_samples)
        self.enabled = bool(enabled)
        self.monitor: Optional[ChangeMonitor] = None
        #: A newer calibration's monitor that waits for the current one's climb to end
        #: (:meth:`adopt`).
        self.pending: Optional[ChangeMonitor] = None
        self.records: List[ChangeRecord] = []
        self.epoch = 0
        #: epoch -> the calibration in force when it ended (written under DIR/epochs/)
        self.epoch_calibrations: Dict[int, object] = {}
        #: camera -> (its record, the predictor it was found with, views sized on so far)
        self._sizing: Dict[str, tuple] = {}
        #: camera -> (its record, its last calibration before the change, the predictor the
        #: change was found with)
        self.recalibrating: Dict[str, tuple] = {}
        #: camera -> its light shift pooled at the last accepted solve
        #: (core.light_pooling.PooledShift): a new view with an intensity centroid is tested
        #: at that centroid plus the shift at its place, as the solve saw its views.
        self.light_shifts: Dict[str, object] = {}
        #: camera -> the latest new views' light-shift errors (own shift less pooled, px)
        self._shift_errors: Dict[str, deque] = {}

    # -- the predictor ---------------------------------------------------------------------
    def build_monitor(self, calibration, arrays, arm_sigma,
                      parameter_covariance=None, joint_covariance=None,
                      prediction=None) -> Optional[ChangeMonitor]:
        """
        Return a monitor of an accepted calibration, scaled on the samples it was solved on.

        The cameras being recalibrated are left out; ``parameter_covariance`` maps cameras to
        (their parameter names, covariance) from the adjustment, ``joint_covariance`` is
        ([(camera, parameter)], C) over all of them with their correlations (what the
        leave-one-out prediction propagates, :func:`~armcal_ros.core.change.agreement`).  Built
        outside the engine's lock (the scales take a fraction of a second); the engine swaps it
        in.  ``prediction`` (an :class:`ArmPrediction`) predicts where the arm really is at a new
        view; without it the arm's measured point serves, with ``arm_sigma`` its error.
        """
        if not self.enabled or calibration is None:
            return None
        cams, sig = {}, {}
        fallback = calibration.hyperparameters.get('pixel_sigma', float('nan'))
        for name, c in calibration.cameras.items():
            if name in self.recalibrating:
                continue
            s = c.sigma_px if np.isfinite(c.sigma_px) and c.sigma_px > 0 else fallback
            if not (np.isfinite(s) and s > 0):
                continue
            cams[name], sig[name] = c.camera, float(s)
        if not cams:
            return None
        arm = max(float(arm_sigma), ARM_SIGMA_FLOOR)
        points, obs = per_point(arrays, limit=REFERENCE_SAMPLES,
                                points=None if prediction is None else prediction.own)
        # The scale is calibrated on the samples the cameras were fitted to, whose residuals
        # the fit has pulled in: there the parameters' uncertainty does not show, so it is
        # left out of the scale and added for the new views only.
        retained = {n: c.redundancy / (2.0 * c.n_inliers)
                    for n, c in calibration.cameras.items()
                    if n in cams and np.isfinite(c.redundancy) and c.n_inliers > 0}
        scales = reference_scales(PredictionModel(cams, sig, arm), points, obs, retained)
        model = PredictionModel(cams, sig, arm, {k: v for k, v in
                                                 (parameter_covariance or {}).items()
                                                 if k in cams},
                                joint_subset(joint_covariance, cams),
                                0.0 if prediction is None else prediction.model_sigma,
                                prediction)
        return ChangeMonitor(model, scales, self.settings)

    def adopt(self, monitor: Optional[ChangeMonitor]):
        """
        Test against ``monitor`` (a newer accepted calibration's) now, or once it has shown it.

        A solve that ran while a camera was drifting off its prediction has absorbed part of
        the change, so while the current monitor's statistics climb (or it judges a suspect)
        the newer one waits as :attr:`pending`, testing the same views beside it
        (:meth:`observe`).  It takes over when the climb ends, when it has tested
        :data:`PENDING_VIEWS` views without a climb of its own (the climb was the older
        calibration's: an early one of a few samples predicts with wide parameter
        covariances and a move of several pixels falls inside them), or when it declares a
        change itself.
        """
        old = self.monitor
        if old is not None and monitor is not None:
            monitor.carry_over(old)
        if old is not None and old.busy:
            self.pending = monitor
            return
        self.monitor, self.pending = monitor, None

    def disputed(self) -> bool:
        """
        Return True while the test has views under suspicion: a camera's statistic climbing.

        A solve that runs meanwhile takes in views the calibration does not explain, perhaps
        a change's first ones; the engine then refuses it if its residuals rose clearly
        (``engine._residuals_worse``), rather than publish every camera bent towards them.
        """
        return any(m is not None and m.busy for m in (self.monitor, self.pending))

    def observe(self, sample) -> Optional[ChangeEvent]:
        """Test one new sample; return the event if a change is declared."""
        if self.monitor is None or sample.reference_points is not None:
            return None
        uvs, extra = {}, {}
        for n, o in sample.observations.items():
            uvs[n], extra[n] = self._as_solved(n, o, sample.point_nominal)
        stamps = [o.stamp_ns for o in sample.observations.values() if o.stamp_ns]
        stamp = min(stamps) if stamps else sample.stamp_ns
        event = _observe(self.monitor, sample, uvs, stamp, extra)
        pending = self.pending
        if pending is None:
            return event
        newer = _observe(pending, sample, uvs, stamp, extra)
        if event is not None:
            return event
        if newer is not None or not self.monitor.busy or (
                pending.tested >= PENDING_VIEWS and not pending.busy):
            self.monitor, self.pending = pending, None
        return newer

    def _as_solved(self, camera, observation, point):
        """
        Return (uv (2,), variance): one view's image point as the solve takes it, and its noise.

        With ``shaded_pooled``, the centroid plus the camera's pooled light shift f at
        ``point``; otherwise the view's own centre (variance 0).  A fitted centre carries the
        fit's own noise and its errors where the ball is half in shadow; the calibration was
        solved on pooled centroids, so the test compares those (measured on a lamp-lit
        desk-4cam recording, 180 s: three false changes on fitted centres, one on pooled ones).

        The pooled shift is known well where it was pooled, and worse at a place the arm
        visits for the first time, where the smooth extrapolates.  What it adds to a new
        view's noise is measured on the new views themselves: each brings its own shift d
        (fitted centre less centroid), and e = d - f(X) has E e^2 = s_d^2 + (f's error)^2 per
        axis, s_d^2 the d's own noise (the pooling's, ``noise_var``).  So the variance added
        is the mean e^2 over the latest :data:`SHIFT_ERROR_VIEWS` views (this one included)
        less s_d^2.  Both centres of a view move together when the camera moves, so e, and
        what it adds, does not grow with a knock or a refocus: the test keeps its power for
        those while a shift extrapolated by a tenth of a pixel is no longer a change (a
        lamp-lit desk-4cam recording, 180 s: two false changes before, none with it;
        docs/ARCHITECTURE.md, "When a camera moves").
        """
        pooled = self.light_shifts.get(camera)
        if observation.centroid_uv is None or pooled is None or pooled.status != 'ok' or \
                point is None:
            return observation.uv[0], 0.0
        f = pooled.at(np.asarray(point, float)[None])[0]
        errors = self._shift_errors.setdefault(camera, deque(maxlen=SHIFT_ERROR_VIEWS))
        errors.append(observation.uv[0] - observation.centroid_uv[0] - f)
        own = pooled.noise_var if np.isfinite(pooled.noise_var) else 0.0
        return observation.centroid_uv[0] + f, max(0.0, float(np.mean(np.square(errors))) - own)

    # -- events ----------------------------------------------------------------------------
    def declare(self, event: ChangeEvent, store, calibration) -> ChangeRecord:
        """Start a new epoch for ``event``: retire the old observations, note the camera."""
        if event.kind == 'disagreement':
            # One camera's views disagree and no new pose explains them: bad detections, not
            # a change.  Reported; nothing is retired and no epoch starts.
            rec = ChangeRecord(event.kind, event.camera, self.epoch, event.onset_ns,
                               event.detected_ns, event.statistic, event.threshold,
                               event.samples, {k: float(v) for k, v in event.evidence.items()},
                               status='reported', what='views not explained by a change')
            self.records.append(rec)
            return rec
        if event.kind in ('arm', 'unexplained'):
            return self._arm_or_unexplained(event, store, calibration)
        camera = event.camera
        if calibration is not None:
            self.epoch_calibrations[self.epoch] = calibration
        self.epoch += 1
        rec = ChangeRecord(event.kind, camera, self.epoch, event.onset_ns, event.detected_ns,
                           event.statistic, event.threshold, event.samples,
                           {k: float(v) for k, v in event.evidence.items()})
        if event.fit is not None:
            rec.rotation_deg, rec.translation_mm = event.fit.rotation_deg, \
                event.fit.translation_mm
            rec.focal_percent = event.fit.focal_percent
        rec.retired = store.retire(event.onset_ns, self.epoch, camera)
        # A calibration solved before the change was declared holds the camera's old pose.
        self.pending = None
        old = calibration.cameras.get(camera) if calibration is not None else None
        self.recalibrating[camera] = (rec, old, event.model)
        self._sizing.pop(camera, None)
        self.records.append(rec)
        return rec

    def _arm_or_unexplained(self, event, store, calibration):
        """
        Report an arm (or unexplained) disagreement; retire the samples when it repeats.

        One alarm is reported only: a new tool or a re-homed joint shows again in the next
        views, a passing disturbance does not.  A second one in a row (no other change between)
        confirms it: every observation before the first one's onset is retired and the
        samples start again, the cameras keeping their calibration meanwhile.
        """
        prev = self.records[-1] if self.records else None
        rec = ChangeRecord(event.kind, event.camera if event.kind == 'unexplained' else None,
                           self.epoch, event.onset_ns, event.detected_ns, event.statistic,
                           event.threshold, event.samples,
                           {k: float(v) for k, v in event.evidence.items()},
                           status='reported', what='arm or marker (unconfirmed)'
                           if event.kind == 'arm' else 'not explained by any one change')
        if event.kind == 'arm' and prev is not None and prev.kind == 'arm' and \
                prev.status == 'reported':
            if calibration is not None:
                self.epoch_calibrations[self.epoch] = calibration
            self.epoch += 1
            rec.epoch = self.epoch
            rec.onset_ns = prev.onset_ns
            rec.retired = store.retire(prev.onset_ns, self.epoch, None)
            self.pending = None
            rec.status, rec.what = 'restarted', 'arm or marker'
            prev.status = 'confirmed'
        self.records.append(rec)
        return rec

    def count_new(self, views):
        """Update each recalibrating camera's count of new views (``views``: camera -> count)."""
        for name, (rec, *_) in self.recalibrating.items():
            rec.new_observations = int(views.get(name, 0))

    def ready(self, name):
        """Return True if camera ``name`` may be solved (not recalibrating, or has enough)."""
        got = self.recalibrating.get(name)
        return got is None or got[0].new_observations >= self.recalibration_samples

    def waiting(self):
        """Return the cameras withheld until they have enough new observations."""
        return [n for n in self.recalibrating if not self.ready(n)]

    def accepted(self, calibration):
        """
        After an accepted solve: close the recalibrations it contains; return the sizing jobs.

        A changed camera's new views are refitted against the predictor the change was found
        with (:func:`size`): the size and the kind (pose or lens) are then measured in the old
        calibration's own frame, free of the drift of the whole solution between the two
        solves.  The measurement is repeated at every accepted solve while the camera gathers
        views (up to :data:`SIZING_VIEWS`): a focus change that twenty views cannot tell from a
        move along the axis may show later.  Returns (camera, record, predictor) to size;
        the refits run outside the engine's lock.
        """
        for name in list(self.recalibrating):
            if name not in calibration.cameras or not self.ready(name):
                continue
            rec, old, model = self.recalibrating.pop(name)
            rec.status = 'recalibrated'
            rec.what = 'camera'
            if model is not None and name in model.cameras:
                self._sizing[name] = (rec, model, 0)
        return [(name, rec, model) for name, (rec, model, _) in self._sizing.items()]

    def size(self, jobs, arrays, joints=None):
        """
        Refit each job's camera to its views in ``arrays``; return (camera, record, result).

        ``result`` is (what, fit, views used) or None; :meth:`apply_sizes` records them.
        ``joints`` are the joint angles of each of the arrays' points (or None): a model
        that predicts the arm (``arm_prediction``) is given the arm where it predicts it.
        """
        points, obs = per_point(arrays)
        joints = [None] * len(points) if joints is None else joints
        out = []
        for name, rec, model in jobs:
            rows = [i for i, uvs in enumerate(obs) if name in uvs]
            X, A, ok = points[rows], [None] * len(rows), np.ones(len(rows), bool)
            if model.arm_prediction is not None:
                X, A, ok = model.arm_prediction.predict(X, [joints[i] for i in rows])
            views = [View(0, X[k], obs[i], arm_design=A[k])
                     for k, i in enumerate(rows) if ok[k]]
            try:
                what, fit = size_change(model, name, views[:SIZING_VIEWS],
                                        false_alarm=self.settings.false_alarm, own_scale=True)
            except (np.linalg.LinAlgError, ValueError):
                out.append((name, rec, None))
                continue
            out.append((name, rec, (what, fit, len(views))))
        return out

    def apply_sizes(self, sized):
        """Record the sizes :meth:`size` measured (for cameras not declared changed since)."""
        for name, rec, got in sized:
            current = self._sizing.get(name)
            if current is None or current[0] is not rec or got is None:
                continue
            what, fit, n = got
            if n <= current[2]:
                continue
            rec.what = what
            rec.rotation_deg, rec.translation_mm = fit.rotation_deg, fit.translation_mm
            rec.focal_percent = fit.focal_percent
            if n >= SIZING_VIEWS:
                del self._sizing[name]
            else:
                self._sizing[name] = (rec, current[1], n)

    def withheld(self):
        """Return the cameras whose published calibration no longer holds."""
        return sorted(self.recalibrating)

    # -- persistence -----------------------------------------------------------------------
    def save(self, directory):
        """Write ``changes.json`` (the events and the cameras being recalibrated)."""
        doc = dict(epoch=self.epoch, records=[_json_safe(asdict(r)) for r in self.records],
                   recalibrating=sorted(self.recalibrating))
        path = os.path.join(directory, CHANGES_FILE)
        atomic_write_text(path, json.dumps(doc, indent=1))
        return path

    def load(self, directory, calibration):
        """Restore from ``changes.json`` (nothing if absent); return the number of events."""
        path = os.path.join(directory, CHANGES_FILE)
        if not os.path.exists(path):
            return 0
        try:
            with open(path, encoding='utf-8') as f:
                doc = json.load(f)
            records = [ChangeRecord(**{k: (float('nan') if v is None else v)
                                       for k, v in r.items()}) for r in doc['records']]
            epoch = int(doc['epoch'])
            waiting = list(doc.get('recalibrating', []))
        except (ValueError, KeyError, TypeError) as exc:
            raise ValueError(f'{path}: not a changes file ({exc})') from exc
        self.records, self.epoch = records, epoch
        by_camera = {r.camera: r for r in records if r.camera is not None}
        self.recalibrating = {
            n: (by_camera[n], None if calibration is None else calibration.cameras.get(n), None)
            for n in waiting if n in by_camera}
        return len(records)


def _observe(monitor, sample, uvs, stamp, extra):
    """Test ``sample`` with ``monitor`` at the arm's predicted point (untested without one)."""
    arm = monitor.model.arm_prediction
    if arm is None:
        return monitor.observe(sample.point_nominal, uvs, stamp, extra)
    got = arm(sample.point_nominal, sample.q)
    if got is None:
        return None
    return monitor.observe(got[0], uvs, stamp, extra, got[1])


class ArmPrediction:
    """
    Where the arm really is at a new view, by the accepted calibration's kinematic model.

    The kinematic models estimate the arm's error parameters dp (:mod:`~armcal_ros.core.priors`:
    X_i = X^_i + J_p(q_i) diag(sigma_p) g + ...): a correction the arm's geometry carries to
    any configuration, seen or not.  A new view's arm point is X^ + A g with A = J_p(q)
    diag(sigma_p), and the change test fuses it at the arm error ``sigma`` (m per axis): the
    RMS over the calibration's own points of what the kinematic part leaves (a field beside it
    in ``hybrid``, the points' own noise), the uncertainty of g being propagated with its
    correlations with the cameras (the joint covariance's :data:`~armcal_ros.core.change.ARM`
    rows).  With the measured point and the size of the correction instead, two cameras and
    an arm known to millimetres predict each other loosely, and a change in either camera is
    explained equally by refitting the other.  A field's correction (``correlated``, the
    field of ``hybrid``) is a function of where the marker is, not of the arm's
    configuration; carried to a configuration not seen it can be off by as much as the
    correction itself (measured on a simulated UR5 with kinematic errors: a lattice field's
    prediction at 0.1 mm raised a false arm alarm), so it is not used.

    ``model_sigma`` is the correction's own uncertainty per axis, for the fusions that take
    the arm on its own (a refit of one camera to points fused from the arm and the others):
    the RMS over the own points of A g's spread once a rigid motion of all of them is taken
    out, Cov = P A Cov(g) A^T P with P the projection off the span of the rigid motions
    (:func:`~armcal_ros.core.kinematic_prior.rigid_motion_jacobian`).  The refitted camera's
    new pose absorbs such a motion; with it left in, the spread holds the frame the arm fixes
    only to its own accuracy (about 1 mm on the UR5 cell at every sample count), which weighs
    the arm far below what it knows relative to the cameras.  ``slice`` is where g sits among
    the adjustment's global parameters.

    ``own`` (N, 3) are the calibration's own points so predicted.  ``kinematics(Q (1, n))``
    returns the marker's KinematicData at a new view, ``shift(jacobian)`` (1, 3) moves a
    measured point to the marker's estimated place on its link (or None).  Calling it with a
    view's measured point and joint angles returns (point (3,), design (3, G)), or None when
    the view has no joint angles.
    """

    def __init__(self, adjustment, points, kinematics_data, kinematics, shift=None):
        pr = adjustment.prior
        if pr is None or 'kinematic' not in getattr(pr, 'global_slices', {}) or \
                kinematics_data is None or kinematics is None or \
                adjustment.global_parameters is None or adjustment.global_covariance is None:
            raise ValueError('an arm prediction needs an adjustment with a kinematic model')
        self.kinematics, self.shift = kinematics, shift
        self.slice = pr.global_slices['kinematic']
        self.scale = pr.kinematics.sigma * pr.settings.kinematic_scale
        self.g = np.asarray(adjustment.global_parameters, float)[self.slice]
        points = np.asarray(points, float)
        self.own = points + kinematics_data.jacobian @ (self.scale * self.g)
        d = np.asarray(adjustment.points, float) - self.own
        self.sigma = float(np.sqrt(np.mean(np.sum(d * d, axis=1)) / 3.0)) if len(d) else 0.0
        # Over a few hundred of the own points: a median within a few per cent, at a cost
        # that does not grow with the session.
        n = len(points)
        keep = np.linspace(0, n - 1, min(n, REFERENCE_SAMPLES)).round().astype(int)
        A = kinematics_data.jacobian[keep] * self.scale[None, None, :]
        A = A.reshape(3 * len(keep), -1)
        Cg = np.asarray(adjustment.global_covariance, float)[self.slice, self.slice]
        R = rigid_motion_jacobian(points[keep]).reshape(3 * len(keep), 6)
        PA = A - R @ np.linalg.lstsq(R, A, rcond=None)[0]
        var = np.einsum('ig,gh,ih->', PA, Cg, PA) / max(1, PA.shape[0])
        self.model_sigma = float(np.sqrt(max(float(var), 0.0))) if n else 0.0

    def forward_error(self, points, joints, adjusted, new) -> float:
        """
        Return the RMS per axis of this prediction at samples a later solve added (m).

        ``points`` (N, 3) measured, ``joints`` their joint angles, ``adjusted`` (N, 3) the
        later solve's points, ``new`` (N,) bool the samples this prediction was not fitted
        to.  The later solve's frame differs from this one's by a rigid motion (the arm fixes
        it only to its own accuracy): it is the one that maps this prediction of the other
        samples onto theirs (:func:`~armcal_ros.core.evaluation.similarity_fit` without
        scale).  NaN with fewer than MIN_FORWARD_SAMPLES of either.
        """
        pred, _, ok = self.predict(points, joints)
        new, old = ok & np.asarray(new, bool), ok & ~np.asarray(new, bool)
        if new.sum() < MIN_FORWARD_SAMPLES or old.sum() < MIN_FORWARD_SAMPLES:
            return float('nan')
        adjusted = np.asarray(adjusted, float)
        frame = similarity_fit(pred[old], adjusted[old], with_scale=False)
        e = adjusted[new] - frame.apply(pred[new])
        return float(np.sqrt(np.mean(np.sum(e * e, axis=1)) / 3.0))

    def predict(self, points, joints):
        """
        Return (points (N, 3), designs (N, 3, G), ok (N,)) of N views at once.

        ``points`` (N, 3) measured, ``joints`` their joint angles (None where a view has
        none: not ok, its rows NaN).  One forward-kinematics call for all of them.
        """
        points = np.asarray(points, float).reshape(-1, 3)
        ok = np.array([q is not None for q in joints], bool).reshape(len(points))
        G = len(self.g)
        X, A = np.full(points.shape, np.nan), np.full((len(points), 3, G), np.nan)
        if not ok.any():
            return X, A, ok
        Q = np.array([np.asarray(q, float).ravel() for q, k in zip(joints, ok) if k])
        jac = self.kinematics(Q).jacobian
        at = points[ok]
        if self.shift is not None:
            at = at + self.shift(jac)
        A[ok] = jac * self.scale[None, None, :]
        X[ok] = at + A[ok] @ self.g
        return X, A, ok

    def __call__(self, point, q):
        """Return (point (3,), design (3, G)) of a view at ``point`` with joints ``q``, or None."""
        X, A, ok = self.predict(np.asarray(point, float).reshape(1, 3), [q])
        return (X[0], A[0]) if ok[0] else None


def per_point(arrays, limit=None, points=None):
    """
    Return (points (N, 3), [name -> uv (2,)] per point) of a store's point-target arrays.

    ``points`` (N, 3) replaces the arrays' measured points (the arm's predicted ones).
    """
    n = len(arrays.points)
    points = arrays.points if points is None else np.asarray(points, float)
    keep = np.arange(n)
    if limit is not None and n > limit:
        keep = np.linspace(0, n - 1, limit).round().astype(int)
    obs = [dict() for _ in range(n)]
    for c, p, uv in zip(arrays.camera_index, arrays.point_index, arrays.uv):
        obs[p][arrays.camera_names[c]] = uv
    return points[keep], [obs[i] for i in keep]


__all__ = ['ArmPrediction', 'ChangeTracker', 'ChangeRecord', 'CHANGES_FILE', 'per_point']
