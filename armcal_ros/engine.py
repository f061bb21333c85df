"""
The ROS-free online calibrator shared by the node and the offline CLI.

It accumulates samples in a :class:`~armcal_ros.frontend.store.SampleStore`, decides when a solve
is due, runs it (synchronously, or in a background worker thread so that the caller - a ROS
executor - never stalls), and hands out the latest accepted :class:`Calibration`.

When a solve is due: at least ``min_samples`` samples, at least ``solve_period_s`` since the last
solve started, and at least ``min_new_samples`` samples added or changed since then (no point
re-solving the same data).  The first solve starts from scratch (DLT, fixed, model); later ones
are warm-started from the current calibration.

A new result replaces the current calibration only if it is not clearly worse: it must have
converged, and no camera's image noise estimated from its residuals (the RMS corrected for the
degrees of freedom its parameters took, :func:`_residuals_worse`) may exceed
``max(reject_rms_ratio x previous, previous + reject_rms_margin_px)`` - while the change test
has views under suspicion, ``reject_rms_ratio`` x previous or what the two estimates' own
scatter allows, no absolute margin - nor its inlier
fraction drop by more than ``reject_inlier_drop`` and by more than its counting noise explains
(fractions as expected rates, :func:`inlier_fall_is_clear`).  A burst of bad detections
therefore cannot overwrite a good calibration; the rejection is reported with its reason.

Cameras on the arm (``EngineSettings.eye_in_hand``) looking at a static target are the same
problem with the roles of base and link swapped: seen from the link, the target moves by
T_link_base(v) = T_base_link(v)^-1 while the cameras stand still.  So the board solver is given
the inverted link poses; what it calls T_link_target is the target's pose in the base frame,
and the cameras' poses come out in the link's frame (T_link_camera).

Targets: point samples (a sphere, a tag) are solved by
:func:`~armcal_ros.core.calibration.calibrate` over one 3-D point per sample.  With a board
(``EngineSettings.board``) every sample is a view - the link pose and the corners each camera
saw - solved by :func:`~armcal_ros.core.board_calibration.calibrate_board`, which also
estimates the board's pose on the link (T_link_target) when the board says so.  The estimate
seeds the next solve and is saved as ``target.yaml`` beside the calibration.
"""

import json
import math
import os
import threading
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Dict, List, Optional, Tuple

import numpy as np
from scipy.stats import f as f_distribution
from threadpoolctl import threadpool_limits

from armcal_ros.change_tracking import (ArmPrediction, ChangeTracker, CHANGES_FILE,
                                        earlier_self, of_earlier_self)
from armcal_ros.core.adjustment import Observations, SolverSettings
from armcal_ros.core.board_calibration import BoardData, calibrate_board, MountSettings
from armcal_ros.core.calibration import calibrate, CalibrationResult, CameraSpec
from armcal_ros.core.change import ARM, ChangeSettings, LAG_VIEWS, SCALE_WINDOW
from armcal_ros.core.initialisation import initialise_with_intrinsics
from armcal_ros.core.intrinsics_prior import IntrinsicsPrior
from armcal_ros.core.image_noise import pooled_pixel_sigma
from armcal_ros.core.kinematic_prior import KinematicData, tip_place
from armcal_ros.core.light_pooling import compare_solves, pool_light_shift, PooledShift
from armcal_ros.core.marker_light import image_offsets
from armcal_ros.core.priors import KINEMATIC_MODELS, PointPrior, PriorSettings
from armcal_ros.core.results import Calibration, calibration_from_result
from armcal_ros.core.earlier_self import lens_test, pose_test
from armcal_ros.core.target import invert, pose_vector
from armcal_ros.frontend.samples import BoardTarget
from armcal_ros.frontend.store import SampleStore, SolverArrays
from armcal_ros.io.calib_files import atomic_write_text, read_extrinsics
from armcal_ros.io.results_files import (CALIBRATION_FILE, load_calibration,
                                         read_target_scale, read_target_yaml, TARGET_FILE,
                                         write_calibration, write_target)

#: Which cameras use their fitted lit-ball centres, and why (:meth:`CalibrationEngine.save`).
CENTRES_FILE = 'lit_centres.json'
#: A camera's views after a reported disagreement within which a change declared on it is
#: taken to be what the report saw first (:meth:`CalibrationEngine._epoch_limits`): the change
#: monitor's scale window and the views it lags by (core/change.py), after which the scale
#: holds views from after the report alone.  The measured case it must keep: a 0.5 % refocus
#: declared 18 of the camera's views after its report.
REPORT_LINK_VIEWS = SCALE_WINDOW + LAG_VIEWS


@dataclass
class EngineSettings:
    """What the engine calibrates and when it re-solves."""

    camera_names: List[str]
    prior: PriorSettings = field(default_factory=PriorSettings)
    solver: SolverSettings = field(default_factory=SolverSettings)
    min_samples: int = 20
    solve_period_s: float = 10.0
    min_new_samples: int = 5
    reject_rms_ratio: float = 1.5
    reject_rms_margin_px: float = 0.3
    reject_inlier_drop: float = 0.1
    base_frame: str = 'base_link'
    #: A board target (None: point samples); ``marker_link`` names its link in target.yaml.
    board: Optional[BoardTarget] = None
    marker_link: str = 'tool0'
    #: The cameras ride on the marker link, the board target is static in ``base_frame``: the
    #: solve swaps the roles (module docstring) and the cameras come out in ``marker_link``.
    eye_in_hand: bool = False
    #: A point marker placed by a kinematic model: the guess (m, on ``marker_link``) the
    #: samples' points were computed at; the tip errors' translation is the place's correction.
    point_place_guess: Optional[Tuple[float, float, float]] = None
    #: Change detection (:mod:`armcal_ros.core.change`; point targets): on, the test's run
    #: and false-alarm probability, and the new observations a changed camera needs before it
    #: is solved again.
    detect_changes: bool = True
    change: ChangeSettings = field(default_factory=ChangeSettings)
    recalibration_samples: int = 20
    #: Forgetting for slow drift: observations older than this (s, before the newest sample)
    #: are retired before each solve; 0 keeps everything.
    max_sample_age_s: float = 0.0
    #: A matte ball lit by one lamp: (lamp position (3,) in base_frame, ambient fraction, ball
    #: radius m); each view's centroid offset is removed before a solve
    #: (:mod:`armcal_ros.core.marker_light`).  None: the marker glows alike from every side.
    marker_light: Optional[Tuple[Tuple[float, float, float], float, float]] = None
    #: Observations carrying a centroid beside a fitted centre (the shaded sphere) are solved
    #: at the centroid plus the camera's light shift pooled over its views
    #: (:mod:`armcal_ros.core.light_pooling`).
    pool_light_shift: bool = False
    #: A camera that changed keeps its views from before the change in the solve, as a camera
    #: of their own (its earlier self) that shares with the camera now what the change left:
    #: a moved camera's lens, a refocused camera's pose, where
    #: :mod:`~armcal_ros.core.earlier_self`'s tests find it unchanged.  They keep tying the
    #: other cameras and the arm to the images.  False retires them from the solve.
    solve_earlier_epochs: bool = True

    def validate(self):
        """Raise ValueError naming the first bad setting; return self."""
        if not self.camera_names:
            raise ValueError('camera_names must name at least one camera')
        if len(set(self.camera_names)) != len(self.camera_names):
            raise ValueError(f'camera_names has duplicates: {self.camera_names}')
        if self.min_samples < 1:
            raise ValueError(f'min_samples must be >= 1, got {self.min_samples}')
        if not self.solve_period_s >= 0:
            raise ValueError(f'solve_period must be >= 0 s, got {self.solve_period_s}')
        if self.min_new_samples < 0:
            raise ValueError(f'min_new_samples must be >= 0, got {self.min_new_samples}')
        self.prior.validate()
        self.solver.validate()
        self.change.validate()
        if int(self.recalibration_samples) != self.recalibration_samples or \
                self.recalibration_samples < 6:
            raise ValueError('recalibration_samples must be an integer >= 6 (a camera has 6 '
                             f'pose parameters), got {self.recalibration_samples!r}')
        if self.marker_light is not None:
            lamp, ambient, radius = self.marker_light
            if np.shape(lamp) != (3,) or not np.all(np.isfinite(lamp)):
                raise ValueError(f'marker_lamp must be 3 finite numbers (m), got {lamp}')
            if not 0.0 <= ambient <= 1.0:
                raise ValueError(f'marker_ambient must be in [0, 1], got {ambient}')
            if not (np.isfinite(radius) and radius > 0):
                raise ValueError('marker_radius must be > 0 (m) to correct a lit marker, got '
                                 f'{radius}')
            if self.board is not None:
                raise ValueError('marker_lamp is for a sphere marker, not a board target')
        if not (np.isfinite(self.max_sample_age_s) and self.max_sample_age_s >= 0):
            raise ValueError(f'max_sample_age must be >= 0 s, got {self.max_sample_age_s}')
        if self.board is not None:
            if not isinstance(self.board, BoardTarget):
                raise ValueError(f'board must be a BoardTarget, got {type(self.board).__name__}')
            if self.prior.model in KINEMATIC_MODELS:
                raise ValueError(f'noise_model {self.prior.model} is not available with a '
                                 'board target (the board solver\'s global parameters are its '
                                 'mount on the link, not the arm\'s kinematic errors); use '
                                 'fixed, independent, correlated or auto')
        if self.point_place_guess is not None:
            if self.board is not None or self.prior.model not in KINEMATIC_MODELS:
                raise ValueError('point_place_guess needs point samples and a kinematic model '
                                 f'(got model {self.prior.model}, board '
                                 f'{self.board is not None})')
            if np.shape(self.point_place_guess) != (3,):
                raise ValueError(f'point_place_guess must have shape (3,), got '
                                 f'{np.shape(self.point_place_guess)}')
        return self


