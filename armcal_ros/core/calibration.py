"""
The whole estimator: initialise every camera, adjust with ``fixed``, then with the chosen model.

The sequence: DLT + RANSAC per camera (no hand-given guess; PnP for a camera whose intrinsics are
given in ``SolverSettings.intrinsics``), a ``fixed``-model adjustment (points held at the robot's
measurements) to bring in distortion, then the chosen noise model warm-started from it.  Cameras
that cannot be initialised (too few or degenerate points) are reported and left out; the others
are still calibrated.
"""

import time
from dataclasses import dataclass, field, replace
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from armcal_ros.core.adjustment import (AdjustmentResult, covariance_under, Observations,
                                        SolverSettings, adjust, with_covariance)
from armcal_ros.core.camera import Camera
from armcal_ros.core.initialisation import (initialise_camera, initialise_with_intrinsics,
                                            InitResult, MIN_POINTS_PNP)
from armcal_ros.core.model_selection import ModelSelection, select_model
from armcal_ros.core.priors import KINEMATIC_MODELS, PointPrior, PriorSettings

#: Initial LM damping of the stage after ``fixed`` (see :func:`calibrate`).
WARM_LAMBDA = 1e-6
#: Re-weighting rounds of the image-noise estimate, and the relative change that ends them
#: (2 %: the estimate's own sampling error over a few hundred observations is larger).
NOISE_ROUNDS = 4
NOISE_TOLERANCE = 0.02


@dataclass
class CameraSpec:
    """A camera to calibrate: its name and image size in pixels."""

    name: str
    width: int
    height: int


@dataclass
class CalibrationResult:
    """
    Result of :func:`calibrate`.

    ``adjustment`` is the final adjustment over the cameras that could be initialised (None if
    none could); ``init`` says per camera how initialisation went; ``stages`` lists
    (model, cost, iterations, seconds) of each adjustment run.
    """

    success: bool
    status: str
    message: str
    adjustment: Optional[AdjustmentResult]
    init: Dict[str, InitResult] = field(default_factory=dict)
    stages: List[Tuple[str, float, int, float]] = field(default_factory=list)
    time_s: float = 0.0
    camera_index: Dict[str, int] = field(default_factory=dict)
    selection: Optional[ModelSelection] = None      # the choice of 'auto'
    #: The image noise (px per axis) the final adjustment was weighted with, and its source:
    #: 'given' (pixel_sigma), 'residuals' (the model's own variance factor), 'free network'
    #: or 'pooled detections' (:mod:`armcal_ros.core.image_noise`).
    pixel_sigma: float = float('nan')
    noise_source: str = 'given'
    #: How the camera covariance was obtained: 'model' (the adjustment's own, S^-1) or
    #: 'widened under <reference model>' (:func:`~armcal_ros.core.adjustment.covariance_under`).
    uncertainty: str = 'model'

    @property
    def cameras(self):
        """Estimated cameras by name (only those that were solved)."""
        if self.adjustment is None:
            return {}
        return {k: v.camera for k, v in self.adjustment.cameras.items()}