@dataclass
class LitCentres:
    """
    Observations with each camera's chosen kind of centre (:func:`lit_centres`).

    ``arrays`` the samples' arrays with the chosen centres and spreads, ``pooling`` camera ->
    its pooled light shift as pooled (status 'ok' where it pools, whichever kind is used),
    ``other_uv`` and ``other_spread`` (M, ...) per observation the kind not chosen (NaN where a
    camera has only one kind).
    """

    arrays: SolverArrays
    pooling: Dict[str, PooledShift]
    other_uv: np.ndarray
    other_spread: np.ndarray


def lit_centres(arrays, fitted=frozenset()) -> LitCentres:
    """
    Return each camera's lit-ball centres: pooled where the shift pools, but for ``fitted``.

    Per camera, the observations with an intensity centroid beside their fitted centre get
    ``uv = centroid + pooled shift`` (:func:`~armcal_ros.core.light_pooling.pool_light_shift`,
    over the nominal points) and a spread that carries the centroid's scatter plus the
    smooth's variance, so that :func:`~armcal_ros.core.image_noise.pooled_pixel_sigma` sees
    the noise of the new centres: a frame variance s^2 + n v per axis, i.e.
    spread^2 = c^2 + 2 (n - 1) v for the centroid's spread c over n frames.  The cameras named
    in ``fitted`` keep their fitted centres (the engine's choice by each kind's own
    solve, :func:`~armcal_ros.core.light_pooling.compare_solves`).
    """
    nan = np.full(arrays.uv.shape, np.nan)
    has = np.all(np.isfinite(arrays.centroid_uv), axis=1)
    if not np.any(has):
        return LitCentres(arrays, {}, nan, nan[:, 0].copy())
    uv, spread = arrays.uv.copy(), arrays.spread_px.copy()
    other_uv, other_spread = nan.copy(), nan[:, 0].copy()
    info = {}
    for c, name in enumerate(arrays.camera_names):
        sel = np.flatnonzero(has & (arrays.camera_index == c))
        if not len(sel):
            continue
        n = arrays.n_frames[sel]
        # Each shift's own noise per axis: the fit's and the centroid's frame scatter (2-D
        # RMS distances) over the frames pooled; their correlation is left out (an upper bound).
        own = (arrays.spread_px[sel] ** 2 + arrays.centroid_spread_px[sel] ** 2) / \
            (2.0 * np.maximum(n - 1, 1))
        pooled = pool_light_shift(arrays.points[arrays.point_index[sel]],
                                  arrays.uv[sel] - arrays.centroid_uv[sel],
                                  own if np.all(n >= 2) else None)
        info[name] = pooled
        if pooled.status != 'ok':
            continue
        p_uv = arrays.centroid_uv[sel] + pooled.shift
        p_spread = np.sqrt(arrays.centroid_spread_px[sel] ** 2 +
                           2.0 * np.maximum(n - 1, 0) * pooled.variance)
        if name in fitted:
            other_uv[sel], other_spread[sel] = p_uv, p_spread
        else:
            other_uv[sel], other_spread[sel] = uv[sel], spread[sel]
            uv[sel], spread[sel] = p_uv, p_spread
    return LitCentres(replace(arrays, uv=uv, spread_px=spread), info, other_uv, other_spread)


#: The image-noise rise test's false-refusal rate: a rise that two estimates of the same noise
#: reach once in a thousand solves.
NOISE_RISE_ALPHA = 1e-3


def _residuals_worse(old, new, ratio, margin_px, disputed=False, alpha=NOISE_RISE_ALPHA):
    """
    Say how the new fit of a camera is clearly worse than the old one, or return ''.

    Compared: the image noise each fit's residuals give, s = sqrt(sum |r|^2 / r) over the r
    degrees of freedom left (``sigma_px``, redundancy counted by leverage), not the raw RMS.
    A fit whose parameters absorb its few observations has an RMS near zero that says nothing
    about the noise (a first solve over three views of a camera: 0.000 px), and the next
    solve's honest 0.99 px is then no reason to refuse it.  Without redundancy in the old fit
    there is no yardstick and nothing is refused on these grounds.  The new noise is allowed
    ``max(ratio x previous, previous + margin_px)``.

    While the change test is ``disputed`` (it has views the calibration does not explain, a
    change's first ones perhaps) the margin is relative instead: the new noise may exceed the
    old by ``ratio`` and by what two estimates of one noise differ by - for Gaussian noise
    s_new^2 / s_old^2 follows Snedecor's F(r_new, r_old), so the ratio is allowed the square
    root of its upper ``alpha`` quantile where that is larger (about 3 x over ten degrees of
    freedom each, 1.24 x over two hundred).  At the 0.01 px of a ball pooled over a dwell a
    margin of tenths of a pixel would let through a solve that took in a knocked camera's
    first views, thirty times worse, and publish it for every camera until the change is
    declared.  Without a dispute the absolute margin stays: a rise there is the model meeting
    new places (a recalibrated camera rejoining the solve doubled the others' noise at 0.006
    px), and a refusal would be compared with the same old calibration at every later solve.
    Calibrations saved before the redundancy was recorded are compared by their RMS.
    """
    a, b, what = old.sigma_px, new.sigma_px, 'image noise from its residuals'
    relative = disputed and np.isfinite(old.redundancy)
    if not np.isfinite(old.redundancy):
        a, b, what = old.rms_px, new.rms_px, 'reprojection RMS'
    if not (np.isfinite(a) and np.isfinite(b)):
        return ''
    if relative:
        r_new = new.redundancy if np.isfinite(new.redundancy) and new.redundancy > 0 else 1.0
        f = float(f_distribution.isf(alpha, r_new, max(old.redundancy, 1e-3)))
        limit = a * max(ratio, math.sqrt(f) if np.isfinite(f) else math.inf)
        why = ' while the change test weighs views that disagree with the calibration'
    else:
        limit, why = max(ratio * a, a + margin_px), ''
    return (f'{what} {b:.3f} px > {limit:.3f} px allowed after {a:.3f} px{why}' if b > limit
            else '')


def _kept(specs, keep, arrays):
    """Return (camera remap, observation mask, specs) of a solve of the cameras ``keep``."""
    remap = -np.ones(len(specs), np.int64)
    remap[keep] = np.arange(len(keep))
    return remap, remap[arrays.camera_index] >= 0, [specs[j] for j in keep]


def inlier_rate(n_inliers, n_observations):
    """
    Return the expected inlier rate after ``n_inliers`` of ``n_observations``: (k + 1) / (n + 2).

    Laplace's rule of succession (the posterior mean under a uniform prior), not k / n: a first
    solve over a handful of observations cannot yet call any of them an outlier, and 7 of 7
    is weak evidence of a rate of 1.  So 7 of 7 then 12 of 14 is a fall from 0.89 to 0.81,
    while 100 of 100 then 85 of 100 (0.99 to 0.85) is still a clear drop (docs/ARCHITECTURE.md,
    "Accepting a solve").
    """
    return (n_inliers + 1.0) / (n_observations + 2.0)


#: One-sided normal quantile of the inlier-fall test: a solve is refused for a fall that counting
#: noise alone would give less than 5 % of the time.
INLIER_FALL_Z = 1.645


def inlier_fall_is_clear(old, new, drop, z=INLIER_FALL_Z):
    """
    Return True if the inlier rate fell from ``old`` to ``new`` (``(k, n)`` pairs) clearly.

    Clearly means both: by more than ``drop`` (as expected rates, :func:`inlier_rate`), and by
    more than ``z`` standard deviations of the two rates' counting noise.  Each rate's variance
    is that of its Beta(k + 1, n - k + 1) posterior, p (1 - p) / (n + 3); the two are treated as
    independent, which over-states the spread when the new solve holds the old one's
    observations - the test errs towards accepting, as the judgement should when its yardstick
    rests on a handful of observations.  So 7 of 7 then 8 of 11 (0.89 to 0.69, a spread of 0.16)
    is accepted, while 100 of 100 then 85 of 100 (0.99 to 0.85, 0.04) and 20 of 20 then 15 of 20
    (0.95 to 0.73, 0.10) are refused.
    """
    po, pn = inlier_rate(*old), inlier_rate(*new)
    fall = po - pn
    sd = np.sqrt(po * (1 - po) / (old[1] + 3.0) + pn * (1 - pn) / (new[1] + 3.0))
    return bool(fall > drop and fall > z * sd)


@dataclass
class SolveOutcome:
    """What one solve did: ``accepted`` says whether it became the current calibration."""

    accepted: bool
    reason: str
    result: Optional[CalibrationResult]
    calibration: Optional[Calibration]
    n_samples: int
    time_s: float


@dataclass
class ProblemInputs:
    """The inputs of a point-marker solve (:meth:`CalibrationEngine.problem_inputs`)."""

    specs: List[CameraSpec]
    points: np.ndarray
    obs: Observations
    kinematics: Optional[KinematicData]
    pooled_sigma_px: float