def calibrate(specs: Sequence[CameraSpec], measured, obs: Observations,
              prior: PriorSettings = None, settings: SolverSettings = None,
              initial: Optional[Dict[str, Camera]] = None, rng=None,
              kinematics=None, globals_init=None, points_init=None,
              pooled_sigma_px=None, reference: Optional[PriorSettings] = None
              ) -> CalibrationResult:
    """
    Calibrate the cameras ``specs`` from robot points ``measured`` (N, 3) and observations.

    ``initial`` maps camera names to warm-start estimates (a previous calibration); cameras
    without one are initialised by DLT.  With a warm start the ``fixed`` stage is skipped.
    ``kinematics`` (:class:`~armcal_ros.core.kinematic_prior.KinematicData`, from joint
    angles) enables the 'kinematic' and 'hybrid' models; ``globals_init`` warm-starts their
    global parameters and ``points_init`` (N, 3) the points (with a warm start, the previous
    adjusted points - new ones at their prediction - save most of the iterations).  With
    ``prior.model == 'auto'`` the model and its hyperparameters are chosen by
    :func:`~armcal_ros.core.model_selection.select_model` after the ``fixed`` stage
    (``result.selection`` says what was chosen and why); ``pooled_sigma_px`` is its image
    noise where the free network cannot estimate one
    (:func:`~armcal_ros.core.image_noise.pooled_pixel_sigma`).  ``reference`` (a prior that
    describes the arm's errors, normally ``auto``'s choice on the same data) widens a single
    model's camera covariance by what the errors it does not describe do to its cameras
    (:func:`~armcal_ros.core.adjustment.covariance_under`; docs/NOISE_MODELS.md, "Honest
    uncertainty").
    """
    t0 = time.perf_counter()
    prior = (prior or PriorSettings()).validate()
    settings = (settings or SolverSettings()).validate()
    if prior.model in KINEMATIC_MODELS and kinematics is None:
        raise ValueError(f'noise_model {prior.model!r} needs joint angles (kinematics); '
                         'use correlated or auto with pose input')
    measured = np.asarray(measured, float)
    rng = rng if rng is not None else np.random.default_rng(0)
    initial = initial or {}
    init: Dict[str, InitResult] = {}
    cams: List[Camera] = []
    keep: List[int] = []
    for j, spec in enumerate(specs):
        sel = obs.camera == j
        given = settings.intrinsics.get(spec.name)
        if spec.name in initial:
            cam = initial[spec.name].copy()
            if given is not None and given.mode == 'fixed':
                cam = given.apply(cam)
            init[spec.name] = InitResult(True, 'warm_start', f'camera {spec.name}: warm start',
                                         cam)
        elif given is not None and given.size_mismatch(spec.width, spec.height):
            init[spec.name] = InitResult(False, 'size_mismatch', f'camera {spec.name}: '
                                         + given.size_mismatch(spec.width, spec.height))
            continue
        elif given is not None:
            res = initialise_with_intrinsics(spec.name, spec.width, spec.height,
                                             measured[obs.point[sel]], obs.uv[sel], given)
            init[spec.name] = res
            if not res.success:
                continue
            cam = res.camera
        else:
            res = initialise_camera(spec.name, spec.width, spec.height,
                                    measured[obs.point[sel]], obs.uv[sel], rng=rng)
            init[spec.name] = res
            if not res.success:
                continue
            cam = res.camera
        cams.append(cam)
        keep.append(j)
    if not cams:
        msgs = '; '.join(r.message for r in init.values())
        return CalibrationResult(False, 'no_camera', f'no camera could be initialised: {msgs}',
                                 None, init, [], time.perf_counter() - t0)
    sub = _observations_of(obs, len(specs), keep)
    stages = []
    points = None if points_init is None else np.asarray(points_init, float)
    inliers = None
    cold = [specs[j].name for j in keep if specs[j].name not in initial]
    # The model stage starts next to its optimum (from the fixed solution or a previous
    # calibration): start it almost Gauss-Newton.  With the Marquardt default of 1e-3 the
    # nearly redundant kinematic parameters crawl (10 iterations instead of 4, measured).
    model_settings = replace(settings, initial_lambda=min(settings.initial_lambda, WARM_LAMBDA))
    selection = None
    if cold or prior.model in ('fixed', 'auto'):
        fixed = adjust(cams, measured, sub, replace(prior, model='fixed'), settings)
        stages.append(('fixed', fixed.cost, fixed.iterations, fixed.time_s))
        few = _too_few_inliers(fixed, sub)
        if few and len(few) < len(keep):
            # A camera whose fixed fit keeps too few of its views to fix its pose (a start that
            # fell into a wrong minimum, views of something else) would leave the later stages
            # singular - every model's evidence undefined - and the other cameras with it.
            for k, (m, n) in few.items():
                init[specs[keep[k]].name] = InitResult(
                    False, 'too_few_inliers', f'camera {specs[keep[k]].name}: only {m} of its '
                    f'{n} observations fit its fixed-model solution (fewer than '
                    f'{MIN_POINTS_PNP}): left out')
            stay = [k for k in range(len(keep)) if k not in few]
            keep = [keep[k] for k in stay]
            sub = _observations_of(obs, len(specs), keep)
            fixed = adjust([cams[k] for k in stay], measured, sub, replace(prior, model='fixed'),
                           settings)
            stages.append(('fixed', fixed.cost, fixed.iterations, fixed.time_s))
        cams = fixed.camera_list()
        inliers = fixed.inliers
        final = fixed
    sigma, source = settings.pixel_sigma, 'given'
    if prior.model == 'auto':
        try:
            selection = select_model(cams, measured, sub, prior, model_settings, kinematics,
                                     inliers, rng=rng, pooled_sigma_px=pooled_sigma_px,
                                     estimate_noise=settings.estimate_noise is not False)
        except ValueError as exc:       # no candidate could be adjusted: a failed solve
            return CalibrationResult(False, 'failed', f'auto: {exc}', None, init, stages,
                                     time.perf_counter() - t0)
        final = selection.result
        stages.append((f'auto:{selection.settings.model}', final.cost, final.iterations,
                       selection.time_s))
        sigma = selection.pixel_sigma
        if selection.noise is not None and selection.noise.success:
            source = 'free network'
        elif sigma != settings.pixel_sigma:
            source = 'pooled detections'
    else:
        kin = kinematics if prior.model in KINEMATIC_MODELS else None
        if prior.model != 'fixed':
            final = adjust(cams, measured, sub, prior, model_settings, points_init=points,
                           inliers=inliers, kinematics=kin, globals_init=globals_init)
            stages.append((prior.model, final.cost, final.iterations, final.time_s))
        if settings.estimate_noise:
            final, sigma, source = _reweighted(final, measured, sub, prior, model_settings,
                                               kin, pooled_sigma_px, stages)
    uncertainty = 'model'
    if reference is not None and prior.model != 'auto' and final.status != 'failed' and \
            reference != prior and (reference.model not in KINEMATIC_MODELS or
                                    kinematics is not None):
        ref = PointPrior(measured, reference,
                         kinematics if reference.model in KINEMATIC_MODELS else None)
        cov = covariance_under(final, measured, sub, replace(model_settings, pixel_sigma=sigma),
                               ref)
        final = with_covariance(final, cov)
        uncertainty = f'widened under {reference.model}'
    failed = [r.message for r in init.values() if not r.success]
    msg = final.message if not failed else final.message + '; skipped: ' + '; '.join(failed)
    status = final.status if not failed else 'partial'
    if selection is not None:
        msg = selection.reason + '; ' + msg
    return CalibrationResult(final.success, status, msg, final, init, stages,
                             time.perf_counter() - t0,
                             {specs[j].name: k for k, j in enumerate(keep)}, selection,
                             float(sigma), source, uncertainty)


def _observations_of(obs: Observations, n_specs: int, keep: List[int]) -> Observations:
    """Return the observations of the cameras ``keep`` (spec indices), renumbered 0..len-1."""
    remap = -np.ones(n_specs, dtype=np.int64)
    remap[keep] = np.arange(len(keep))
    sel = remap[obs.camera] >= 0
    return Observations(remap[obs.camera[sel]], obs.point[sel], obs.uv[sel])


def _too_few_inliers(result: AdjustmentResult, obs: Observations) -> Dict[int, Tuple[int, int]]:
    """
    Return {camera index: (inliers, observations)} of the cameras with under MIN_POINTS_PNP.

    Six points are the fewest that fix a camera's pose with its intrinsics known
    (:mod:`~armcal_ros.core.initialisation`); with fewer inliers its parameters are
    unobservable.
    """
    few = {}
    inliers = np.asarray(result.inliers, bool)
    for k in np.unique(obs.camera):
        sel = obs.camera == k
        m = int(np.sum(inliers[sel]))
        if m < MIN_POINTS_PNP:
            few[int(k)] = (m, int(np.sum(sel)))
    return few


def variance_factor_sigma(result: AdjustmentResult) -> float:
    """
    Image noise (px per axis) from an adjustment's residuals: sqrt(sum_j SSR_j / sum_j r_j).

    r_j is camera j's redundancy by leverage and SSR_j = sigma_j^2 r_j its weighted sum of
    squared residuals (:class:`~armcal_ros.core.adjustment.CameraEstimate`); NaN when no
    camera has redundancy.
    """
    ssr = red = 0.0
    for e in result.cameras.values():
        if np.isfinite(e.sigma_px) and np.isfinite(e.redundancy) and e.redundancy > 0:
            ssr += e.sigma_px ** 2 * e.redundancy
            red += e.redundancy
    return float(np.sqrt(ssr / red)) if red > 0 else float('nan')


def _reweighted(final, measured, obs, prior, settings, kin, pooled_sigma_px, stages):
    """
    Re-solve at the image noise the model's own residuals give, until it settles.

    The variance factor of the adjustment, s^2 = sum |r|^2 / r with the redundancy r counted
    by leverage (what each camera's parameters, the points under their prior and the global
    parameters take), estimates the image noise the images were weighted with; the weighting
    changes how much the prior pulls, so the estimate is iterated (variance component
    estimation, Foerstner 1979).  With one camera seeing the marker, its residuals cannot
    separate image noise from the points' freedom: the scatter of the pooled detections
    (``pooled_sigma_px``) is used instead when there is one.  Returns (result, sigma,
    source).
    """
    sigma, source = settings.pixel_sigma, 'given'
    seeing = [e for e in final.cameras.values() if e.n_inliers]
    one = len(seeing) == 1 and prior.model != 'fixed'
    for _ in range(NOISE_ROUNDS):
        if final.status == 'failed':
            break
        if one and pooled_sigma_px is not None and np.isfinite(pooled_sigma_px) \
                and pooled_sigma_px > 0:
            new, how = float(pooled_sigma_px), 'pooled detections'
        else:
            new, how = variance_factor_sigma(final), 'residuals'
        if not (np.isfinite(new) and new > 0):
            break
        if abs(new / sigma - 1.0) < NOISE_TOLERANCE:
            sigma, source = new, how
            break
        final = adjust(final.camera_list(), measured, obs, prior,
                       replace(settings, pixel_sigma=new), points_init=final.points,
                       inliers=final.inliers, kinematics=kin,
                       globals_init=final.global_parameters)
        stages.append((f'{prior.model} at {new:.3g} px', final.cost, final.iterations,
                       final.time_s))
        sigma, source = new, how
    return final, sigma, source