class CalibrationEngine:
    """
    Accumulate samples and keep an up-to-date calibration.

    Thread safety: :meth:`add_sample`, :meth:`maybe_solve_async`, :meth:`current` and
    :meth:`reset` may be called from any thread; one solve runs at a time.
    """

    def __init__(self, settings: EngineSettings, store: Optional[SampleStore] = None,
                 clock: Callable[[], float] = time.monotonic,
                 kinematics_fn: Optional[Callable[[np.ndarray], KinematicData]] = None):
        self.settings = settings.validate()
        # kinematics_fn(Q (N, n)) -> KinematicData: the marker's Jacobian with respect to the
        # robot's kinematic error parameters at each sample's joint angles (kinematic, hybrid
        # and auto need it; the engine itself knows nothing of robots).
        self.kinematics_fn = kinematics_fn
        # The last accepted solve's arm prediction and the samples it was fitted to, and the
        # error it showed at the samples a later solve added (_checked_arm_prediction).
        self._arm_checked, self._arm_forward = (None, set()), float('nan')
        #: run_solver(fn, *args, **kwargs) -> fn(*args, **kwargs): how each adjustment runs
        #: (None: here, on the calling thread).  The node runs them in a child process
        #: (:class:`~armcal_ros.solver_process.SolverProcess`), so that a solve does not hold
        #: the interpreter its front end needs; the engine's state stays in this process.
        self.run_solver: Optional[Callable] = None
        self._auto_choice: Optional[PriorSettings] = None
        self._auto_samples = 0
        self._auto_pixel_sigma: Optional[float] = None   # the image noise auto estimated
        # A single model's uncertainty reference (auto's choice) and the samples it saw.
        self._reference: Optional[PriorSettings] = None
        self._reference_samples = 0
        self.auto_reason = ''
        self.store = store if store is not None else SampleStore()
        self.clock = clock
        self.image_sizes: Dict[str, tuple] = {}
        #: Camera name -> the frame_id its images carry (set by whoever reads the images);
        #: the optical frame every output names.  See :meth:`frame_id`.
        self.frame_ids: Dict[str, str] = {}
        self._lock = threading.RLock()
        self._current: Optional[Calibration] = None
        self._last_solve_start = -np.inf
        self._revision_at_last_solve = -1
        self._samples_at_last_solve = 0
        # Each camera's views at the last solve, and the store revision before which none of
        # them can have grown by solve_if_grown's factor (_a_camera_grew).
        self._views_at_last_solve: Dict[str, int] = {}
        self._views_check_at = 0
        self._worker: Optional[threading.Thread] = None
        self._listeners: List[Callable[[SolveOutcome], None]] = []
        self.last_outcome: Optional[SolveOutcome] = None
        self.n_solves = 0
        self.n_rejected = 0
        # Board targets: the mount in use (the seed, then the latest accepted estimate).
        board = self.settings.board
        self.T_link_target: Optional[np.ndarray] = (
            None if board is None or board.T_link_target is None else board.T_link_target.copy())
        self.mount_std: Optional[np.ndarray] = None
        #: The factor of the target's points (a tag of estimated size: size over the guess).
        self.target_scale = 1.0
        #: Declared changes, epochs and cameras being recalibrated (point targets only: a
        #: board's corners are tested by its own solver's residuals).
        self.changes = ChangeTracker(self.settings.change, self.settings.recalibration_samples,
                                     enabled=self.settings.detect_changes and board is None)
        self._change_listeners: List[Callable] = []
        self._views_counted_at = -1
        #: Camera -> its pooled light shift at the last solve (``pool_light_shift``).
        self.light_pooling = {}
        #: Cameras whose fitted lit-ball centres are used though their shift pools: a
        #: calibration fitted them clearly better (:meth:`_choose_centres`).
        self._fitted_centres = set()
        #: Views with both kinds of centre when the kinds were last weighed (:meth:`_centres_due`).
        self._centres_compared_at: Optional[int] = None
        #: Camera -> why its kind of centre was last changed (shown with its pooling).
        self._centre_notes: Dict[str, str] = {}
        #: A changed camera's earlier self in the solve (:meth:`_epoch_cameras`) -> its last
        #: accepted estimate (the next solve's start), -> what it may share with its camera
        #: ('lens' after a move, 'pose' after a lens change), and -> the last test's verdict.
        self._epoch_warm: Dict[str, object] = {}
        self._epoch_share: Dict[str, str] = {}
        self._epoch_until: Dict[Tuple[str, int], int] = {}
        self.epoch_verdicts: Dict[str, str] = {}

    @property
    def target_estimated(self) -> Optional[bool]:
        """
        Return whether the target's place is estimated (None: it has no place to report).

        A board or tag has a pose on its link (given or estimated); a point marker has a place
        only when a kinematic model estimates it (``point_place_guess``).
        """
        if self.settings.board is not None:
            return bool(self.settings.board.estimate_mount)
        return True if self.settings.point_place_guess is not None else None

    # -- inputs --------------------------------------------------------------------------
    def set_image_size(self, camera, width, height):
        """Record a camera's image size (from its images or its CameraInfo)."""
        if camera not in self.settings.camera_names:
            raise ValueError(f'camera {camera!r} is not in camera_names '
                             f'{self.settings.camera_names}')
        with self._lock:
            self.image_sizes[camera] = (int(width), int(height))

    def add_sample(self, sample):
        """
        Add a sample to the store and test it against the current calibration.

        Returns the store's AddResult.  A declared change starts a new epoch at once (the
        changed camera's older observations are retired) and is passed to the
        :meth:`on_change` callbacks.
        """
        with self._lock:
            result = self.store.add(sample)
            event = self.changes.observe(sample)
            record = (self.changes.declare(event, self.store, self._current)
                      if event is not None else None)
        if record is not None:
            for cb in list(self._change_listeners):
                cb(record)
        return result

    def on_change(self, callback):
        """Register ``callback(ChangeRecord)``, called when a change is declared."""
        self._change_listeners.append(callback)

    def withheld(self):
        """Return the cameras whose calibration no longer holds (changed, not yet re-solved)."""
        with self._lock:
            return self.changes.withheld()

    @property
    def published(self) -> Optional[Calibration]:
        """Return the current calibration without the withheld cameras (None if none)."""
        with self._lock:
            cal, gone = self._current, set(self.changes.withheld())
        if cal is None or not gone:
            return cal
        return replace(cal, cameras={k: v for k, v in cal.cameras.items() if k not in gone})

    def reset(self):
        """
        Forget every sample (the current calibration is kept until a new one replaces it).

        The kinds of lit-ball centre are weighed again at the next solve: the views they were
        last weighed on are gone, so waiting for their count to double would keep the choice
        until the new session outgrew the old one.
        """
        with self._lock:
            self.store.clear()
            self._centres_compared_at = None
            self._revision_at_last_solve = -1
            self._samples_at_last_solve = 0
            self._views_at_last_solve = {}

    def on_result(self, callback: Callable[[SolveOutcome], None]):
        """Register ``callback(outcome)``, called from the solving thread after every solve."""
        self._listeners.append(callback)

    @property
    def current(self) -> Optional[Calibration]:
        """Return the latest accepted calibration (or None)."""
        with self._lock:
            return self._current

    @property
    def solving(self):
        """Return True while a background solve runs."""
        return self._worker is not None and self._worker.is_alive()

    # -- deciding and solving ------------------------------------------------------------
    def solve_due(self, now=None):
        """Return (due, reason)."""
        now = self.clock() if now is None else now
        with self._lock:
            n = len(self.store)
            if n < self.settings.min_samples:
                return False, f'{n} of {self.settings.min_samples} samples'
            if now - self._last_solve_start < self.settings.solve_period_s:
                return False, 'solve_period not elapsed'
            if self.store.revision == self._revision_at_last_solve:
                return False, 'no new samples'
            if self._recalibration_ready():
                return True, 'a changed camera has enough new observations'
            new = abs(n - self._samples_at_last_solve)
            if self._current is not None and new < self.settings.min_new_samples and \
                    self.store.revision - self._revision_at_last_solve < \
                    self.settings.min_new_samples:
                return False, (f'{new} new samples '
                               f'(min_new_samples {self.settings.min_new_samples})')
            return True, 'due'

    def solve_if_grown(self, growth=2.0):
        """
        Solve now if the samples have grown by ``growth`` since the last solve (offline use).

        Reading a recording, the samples arrive faster than a live node would solve them; this
        solves at ``min_samples`` and whenever the store, or one camera's views among those
        that had ``min_samples`` of them, has grown by the factor since (and as soon as a
        changed camera has its new observations), so that change detection follows the
        recording in time order as the node would, at a logarithmic number of solves.  A
        camera recalibrated from its first new views is thus solved again as its own views
        double, not only as the whole store does: meanwhile that first recalibration, from one
        part of the workspace, is what its new views elsewhere are tested against.
        Returns the outcome, or None if no solve was due.
        """
        with self._lock:
            n = len(self.store)
            last = self._samples_at_last_solve if self.n_solves else 0
            ready = self._recalibration_ready()
            due = not last or n >= growth * last or ready or self._a_camera_grew(growth)
        if n < self.settings.min_samples or not self.image_sizes or not due:
            return None
        # As in the node: an error in a solve along the way is that solve's failure, not the
        # end of the recording's calibration (the last solve, over everything, decides).
        return self._guarded_solve()

    def _a_camera_grew(self, growth):
        """
        Return True if a camera's views have grown by ``growth`` since the last solve (lock held).

        Only cameras that had ``min_samples`` views then count.  A sample adds at most one
        view per camera, so the views are counted again only once enough samples can have
        come in for the nearest camera to get there (the store's revision counts them).
        """
        before = {c: v for c, v in self._views_at_last_solve.items()
                  if v >= self.settings.min_samples}
        if not before or self.store.revision < self._views_check_at:
            return False
        now = self.store.views_per_camera()
        short = min(growth * v - now.get(c, 0) for c, v in before.items())
        if short <= 0:
            return True
        self._views_check_at = self.store.revision + int(math.ceil(short))
        return False

    def feed(self, samples):
        """Add ``samples`` in time order as a recording is read, solving as they grow."""
        for sample in samples:
            self.add_sample(sample)
            self.solve_if_grown()

    def _recalibration_ready(self):
        """
        Return True if a changed camera has reached its new views (lock held).

        Counted only when the store has changed since the last count: the node asks this on
        every solve check.
        """
        waiting = self.changes.waiting()
        if not waiting:
            return False
        if self._views_counted_at != self.store.revision:
            self._views_counted_at = self.store.revision
            self.changes.count_new(self.store.views_per_camera())
        return any(self.changes.ready(n) for n in waiting)

    def _kinematics(self, arrays, place=None):
        """
        Return the KinematicData of the samples in ``arrays`` (None without joint angles).

        ``place`` (3,) evaluates it for a marker there on the link instead of at the guess
        (a point marker placed by a kinematic model).
        """
        if self.kinematics_fn is None or len(arrays.points) == 0:
            return None
        by_id = {s.id: s for s in self.store.samples}
        qs = [by_id[i].q for i in arrays.sample_ids]
        if any(q is None for q in qs):
            return None
        Q = np.asarray(qs, float)
        return self.kinematics_fn(Q) if place is None else self.kinematics_fn(Q, place)

    def _points_at_place(self, arrays, kin, specs, obs, initial, solver):
        """
        Points, KinematicData and initial cameras of a point marker placed by a kinematic model.

        The samples' points X^_i were computed at the guess m0.  With R_i the marker link's
        rotation (the tip translation's Jacobian columns), the marker at m is exactly
        X_i = X^_i + R_i (m - m0).  The kinematic solve starts at the last accepted place; on a
        first solve the place is first found by the ``fixed`` model with a one-point target
        (:func:`calibrate_board`, which starts the cameras again once the guess proves off):
        cameras started by DLT from points centimetres off can fail outright.  Returns
        (points, kin, place, initial, stage note).
        """
        m0 = np.asarray(self.settings.point_place_guess, float)
        cols = [list(kin.names).index(f'tip/t{a}') for a in 'xyz']
        R = kin.jacobian[:, :, cols]
        with self._lock:
            known = None if self.T_link_target is None else self.T_link_target[:3, 3].copy()
        note = 'place: the last accepted estimate'
        if known is None:
            poses = np.tile(np.eye(4), (len(R), 1, 1))
            poses[:, :3, :3] = R
            poses[:, :3, 3] = arrays.points - R @ m0
            seed = np.eye(4)
            seed[:3, 3] = m0
            data = BoardData(poses, np.zeros((1, 3)), obs.point, obs.camera,
                             np.zeros(len(obs.point), np.int64), obs.uv)
            try:
                first = self._run(calibrate_board, specs, data, PriorSettings('fixed'), solver,
                                  T_link_target=seed, mount=MountSettings(estimate=True),
                                  initial=initial)
            except ValueError:
                first = None
            adj = None if first is None else first.calibration.adjustment
            if adj is None or not first.calibration.success:
                return arrays.points, kin, m0, initial, 'place: the guess (fixed stage failed)'
            known = first.T_link_target[:3, 3]
            initial = {**(initial or {}),
                       **{k: c.camera for k, c in adj.cameras.items()
                          if c.camera is not None and c.status == 'ok'}}
            note = (f'place: fixed stage moved the guess by '
                    f'{1e3 * np.linalg.norm(known - m0):.1f} mm')
        points = arrays.points + R @ (known - m0)
        return points, self._kinematics(arrays, known), known, initial, note

    def _prior_for_solve(self, n_samples):
        """
        Return the prior to solve with, and whether it is a model search.

        With ``auto`` the search (:func:`~armcal_ros.core.model_selection.select_model`, a few
        seconds) runs on the first solve and again whenever the samples have grown by half
        since the last search; in between, background re-solves reuse its choice.
        """
        prior = self.settings.prior
        if prior.model != 'auto':
            return prior, False
        if self._auto_choice is None or n_samples >= 1.5 * self._auto_samples:
            return prior, True
        return self._auto_choice, False

    def _problem(self, epochs=None):
        """
        Return (arrays, specs, cameras without an image size, lit centres) of a solve.

        ``epochs`` (name -> (camera, epoch tag), :meth:`_epoch_cameras`) adds moved cameras'
        earlier selves after the cameras; each takes its camera's image size and choice of
        lit-ball centre.
        """
        epochs = epochs or {}
        names = list(self.settings.camera_names)
        arrays = self.store.arrays(camera_names=names, epochs=epochs,
                                   until_ns=self._epoch_until)
        lit = None
        if self.settings.pool_light_shift:
            fitted = set(self._fitted_centres) | {e for e, (c, _) in epochs.items()
                                                  if c in self._fitted_centres}
            lit = lit_centres(arrays, fitted)
            arrays = lit.arrays
            self.light_pooling = self._labelled({k: v for k, v in lit.pooling.items()
                                                 if k not in epochs})
        specs, missing = [], []
        for name in list(names) + list(epochs):
            size = self.image_sizes.get(epochs[name][0] if name in epochs else name)
            if size is None:
                missing.append(name)
            w, h = size or (0, 0)
            specs.append(CameraSpec(name, w, h))
        return arrays, specs, missing, lit

    def _epoch_cameras(self):
        """
        Return name -> (camera, epoch tag): changed cameras' earlier selves to solve (lock held).

        Each camera declared changed has its observations from before the change retired with
        the new epoch's tag; while at least ``recalibration_samples`` of them lie on samples
        still held (as many views as a changed camera needs to be solved again), they are
        solved as a camera named ``<camera>#<tag>`` once the change has been sized (after the
        first solve that recalibrated the camera): a move (``what == 'pose'``) may share the
        lens, a lens change (``'lens'``) the pose (:attr:`_epoch_share`).  Before the sizing,
        the tests would judge on the camera's first few new views, too few to see a small
        refocus: measured on a lamp-lit cluttered PUMA recording, a 0.5 % refocus
        passed it at the recalibrating solve (focal z -0.56 on 20 new views) and failed it at
        the next, 21 samples later (z -3.02); the calibration accepted in between, one lens
        bent to both epochs, led to a reported disagreement.
        """
        if not self.settings.solve_earlier_epochs or not self.changes.records:
            return {}
        self._epoch_until = self._epoch_limits()
        views = self.store.retired_views(self._epoch_until)
        out, share = {}, {}
        for rec in self.changes.records:
            if rec.kind == 'camera' and rec.what in ('pose', 'lens') and \
                    rec.camera in self.settings.camera_names and \
                    views.get((rec.camera, rec.epoch), 0) >= self.changes.recalibration_samples:
                name = earlier_self(rec.camera, rec.epoch)
                out[name] = (rec.camera, rec.epoch)
                share[name] = 'lens' if rec.what == 'pose' else 'pose'
        self._epoch_share = share
        return out

    def _epoch_limits(self):
        """
        Return (camera, epoch) -> the time before which its retired views are trusted.

        A disagreement reported on a camera's views (nothing retired: no single change
        explained them) before the change later declared on it is most likely that change's
        first sign, found before it could be told apart: measured on a 0.5 % refocus
        (bench/changes.py's ur5-2cam, seed 8) the report's onset was the refocus's to 0.3 s
        and the declared onset 50 s late, 18 views of the new lens among the old.  Retired
        views are all from before the declared onset; those from the report's onset on are
        left out of the earlier self, which has one lens and one pose.

        A report is taken for the change's first sign only while the camera has had at most
        :data:`REPORT_LINK_VIEWS` views between the two onsets: after that many the change
        monitor's scale is made of views after the report alone, and what it declares is
        judged against them - a later change, not the report's (a report on a burst of bad
        detections must not cost an earlier self the hours of views that follow it).
        """
        out, since = {}, {}
        for rec in sorted(self.changes.records, key=lambda r: r.detected_ns):
            if rec.camera is None:
                continue
            if rec.kind in ('unexplained', 'disagreement'):
                since.setdefault(rec.camera, rec.onset_ns)
            elif rec.kind == 'camera':
                first = since.pop(rec.camera, None)
                if first is not None and first < rec.onset_ns and self.store.retired_since(
                        rec.camera, rec.epoch, first) <= REPORT_LINK_VIEWS:
                    out[(rec.camera, rec.epoch)] = first
        return out

    def _epoch_start(self, epochs):
        """Return each earlier self's start: its last estimate, or the camera as it was."""
        out = {}
        for name, (camera, tag) in epochs.items():
            cam = self._epoch_warm.get(name)
            if cam is None:
                cal = self.changes.epoch_calibrations.get(tag - 1)
                if cal is not None and camera in cal.cameras:
                    cam = cal.cameras[camera].camera
            if cam is not None:
                cam = cam.copy()
                cam.name = name
                out[name] = cam
        return out

    def _shared_parts(self, result, epochs, solved):
        """
        Return {earlier self: (camera, 'lens' or 'pose')}: what the solve finds unchanged.

        ``solved`` are the cameras of the solve ``result`` (each earlier self with a lens and
        a pose of its own).  Each earlier self is tested first for the part its change's
        sizing says it left (:attr:`_epoch_share`), then for the other: a small refocus can
        be sized as a move along the axis, and its pose is then what stayed.  The first
        part found unchanged is shared; with neither the earlier self is left out.  Each
        verdict is kept in :attr:`epoch_verdicts`.
        """
        adj = result.adjustment
        if adj is None or not result.success or adj.covariance is None:
            return {}
        tests = {'lens': lens_test, 'pose': pose_test}
        out, notes = {}, {}
        for name, (camera, _) in epochs.items():
            if name not in solved or camera not in solved or \
                    any(adj.cameras[n].status != 'ok' for n in (name, camera)):
                continue
            first = self._epoch_share.get(name, 'lens')
            said = []
            for part in (first, 'pose' if first == 'lens' else 'lens'):
                try:
                    test = tests[part](adj, name, camera)
                except ValueError as exc:
                    said.append(f'{part}: {exc}')
                    continue
                said.append(f'{part}: {test.message}')
                if test.same:
                    out[name] = (camera, part)
                    break
            notes[name] = (f'solved with the {out[name][1]} of {camera}' if name in out else
                           'left out, its lens and its pose changed') + f' ({"; ".join(said)})'
        with self._lock:
            self.epoch_verdicts = notes
        return out

    def problem_inputs(self) -> Optional[ProblemInputs]:
        """
        Return what a point-marker solve of the current samples starts from (None if nothing).

        The cameras with a known image size, the measured points, the observations, the
        arm's Jacobian (None without joint angles) and the pooled-detection image noise: what
        the engine passes to :func:`~armcal_ros.core.calibration.calibrate`, for tools that
        study the adjustment on these data (bench/hyperparameters.py).
        """
        with self._lock:
            arrays, specs, missing, _ = self._problem()
            kin = self._kinematics(arrays)
        keep = [j for j, s in enumerate(specs) if s.name not in missing]
        if not keep or len(arrays.points) == 0:
            return None
        remap = -np.ones(len(specs), np.int64)
        remap[keep] = np.arange(len(keep))
        sel = remap[arrays.camera_index] >= 0
        obs = Observations(remap[arrays.camera_index[sel]], arrays.point_index[sel],
                           arrays.uv[sel])
        return ProblemInputs([specs[j] for j in keep], arrays.points, obs, kin,
                             pooled_pixel_sigma(arrays.spread_px[sel], arrays.n_frames[sel]))

    def solve(self, force=False) -> SolveOutcome:
        """
        Solve now on a snapshot of the samples (synchronously) and maybe accept the result.

        It always solves, due or not (``force`` is accepted for symmetry with
        :meth:`maybe_solve_async`).

        BLAS runs single-threaded here: the solver's matrices are small to medium, and a
        multi-threaded OpenBLAS competing with the node's other threads on a loaded 2-core
        machine made the ``auto`` search 13 x slower (measured: 60 s against 4.7 s).
        """
        with threadpool_limits(limits=1, user_api='blas'):
            return self._solve()

    def _solve(self) -> SolveOutcome:
        if self.settings.board is not None:
            return self._solve_board()
        t0 = time.perf_counter()
        with self._lock:
            self._last_solve_start = self.clock()
            self._forget_old_samples()
            self._revision_at_last_solve = self.store.revision
            epochs = self._epoch_cameras()
            arrays, specs, missing, lit = self._problem(epochs)
            n = len(arrays.points)
            self._samples_at_last_solve = len(self.store)
            self._views_at_last_solve = self.store.views_per_camera()
            self._views_check_at = 0
            initial = ({k: c.camera for k, c in self._current.cameras.items()}
                       if self._current is not None else None)
            if initial is not None:
                initial.update(self._epoch_start(epochs))
            prior, searching = self._prior_for_solve(n)
            kin = self._kinematics(arrays)
            self.changes.count_new(self.store.views_per_camera())
            waiting = set(self.changes.waiting())
            restarted = {k: v for k, v in self.changes.recalibrating.items()
                         if k not in waiting}
        keep = [j for j, s in enumerate(specs) if s.name not in missing and s.name not in waiting]
        # A camera's earlier self is solved only beside the camera: there what it shares is tested.
        kept = {specs[j].name for j in keep}
        keep = [j for j in keep if specs[j].name not in epochs or epochs[specs[j].name][0] in kept]
        if initial is not None:
            initial = self._restart_changed(initial, restarted, arrays)
        if prior.model in KINEMATIC_MODELS and kin is None:
            return self._finish(SolveOutcome(
                False, f'noise_model {prior.model} needs joint angles for every sample (this '
                'engine has no robot model or some samples came without joints)', None, None,
                n, time.perf_counter() - t0))
        if not keep or n == 0:
            reason = ('no samples' if n == 0 else
                      f'image size unknown for {missing}: no image received yet')
            return self._finish(SolveOutcome(False, reason, None, None, n,
                                             time.perf_counter() - t0))
        remap, sel, specs_kept = _kept(specs, keep, arrays)
        result, kw, points, place, note = self._calibrate_once(
            arrays, sel, remap, specs_kept, prior, searching, kin, initial, n)
        if searching:
            self._remember_auto_choice(result, n)
        shared = {}
        if any(s.name in epochs for s in specs_kept):
            # Each earlier self has been solved with a lens and a pose of its own; the solve
            # is repeated with those whose lens (or pose) did not change sharing it, the
            # others left out (with everything its own one brought no consistent gain:
            # docs/BENCHMARKS.md, *changes*).
            shared = self._shared_parts(result, epochs, {s.name for s in specs_kept})
            if searching and self._auto_choice is not None:
                prior, searching = self._auto_choice, False
            warm = {k: c.camera for k, c in result.adjustment.cameras.items()
                    if c.camera is not None and c.status == 'ok'} \
                if result.adjustment is not None else {}
            keep2 = [j for j in keep if specs[j].name not in epochs or specs[j].name in shared]
            remap2, sel2, specs2 = _kept(specs, keep2, arrays)
            again = self._calibrate_once(arrays, sel2, remap2, specs2, prior, False, kin,
                                         {**(initial or {}), **warm}, n, shared)
            if again[0].adjustment is not None and again[0].success:
                result, kw, points, place, note = again
                remap, sel, specs_kept = remap2, sel2, specs2
            else:
                shared = {}
        # With a lamp given the solve's views are corrected ones: no like-for-like other kind.
        if lit is not None and self.settings.marker_light is None:
            chosen = self._choose_centres(result, arrays, lit, sel, remap, specs_kept, kin,
                                          initial, n, shared)
            if chosen is not None:
                arrays, (result, kw, points, place, note) = chosen
        outcome = self._judge(result, n, time.perf_counter() - t0, hidden=epochs)
        if outcome.accepted:
            if epochs:
                outcome.calibration.hyperparameters['earlier_epochs'] = {
                    k: self.epoch_verdicts.get(k, '') for k in epochs if k in self.epoch_verdicts}
                with self._lock:
                    self._epoch_warm = {k: c.camera for k, c in result.adjustment.cameras.items()
                                        if k in epochs and c.status == 'ok'}
                arrays = arrays.without_cameras(epochs)
            self._follow_changes(outcome, arrays, points, kw['kinematics'], place)
        if outcome.accepted and place is not None:
            place = tip_place(result.adjustment, place)
            if place is not None:
                T = np.eye(4)
                T[:3, 3] = place[0]
                with self._lock:
                    self.T_link_target, self.mount_std = T, place[1]
                outcome.calibration.hyperparameters['T_link_target'] = pose_vector(T)
                outcome.calibration.hyperparameters['place_stage'] = note
        return self._finish(outcome)

    def _calibrate_once(self, arrays, sel, remap, specs_kept, prior, searching, kin, initial,
                        n, shared=None):
        """
        Return (result, kw, points, place, note) of one calibration of ``arrays[sel]``.

        ``shared``: {camera: (camera whose lens or pose it shares, 'lens' or 'pose')}
        (SolverSettings.shared_lens, shared_pose).
        """
        obs = Observations(remap[arrays.camera_index[sel]], arrays.point_index[sel],
                           arrays.uv[sel])
        # Every model gets the arm's Jacobian when there is one: the kinematic ones and auto
        # use it, the others need it for an uncertainty reference that is kinematic.
        kw = dict(kinematics=kin)
        if searching or self.settings.solver.estimate_noise:
            kw['pooled_sigma_px'] = pooled_pixel_sigma(arrays.spread_px[sel],
                                                       arrays.n_frames[sel])
        solver = self._solver_settings(searching)
        if shared:
            solver = replace(
                solver, shared_lens={k: c for k, (c, p) in shared.items() if p == 'lens'},
                shared_pose={k: c for k, (c, p) in shared.items() if p == 'pose'})
        points, place, note = arrays.points, None, None
        if self.settings.point_place_guess is not None:
            points, kin, place, initial, note = self._points_at_place(
                arrays, kin, specs_kept, obs, initial, solver)
            kw['kinematics'] = kin
        if self.settings.marker_light is not None:
            obs, initial = self._light_corrected(specs_kept, points, obs, initial, solver, kw)
        if self.settings.prior.model != 'auto':
            kw['reference'] = self._reference_for(specs_kept, points, obs, initial, kin, solver,
                                                  n, arrays, sel)
        result = self._run(calibrate, specs_kept, points, obs, prior, solver, initial=initial,
                           **kw)
        if (result.adjustment is None or not np.all(np.isfinite(result.adjustment.covariance))) \
                and initial is not None:
            # A warm start that failed may have been poisoned: try once from scratch.
            result = self._run(calibrate, specs_kept, points, obs, prior, solver, **kw)
        return result, kw, points, place, note

    def _choose_centres(self, result, arrays, lit, sel, remap, specs_kept, kin, initial, n,
                        shared):
        """
        Return (arrays, calibration) with each camera's better kind of lit-ball centre, or None.

        Every camera with both kinds (a light shift that pools) is solved with its other kind
        too, in one more solve of all of them, and each camera's two kinds are weighed by
        :func:`~armcal_ros.core.light_pooling.compare_solves`: the image noise of each kind
        by its own solve's residuals.  Where only some cameras change kind a third solve is
        made with the choice.  Under ``auto`` these solves are searches, so that each kind is
        weighed at its own image noise, and the search of the kind taken is kept.  None
        where nothing changes (``result`` stands), where it is not due
        (:meth:`_centres_due`) or where the other solve fails.  Neither the shifts nor
        their own noise can tell which kind is the better (core/light_pooling.py); a
        calibration can.  Measured on the simulator's recordings (docs/BENCHMARKS.md): a
        centroid over clutter or under a lamp close by made pooled centres twice as far off
        as the fits, where under even light pooled centres were half as far off as the fits
        in one camera of the same cell.
        """
        adj = result.adjustment
        if adj is None or not result.success or len(adj.inliers) != int(sel.sum()):
            return None
        finite = np.all(np.isfinite(lit.other_uv[sel]), axis=1)
        cam = remap[arrays.camera_index[sel]]
        # A moved camera's earlier self takes its camera's choice (_problem, _switch_centres).
        both = [spec.name for j, spec in enumerate(specs_kept)
                if spec.name in self.settings.camera_names and np.any(finite & (cam == j))]
        views = int(np.sum(finite))
        if not both or not self._centres_due(views):
            return None
        with self._lock:
            self._centres_compared_at = views
        # Under auto each kind is solved at its own image noise, by a search of its own:
        # between searches the chosen model is solved at the noise the last search estimated,
        # the noise of the centres it was made with, and other centres solved at it are
        # weighed wrongly against the arm's prior (fits of 0.06 px at the pooled centres'
        # 0.14 px) - in the comparison and, once taken, in every solve up to the next search.
        prior = self.settings.prior
        search = prior.model == 'auto'
        warm = {**(initial or {}), **{k: c.camera for k, c in adj.cameras.items()
                                      if c.camera is not None and c.status == 'ok'}}
        other = self._switch_centres(arrays, lit, both)
        again = self._calibrate_once(other, sel, remap, specs_kept, prior, search, kin, warm, n,
                                     shared)
        if again[0].adjustment is None or not again[0].success or \
                len(again[0].adjustment.inliers) != int(sel.sum()):
            return None
        switched = {}
        for name in both:
            judged = compare_solves(*self._own_residuals(result, arrays, sel, remap,
                                                         specs_kept, name),
                                    *self._own_residuals(again[0], other, sel, remap,
                                                         specs_kept, name))
            if judged.switch:
                switched[name] = judged
        if not switched:
            return None
        if len(switched) < len(both):
            other = self._switch_centres(arrays, lit, switched)
            again = self._calibrate_once(other, sel, remap, specs_kept, prior, search, kin,
                                         warm, n, shared)
            if again[0].adjustment is None or not again[0].success:
                return None
        if search:
            self._remember_auto_choice(again[0], n)
        self._adopt_centres(switched, lit)
        return other, again

    def _centres_due(self, views):
        """
        Whether the kinds of lit-ball centre are to be weighed at a solve of ``views`` views.

        At the first solve with both kinds, and then each time the views with both have
        doubled: the comparison costs a second solve (a search under auto), and the noise
        estimates it rests on gain a factor sqrt(2) in precision with each doubling.
        """
        with self._lock:
            last = self._centres_compared_at
        return last is None or views >= 2 * last

    @staticmethod
    def _own_residuals(result, arrays, sel, remap, specs_kept, name):
        """Return (residuals (n, 2), redundancy) of camera ``name``'s inlier views in a solve."""
        adj = result.adjustment
        est = adj.cameras.get(name)
        j = [s.name for s in specs_kept].index(name)
        rows = np.flatnonzero((remap[arrays.camera_index[sel]] == j) & adj.inliers)
        if est is None or est.status != 'ok' or not len(rows):
            return np.zeros((0, 2)), float('nan')
        p = est.camera.project(adj.points[arrays.point_index[sel][rows]])
        return arrays.uv[sel][rows] - p, est.redundancy

    def _switch_centres(self, arrays, lit, switched):
        """Return ``arrays`` with the ``switched`` cameras' centres of the other kind."""
        uv, spread = arrays.uv.copy(), arrays.spread_px.copy()
        earlier = [n for n in arrays.camera_names
                   if (of_earlier_self(n) or ('',))[0] in switched]
        for name in list(switched) + earlier:
            c = list(arrays.camera_names).index(name)
            rows = np.flatnonzero((arrays.camera_index == c) &
                                  np.all(np.isfinite(lit.other_uv), axis=1))
            uv[rows], spread[rows] = lit.other_uv[rows], lit.other_spread[rows]
        return replace(arrays, uv=uv, spread_px=spread)

    def _adopt_centres(self, switched, lit):
        """Make the ``switched`` cameras' other kind of centre their choice from now on."""
        with self._lock:
            for name, judged in switched.items():
                how = f'{judged.sigma_other:.3f} px against {judged.sigma_used:.3f} px'
                if name in self._fitted_centres:
                    self._fitted_centres.discard(name)
                    self._centre_notes[name] = (f'the pooled centres fit a calibration '
                                                f'better ({how})')
                else:
                    self._fitted_centres.add(name)
                    self._centre_notes[name] = (f'the fitted centres are used: they fit a '
                                                f'calibration better ({how})')
            self.light_pooling = self._labelled(lit.pooling)

    def _labelled(self, pooling):
        """
        Return ``pooling`` (camera -> PooledShift) as reported: the choice of centre said.

        A camera whose shift pools but whose fitted centres are used has status 'fits_kept'
        (the change test then takes its new views at their fits); the reason of the last
        change of kind follows the pooling's own message.
        """
        out = {}
        for name, p in pooling.items():
            if p.status == 'ok' and name in self._fitted_centres:
                p = replace(p, status='fits_kept')
            note = self._centre_notes.get(name) if p.status in ('ok', 'fits_kept') else None
            out[name] = replace(p, message=f'{p.message}; {note}') if note else p
        return out

    def _light_corrected(self, specs, points, obs, initial, solver, kw):
        """
        Observations with a lit ball's centroid offsets removed; the initial cameras used.

        The offset of each view depends on where the camera stands
        (:func:`~armcal_ros.core.marker_light.image_offsets`): it is computed with the current
        calibration, or, on a first solve, with a first calibration of the uncorrected views
        (a bias of half a pixel moves cameras far less than the offsets' own dependence on
        them needs).
        """
        lamp, ambient, radius = self.settings.marker_light
        cams = dict(initial or {})
        if any(s.name not in cams for s in specs):
            first = self._run(calibrate, specs, points, obs,
                              replace(self.settings.prior, model='fixed'), solver,
                              initial=initial or None,
                              **{k: v for k, v in kw.items() if k == 'pooled_sigma_px'})
            cams.update({k: v for k, v in first.cameras.items() if k not in cams})
        have = [s.name in cams for s in specs]
        sel = np.asarray(have)[obs.camera]
        offsets = np.zeros_like(obs.uv)
        if np.any(sel):
            cam_list = [cams.get(s.name) for s in specs]
            offsets[sel] = image_offsets(cam_list, obs.camera[sel], points[obs.point[sel]],
                                         lamp, ambient, radius)
        return Observations(obs.camera, obs.point, obs.uv - offsets), (cams or None)

    def _forget_old_samples(self):
        """Forget observations older than ``max_sample_age_s`` before the newest (lock held)."""
        age = self.settings.max_sample_age_s
        if age <= 0 or not len(self.store):
            return
        newest = max(o.stamp_ns for smp in self.store.samples
                     for o in smp.observations.values())
        self.store.forget(newest - int(age * 1e9))

    def _restart_changed(self, initial, restarted, arrays):
        """
        Start each changed camera from a PnP of its new observations with its old intrinsics.

        A knocked camera keeps its lens: the pose alone explains its new views, and a PnP
        from the old intrinsics is a far better start than the old pose or a DLT.  If the PnP
        fails (the lens changed too much to explain them), the camera starts from a DLT.
        """
        initial = dict(initial)
        for name, (rec, old, _) in restarted.items():
            initial.pop(name, None)
            if old is None or name not in arrays.camera_names:
                continue
            sel = arrays.camera_index == arrays.camera_names.index(name)
            cam = old.camera
            got = initialise_with_intrinsics(
                name, cam.width, cam.height, arrays.points[arrays.point_index[sel]],
                arrays.uv[sel], IntrinsicsPrior(cam.intrinsics(), cam.dist))
            if got.success:
                initial[name] = got.camera
        return initial

    def _follow_changes(self, outcome, arrays, points, kin=None, place=None):
        """
        After an accepted solve: close recalibrations, rebuild the change monitor.

        ``kin`` is the solve's KinematicData, ``place`` the marker's place on its link it was
        solved at (a point marker placed by a kinematic model; None otherwise).
        """
        cal = outcome.calibration
        adj = outcome.result.adjustment
        with self._lock:
            by_id = {s.id: s.q for s in self.store.samples}
        joints = [by_id.get(i) for i in arrays.sample_ids]
        arm, predictor = 0.0, None
        if adj is not None and adj.points is not None and len(adj.points) == len(points):
            predictor = self._checked_arm_prediction(adj, points, kin, place, arrays, joints)
            arm = (predictor.sigma if predictor is not None
                   else self._unpredicted_arm_sigma(adj, points, kin))
        cal.hyperparameters['arm_sigma_mm'] = 1e3 * arm
        # A solve that left a camera out (its fit degenerate: core.results.calibration_from_result)
        # is published but not tested against: the others were solved beside a camera bent to
        # a few of its views, and a kept camera's old fit is not this adjustment's.  Measured on
        # a textured UR5 recording: the first solve (20 samples) kept one camera of two, and
        # the monitor built from it declared that camera moved at the next part of the
        # workspace (0.6 deg / 58 mm, withheld to the end).  The current monitor stays.
        partial = bool(cal.not_calibrated)
        blocks, joint, rows = {}, None, []
        if not partial and adj is not None and adj.covariance is not None:
            names = list(adj.parameter_names)
            for cam in cal.cameras:
                idx = [i for i, p in enumerate(names) if p.startswith(cam + '/')]
                if idx and np.all(np.isfinite(adj.covariance[np.ix_(idx, idx)])):
                    blocks[cam] = ([names[i][len(cam) + 1:] for i in idx],
                                   adj.covariance[np.ix_(idx, idx)])
                    rows.extend((i, cam) for i in idx)
            idx = [i for i, _ in rows]
            C = adj.covariance[np.ix_(idx, idx)]
            labels = [(cam, names[i][len(cam) + 1:]) for i, cam in rows]
            if predictor is not None and adj.global_cross_covariance is not None:
                # The arm's model's parameters beside the cameras': relative to the cameras
                # the arm is known far better than on its own (ArmPrediction).
                X = adj.global_cross_covariance[idx][:, predictor.slice]
                C = np.block([[C, X], [X.T, adj.global_covariance[predictor.slice,
                                                                  predictor.slice]]])
                labels += [(ARM, f'g{k}') for k in range(X.shape[1])]
            if rows and np.all(np.isfinite(C)):
                joint = (labels, C)
        with self._lock:
            jobs = self.changes.accepted(cal)
        sized = self.changes.size(jobs, arrays, joints)
        monitor = None if partial else self.changes.build_monitor(cal, arrays, arm, blocks,
                                                                  joint, predictor)
        with self._lock:
            self.changes.apply_sizes(sized)
            self.changes.light_shifts = dict(self.light_pooling)
            if not partial:
                self.changes.adopt(monitor)

    def _unpredicted_arm_sigma(self, adj, points, kin):
        """
        Return the arm's error per axis at a new view tested at its measured point (m).

        The largest of: the adjustment's corrections at its own points (RMS per axis); what
        the solved model's prior gives a point less a rigid motion
        (:meth:`~armcal_ros.core.priors.PointPrior.relative_sigma`); and, with joint angles,
        what the kinematic prior's stated tolerances (scale 1) give the same way - the arm's
        accuracy before any calibration of it.  The corrections are posterior means, shrunk
        towards zero, and a model chosen on a first few samples in one part of the workspace
        may claim a far smaller error than the arm has elsewhere: on a lamp-lit textured UR5
        recording the first monitor (20 samples, ``independent``, 0.2 mm) took 0.27 mm where
        the kinematic tolerances say 1.35 mm, and declared the arm changed at the next part of
        the workspace (docs/BENCHMARKS.md *realism-effects*).  Until a kinematic prediction has
        shown how it predicts ahead (:meth:`_checked_arm_prediction`) nothing knows better.
        """
        arm = float(np.sqrt(np.mean(np.sum((adj.points - points) ** 2, axis=1)) / 3.0))
        if adj.prior is not None:
            arm = max(arm, adj.prior.relative_sigma())
        if kin is not None and len(points) and kin.n == len(points):
            tolerances = PointPrior(points, replace(self.settings.prior, model='kinematic',
                                                    kinematic_scale=1.0), kinematics=kin)
            arm = max(arm, tolerances.relative_sigma())
        return arm

    def _checked_arm_prediction(self, adj, points, kin, place, arrays, joints):
        """
        Return this solve's ArmPrediction, its error no smaller than the last one's was ahead.

        A model's residual at its own samples says little of its error at places it was not
        fitted to (a kinematic model of 48 parameters on 20 samples fits them to 0.03 mm and
        predicted the next views of a lamp-lit UR5 recording several times worse).  Each
        accepted solve measures the previous prediction at the samples added since
        (:meth:`~armcal_ros.change_tracking.ArmPrediction.forward_error`), and the new
        prediction's error is at least that: the arm is predicted no better than the model has
        shown it predicts.  The first solve's prediction, never checked, is not used.
        ``joints``: the joint angles of each of ``arrays``' samples (None where unknown).
        """
        predictor = self._arm_prediction(adj, points, kin, place)
        previous, fitted = self._arm_checked
        ids = np.asarray(arrays.sample_ids)
        if predictor is not None:
            self._arm_checked = (predictor, set(int(i) for i in ids))
        if previous is None:
            self._arm_forward = float('nan')
        else:
            new = np.array([int(i) not in fitted for i in ids])
            got = previous.forward_error(arrays.points, joints, adj.points, new)
            if np.isfinite(got):
                self._arm_forward = got
        if predictor is None or not np.isfinite(self._arm_forward):
            return None
        predictor.sigma = max(predictor.sigma, self._arm_forward)
        return predictor

    def _arm_prediction(self, adj, points, kin, place):
        """Return the :class:`ArmPrediction` of an accepted adjustment (None if it cannot)."""
        kinematics, shift = self.kinematics_fn, None
        if place is not None and kinematics is not None:
            m0 = np.asarray(self.settings.point_place_guess, float)
            known = np.asarray(place, float)
            kinematics = (lambda Q, f=self.kinematics_fn, p=known: f(Q, p))
            names = list(kin.names) if kin is not None else []
            if not all(f'tip/t{a}' in names for a in 'xyz'):
                return None
            cols = [names.index(f'tip/t{a}') for a in 'xyz']
            shift = (lambda jac, c=cols, d=known - m0: jac[:, :, c] @ d)
        try:
            return ArmPrediction(adj, points, kin, kinematics, shift)
        except ValueError:
            return None

    def _reference_for(self, specs, points, obs, initial, kin, solver, n, arrays, sel):
        """
        Return the prior that describes the arm's errors on these data (``auto``'s choice).

        A single model's covariance is widened by what the errors it does not describe do to
        its cameras (:func:`~armcal_ros.core.calibration.calibrate`, ``reference``); which
        errors the data show is what the ``auto`` search finds.  It runs on the first solve
        and again whenever the samples have grown by half, as ``auto`` itself does; in
        between the last choice serves.  None if the search fails.
        """
        with self._lock:
            ref, at = self._reference, self._reference_samples
        if ref is not None and n < 1.5 * at:
            return ref
        pooled = pooled_pixel_sigma(arrays.spread_px[sel], arrays.n_frames[sel])
        search = self._run(calibrate, specs, points, obs,
                           replace(self.settings.prior, model='auto'), solver, initial=initial,
                           kinematics=kin, pooled_sigma_px=pooled)
        if search.selection is None or not search.success:
            return ref
        with self._lock:
            self._reference, self._reference_samples = search.selection.settings, n
        return search.selection.settings

    def _solver_settings(self, searching):
        """Between auto's searches, solve the chosen model with the image noise it estimated."""
        solver = self.settings.solver
        if not searching and self.settings.prior.model == 'auto' and self._auto_pixel_sigma:
            solver = replace(solver, pixel_sigma=self._auto_pixel_sigma, estimate_noise=False)
        return solver

    def _remember_auto_choice(self, result, n):
        """After an auto search: keep its choice, sample count, image noise and reason."""
        if result.selection is None:
            return
        with self._lock:
            self._auto_choice = result.selection.settings
            self._auto_samples = n
            self._auto_pixel_sigma = result.selection.pixel_sigma
            self.auto_reason = result.selection.reason

    def _board_problem(self, samples, specs):
        """Return the BoardData of ``samples`` over the cameras ``specs`` (index = position)."""
        board = self.settings.board
        n_points = len(board.points)
        cam_index = {s.name: j for j, s in enumerate(specs)}
        view, cam, corner, uv = [], [], [], []
        for v, smp in enumerate(samples):
            for name, o in smp.observations.items():
                c = cam_index.get(name)
                ok = (o.ids >= 0) & (o.ids < n_points)
                if c is None or not ok.any():
                    continue
                k = int(np.count_nonzero(ok))
                view.append(np.full(k, v))
                cam.append(np.full(k, c))
                corner.append(o.ids[ok])
                uv.append(o.uv[ok])

        def cat(parts, shape=(0,)):
            return np.concatenate(parts) if parts else np.zeros(shape)
        poses = np.array([smp.pose for smp in samples]).reshape(-1, 4, 4)
        if self.settings.eye_in_hand:
            poses = invert(poses)
        return BoardData(poses, board.points, cat(view), cat(cam), cat(corner), cat(uv, (0, 2)))

    def _solve_board(self) -> SolveOutcome:
        """One solve of board views (:func:`calibrate_board`), estimating the mount if asked."""
        t0 = time.perf_counter()
        board = self.settings.board
        with self._lock:
            self._last_solve_start = self.clock()
            self._revision_at_last_solve = self.store.revision
            samples = sorted(self.store.samples, key=lambda smp: smp.id)
            n = len(samples)
            self._samples_at_last_solve = n
            initial = ({k: c.camera for k, c in self._current.cameras.items()}
                       if self._current is not None else None)
            prior, searching = self._prior_for_solve(n)
            seed = None if self.T_link_target is None else self.T_link_target.copy()
            scale = self.target_scale
            sizes = dict(self.image_sizes)

        def refuse(reason):
            return self._finish(SolveOutcome(False, reason, None, None, n,
                                             time.perf_counter() - t0))
        if prior.model in KINEMATIC_MODELS:
            return refuse(f'noise_model {prior.model} is not available with a board target; '
                          'use fixed, independent, correlated or auto')
        if n == 0:
            return refuse('no samples')
        if any(smp.pose is None for smp in samples):
            return refuse('board samples need the link pose (pose input or joint angles)')
        names = list(self.settings.camera_names)
        missing = [c for c in names if c not in sizes]
        specs = [CameraSpec(c, *sizes[c]) for c in names if c in sizes]
        if not specs:
            return refuse(f'image size unknown for {missing}: no image received yet')
        data = self._board_problem(samples, specs)
        if not len(data):
            return refuse('no board corners in the samples')
        solver = self._solver_settings(searching)
        try:
            res = self._run(calibrate_board, specs, data, prior, solver, T_link_target=seed,
                            mount=MountSettings(estimate=board.estimate_mount,
                                                estimate_scale=board.estimate_scale),
                            initial=initial, scale=scale)
        except ValueError as exc:
            return refuse(f'board solve failed: {exc}')
        result = res.calibration
        if searching:
            self._remember_auto_choice(result, n)
        outcome = self._judge(result, n, time.perf_counter() - t0,
                              model=None if prior.model == 'auto' else res.model)
        if outcome.accepted:
            with self._lock:
                self.T_link_target = np.array(res.T_link_target, float)
                self.mount_std = None if res.mount_std is None else np.array(res.mount_std)
                self.target_scale = float(res.scale)
            outcome.calibration.hyperparameters['T_link_target'] = pose_vector(
                res.T_link_target)
            if board.estimate_scale:
                outcome.calibration.hyperparameters['target_scale'] = float(res.scale)
        return self._finish(outcome)

    def _judge(self, result, n, elapsed, model=None, hidden=()):
        if result.adjustment is None or not result.success:
            return SolveOutcome(False, f'solve failed: {result.message}', result, None, n, elapsed)
        used = (result.selection.settings if result.selection is not None
                else self._auto_choice if self.settings.prior.model == 'auto'
                else self.settings.prior)
        hyper = dict(model=used.model, point_sigma=used.point_sigma, bias_sigma=used.bias_sigma,
                     coherence_length=used.coherence_length,
                     kinematic_scale=getattr(used, 'kinematic_scale', 1.0),
                     pixel_sigma=(result.pixel_sigma if np.isfinite(result.pixel_sigma)
                                  else self.settings.solver.pixel_sigma),
                     pixel_sigma_source=(result.noise_source if np.isfinite(result.pixel_sigma)
                                         else 'given'),
                     uncertainty=getattr(result, 'uncertainty', 'model'))
        if self.settings.prior.model == 'auto' and not result.selection and \
                self._auto_pixel_sigma:
            hyper['pixel_sigma_source'] = 'free network (the last search)'
        if self.settings.prior.model == 'auto':
            hyper['auto_reason'] = self.auto_reason
        new = calibration_from_result(result, n, hyper, hidden)
        if model:
            new.model = model      # e.g. 'correlated+mount': the board solver's own name
        with self._lock:
            old = self._current
        if not new.cameras:
            return SolveOutcome(False, 'rejected: no camera\'s fit is a calibration (' + '; '.join(
                f'{k}: {v}' for k, v in new.not_calibrated.items()) + ')', result, new, n,
                elapsed)
        # A degenerate camera is left out: it keeps its previous calibration (below), or has
        # none yet; the others' are accepted.
        unusable = ''.join(f'; {k} not calibrated: {v}' for k, v in new.not_calibrated.items())
        if old is not None:
            s = self.settings
            with self._lock:
                changed = set(self.changes.recalibrating)
                disputed = self.settings.detect_changes and self.changes.disputed()
            for name, c in new.cameras.items():
                if name not in old.cameras or name in changed:
                    # A changed camera's old fit is another epoch's: no yardstick.
                    continue
                o = old.cameras[name]
                worse = _residuals_worse(o, c, s.reject_rms_ratio, s.reject_rms_margin_px,
                                         disputed)
                if worse:
                    return SolveOutcome(False, f'rejected: {name} {worse}', result, new, n,
                                        elapsed)
                fo = inlier_rate(o.n_inliers, o.n_observations)
                fn = inlier_rate(c.n_inliers, c.n_observations)
                if inlier_fall_is_clear((o.n_inliers, o.n_observations),
                                        (c.n_inliers, c.n_observations), s.reject_inlier_drop):
                    return SolveOutcome(False, f'rejected: {name} inlier fraction fell from '
                                        f'{o.n_inliers}/{o.n_observations} to '
                                        f'{c.n_inliers}/{c.n_observations} (rates {fo:.2f}, '
                                        f'{fn:.2f})', result, new, n, elapsed)
            dropped = [k for k in old.cameras if k not in new.cameras and k not in changed]
            if dropped:
                for k in dropped:
                    new.cameras[k] = old.cameras[k]
        return SolveOutcome(True, result.message + unusable, result, new, n, elapsed)

    def _finish(self, outcome: SolveOutcome):
        with self._lock:
            self.n_solves += 1
            if outcome.accepted:
                self._current = outcome.calibration
            elif outcome.result is not None:
                self.n_rejected += 1
            self.last_outcome = outcome
        for cb in list(self._listeners):
            cb(outcome)
        return outcome

    def _run(self, fn, *args, **kwargs):
        """One adjustment (``calibrate`` or ``calibrate_board``), where :attr:`run_solver` says."""
        if self.run_solver is None:
            return fn(*args, **kwargs)
        return self.run_solver(fn, *args, **kwargs)

    def _solve_in_background(self):
        """
        Run :meth:`solve` on the solver thread; an unexpected error ends as a failed outcome.

        Without this an error (or a solver process that died) would end the thread with a
        traceback on stderr and no outcome: the node would go on as if no solve had been due.
        """
        self._guarded_solve()

    def _guarded_solve(self) -> SolveOutcome:
        """Return :meth:`solve`'s outcome, or a failed one saying what an unexpected error was."""
        t0 = time.perf_counter()
        try:
            return self.solve()
        except Exception as exc:  # noqa: B902 - whatever it is, it must be reported
            return self._finish(SolveOutcome(
                False, f'solve failed: {type(exc).__name__}: {exc}', None, None,
                len(self.store), time.perf_counter() - t0))

    def maybe_solve_async(self, force=False):
        """Start a background solve if one is due (or ``force``); return True if started."""
        with self._lock:
            if self.solving:
                return False
            if not force and not self.solve_due()[0]:
                return False
            self._worker = threading.Thread(target=self._solve_in_background, name='armcal-solver',
                                            daemon=True)
            self._worker.start()
            return True

    def frame_id(self, camera) -> str:
        """Return ``camera``'s optical frame: its images' frame_id, else <camera>_optical_frame."""
        return self.frame_ids.get(camera) or f'{camera}_optical_frame'

    def wait(self, timeout=None):
        """Wait for a running background solve; return True if none is running afterwards."""
        w = self._worker
        if w is not None:
            w.join(timeout)
        return not self.solving

    # -- persistence ---------------------------------------------------------------------
    def save(self, directory):
        """
        Write samples and the current calibration to ``directory``.

        Files: samples (the store's format, retired observations included), ``<camera>.yaml``
        and ``extrinsics.yaml`` for the calibrated cameras (not those withheld after a change),
        ``calibration.json`` with the quality figures, ``changes.json`` with the declared
        changes and ``lit_centres.json`` with each camera's kind of lit-ball centre (a restart
        keeps the choice rather than solving twice to make it again); a withheld camera's
        earlier ``<camera>.yaml`` is renamed ``<camera>.before_change.yaml``.  Each file is
        written atomically.  Returns the list of files written.
        """
        os.makedirs(directory, exist_ok=True)
        with self._lock:
            written = [self.store.save(directory), self.changes.save(directory)]
            gone = self.changes.withheld()
            centres = dict(fitted=sorted(self._fitted_centres), notes=dict(self._centre_notes),
                           compared_at_views=self._centres_compared_at)
        path = os.path.join(directory, CENTRES_FILE)
        atomic_write_text(path, json.dumps(centres, indent=1))
        written.append(path)
        cal = self.published
        if cal is not None:
            written += write_calibration(directory, cal, self.settings.base_frame,
                                         dict(self.frame_ids))
        for name in gone:
            # A driver's camera_info_manager would load the old file as if it still held.
            old = os.path.join(directory, f'{name}.yaml')
            if os.path.exists(old):
                os.replace(old, os.path.join(directory, f'{name}.before_change.yaml'))
        with self._lock:
            T, std, scale = self.T_link_target, self.mount_std, self.target_scale
        if self.target_estimated is not None and T is not None and cal is not None:
            written.append(write_target(directory, T, std, self.settings.marker_link,
                                        self.target_estimated, scale))
        return [str(w) for w in written if w]

    def load(self, directory):
        """
        Resume from ``directory``: samples and the last calibration, when present.

        Returns a message saying what was restored.  Files that do not exist are not an error
        (a first start); files that exist but cannot be read raise ValueError naming them.
        """
        said = []
        store_file = os.path.join(directory, 'samples.npz')
        if os.path.exists(store_file):
            store = SampleStore.load(directory, joint_names=self.store.joint_names,
                                     max_samples=self.store.max_samples,
                                     min_sample_spacing=self.store.min_sample_spacing)
            board = self.settings.board is not None
            wrong = [smp.id for smp in store.samples
                     if (smp.pose is None or smp.reference_points is None) == board]
            if wrong:
                raise ValueError(f'{store_file}: {len(wrong)} saved samples are '
                                 f'{"point" if board else "board"} samples, but the target '
                                 f'is a {"board" if board else "point"} (marker_type changed?)')
            with self._lock:
                self.store = store
            said.append(f'{len(store)} samples')
        cal_file = os.path.join(directory, CALIBRATION_FILE)
        if os.path.exists(cal_file):
            cal = load_calibration(directory)
            _, poses = read_extrinsics(os.path.join(directory, 'extrinsics.yaml'))
            with self._lock:
                for name, (_, _, frame) in poses.items():
                    self.frame_ids.setdefault(name, frame)
                self._current = cal
                for name, c in cal.cameras.items():
                    if name in self.settings.camera_names:
                        self.image_sizes.setdefault(name, (c.camera.width, c.camera.height))
                if cal.n_samples == len(self.store):
                    # Solved on exactly these samples: a restart need not solve them again.
                    self._revision_at_last_solve = self.store.revision
                    self._samples_at_last_solve = len(self.store)
                    self._views_at_last_solve = self.store.views_per_camera()
            said.append(f'calibration of {sorted(cal.cameras)} ({cal.model}, '
                        f'{cal.n_samples} samples)')
        if os.path.exists(os.path.join(directory, CHANGES_FILE)):
            with self._lock:
                n = self.changes.load(directory, self._current)
            if n:
                said.append(f'{n} declared change(s)')
        centres_file = os.path.join(directory, CENTRES_FILE)
        if os.path.exists(centres_file):
            try:
                with open(centres_file, encoding='utf-8') as f:
                    doc = json.load(f)
                fitted = {str(n) for n in doc['fitted']}
                notes = {str(k): str(v) for k, v in doc.get('notes', {}).items()}
                at = doc.get('compared_at_views')
                at = None if at is None else int(at)
            except (ValueError, KeyError, TypeError, AttributeError) as exc:
                raise ValueError(f'{centres_file}: not a file of lit-ball centres ({exc})') \
                    from exc
            known = set(self.settings.camera_names)
            with self._lock:
                self._fitted_centres = fitted & known
                self._centre_notes = {k: v for k, v in notes.items() if k in known}
                self._centres_compared_at = at
            if self._fitted_centres:
                said.append(f'fitted centres for {sorted(self._fitted_centres)}')
        target_file = os.path.join(directory, TARGET_FILE)
        board = self.settings.board
        if self.target_estimated and os.path.exists(target_file):
            T = read_target_yaml(target_file)
            scale = (read_target_scale(target_file)
                     if board is not None and board.estimate_scale else 1.0)
            with self._lock:
                self.T_link_target = T
                self.target_scale = scale
            said.append('the target\'s place')
        return 'restored ' + ' and '.join(said) if said else 'nothing to restore'
