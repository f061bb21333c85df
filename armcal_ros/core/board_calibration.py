"""
Calibrate cameras from a board (many points per pose) carried by a link with measured poses.

Data: per view v the link pose T_base_link_v (forward kinematics or a measured pose), and per
camera the detected board corners (id k, pixel uv).  Each (view, corner) seen by any camera is
one 3-D point of the adjustment, X^_vk = T_base_link_v T_link_target p_k
(:mod:`armcal_ros.core.target`); several cameras seeing it share the point.

Sequence:

1. Initialise (no guess needed): per camera, every view's board pose from its corners (Zhang's
   planar calibration for rough intrinsics, or PnP with given ones), then the hand-eye closed
   form for the camera pose T_camera_base and the mount T_link_target.  A guess of the mount
   replaces the hand-eye one as the seed.
2. Mount estimation (``MountSettings.estimate``): the six mount corrections are global
   parameters of the adjustment with the design d X^ / d(t, r) and a loose Gaussian prior
   (:class:`~armcal_ros.core.kinematic_prior.KinematicData`): ``fixed`` becomes "points =
   X^ + J dp" (a 1 um point sigma), ``independent`` the same with its point sigma, and
   ``correlated`` adds the lattice field next to them (the ``hybrid`` form of the prior).  The
   design is linear in dp, the mount is not: after each solve the estimate is folded into
   T_link_target and the problem is re-linearised there until the correction is below
   ``tolerance`` (2-4 rounds from a centimetre/degree start).  Each round re-centres the prior
   on the current mount, so the prior only regularises the step; with the default sigmas
   (5 cm, 10 deg) it is far looser than the data anyway.
3. Without mount estimation the given T_link_target is held and the chosen model is solved as
   for any point target.

A point marker (a sphere, a tag's centre) whose place on the link is unknown is the one-point
case: X^_v = T_base_link_v T_link_target 0.  Its views have no pose of their own, so the cameras
start from the nominal points at the guessed place (DLT, or PnP with given intrinsics) and the
guess seeds the mount; the mount's rotation is not observable (the prior holds it at the
guess), its translation - the marker's place - is, once the views turn the wrist.

With ``auto`` the mount comes from the ``fixed`` stage and is then held while the model is chosen.
"""

from dataclasses import dataclass, field, replace
from typing import Dict, List, Optional, Sequence

import numpy as np

from armcal_ros.core.adjustment import Observations, SolverSettings
from armcal_ros.core.calibration import calibrate, CalibrationResult, CameraSpec
from armcal_ros.core.camera import Camera, DISTORTION_NAMES
from armcal_ros.core.kinematic_prior import KinematicData
from armcal_ros.core.priors import PriorSettings
from armcal_ros.core.target import (board_view_poses, correct_mount, hand_eye, HandEye,
                                    mount_jacobian, mount_points, MOUNT_NAMES)


@dataclass
class BoardData:
    """
    Board observations.

    ``poses`` (V, 4, 4) T_base_link per view; ``points`` (P, 3) board points in the target
    frame (row = corner id); per observation m: ``view`` (M,), ``camera`` (M,) index into the
    camera list, ``corner`` (M,) corner id, ``uv`` (M, 2) pixels.
    """

    poses: np.ndarray
    points: np.ndarray
    view: np.ndarray
    camera: np.ndarray
    corner: np.ndarray
    uv: np.ndarray

    def __post_init__(self):
        self.poses = np.asarray(self.poses, float)
        self.points = np.asarray(self.points, float)
        self.view = np.asarray(self.view, np.int64).reshape(-1)
        self.camera = np.asarray(self.camera, np.int64).reshape(-1)
        self.corner = np.asarray(self.corner, np.int64).reshape(-1)
        self.uv = np.asarray(self.uv, float).reshape(-1, 2)
        m = len(self.view)
        if self.poses.ndim != 3 or self.poses.shape[1:] != (4, 4):
            raise ValueError(f'poses must have shape (V, 4, 4), got {self.poses.shape}')
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f'points must have shape (P, 3), got {self.points.shape}')
        for name in ('camera', 'corner'):
            if getattr(self, name).shape != (m,):
                raise ValueError(f'{name} must have shape ({m},) like view, got '
                                 f'{getattr(self, name).shape}')
        if self.uv.shape != (m, 2) or not np.all(np.isfinite(self.uv)):
            raise ValueError(f'uv must be finite with shape ({m}, 2), got {self.uv.shape}')
        if m and (self.view.min() < 0 or self.view.max() >= len(self.poses)):
            raise ValueError(f'view must index the {len(self.poses)} poses')
        if m and (self.corner.min() < 0 or self.corner.max() >= len(self.points)):
            raise ValueError(f'corner must index the {len(self.points)} board points')

    def __len__(self):
        return len(self.view)

    def select(self, mask):
        """Return the observations selected by a mask or index array (poses kept)."""
        return BoardData(self.poses, self.points, self.view[mask], self.camera[mask],
                         self.corner[mask], self.uv[mask])

    def point_table(self):
        """Return (point_view (N,), point_corner (N,), point index per observation (M,))."""
        key = self.view * len(self.points) + self.corner
        uniq, inv = np.unique(key, return_inverse=True)
        return uniq // len(self.points), uniq % len(self.points), inv.reshape(-1)


@dataclass
class MountSettings:
    """
    How T_link_target is treated: estimated or held, and the prior of its correction.

    ``sigma_translation`` (m) and ``sigma_rotation`` (rad) are prior standard deviations of
    the correction of the seed; ``fixed_point_sigma`` (m) is the point sigma that stands for
    "points exactly at X^ + J dp" under the ``fixed`` model.  ``estimate_scale`` adds the
    target's scale (its points are multiplied by it: a tag of unknown side, its size guessed)
    as a seventh global parameter, prior standard deviation ``sigma_scale`` (relative).
    """

    estimate: bool = True
    estimate_scale: bool = False
    sigma_scale: float = 0.5
    sigma_translation: float = 0.05
    sigma_rotation: float = np.radians(10.0)
    fixed_point_sigma: float = 1e-6
    max_rounds: int = 10
    tolerance: float = 1e-7

    def validate(self):
        """Raise ValueError naming the first bad setting; return self."""
        for name in ('sigma_translation', 'sigma_rotation', 'fixed_point_sigma', 'tolerance',
                     'sigma_scale'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f'mount {name} must be > 0, got {v}')
        if self.max_rounds < 1:
            raise ValueError(f'mount max_rounds must be >= 1, got {self.max_rounds}')
        return self

    def sigma(self):
        """Return the prior sigmas of (t, r) (6,), and of the scale when it is estimated."""
        s = [self.sigma_translation] * 3 + [self.sigma_rotation] * 3
        return np.array(s + ([self.sigma_scale] if self.estimate_scale else []))

    def names(self):
        """Return the global parameters' names, in the order of :meth:`sigma`."""
        return list(MOUNT_NAMES) + (['target/scale'] if self.estimate_scale else [])


@dataclass
class BoardInit:
    """How the cameras and the mount were initialised, per camera."""

    method: Dict[str, str] = field(default_factory=dict)
    view_rms_px: Dict[str, float] = field(default_factory=dict)
    hand_eye: Dict[str, HandEye] = field(default_factory=dict)
    mount_seed: str = ''


@dataclass
class BoardCalibrationResult:
    """
    Result of :func:`calibrate_board`.

    ``calibration`` the final :class:`CalibrationResult` (its points are the (view, corner)
    points ``point_view`` / ``point_corner``); ``T_link_target`` the mount used or estimated,
    ``mount_std`` (6,) standard deviations of its last correction (t in m, r in rad) when
    estimated, (7,) with the scale's; ``rounds`` re-linearisation rounds; ``model`` the prior
    actually solved; ``scale`` the factor of the target's points (1 unless estimated).
    """

    calibration: CalibrationResult
    T_link_target: np.ndarray
    mount_std: Optional[np.ndarray]
    init: BoardInit
    point_view: np.ndarray
    point_corner: np.ndarray
    measured: np.ndarray
    observations: Observations
    rounds: int = 0
    model: str = ''
    stages: List[str] = field(default_factory=list)
    scale: float = 1.0

    @property
    def success(self):
        """Return True if the final adjustment converged."""
        return bool(self.calibration.success)

    @property
    def cameras(self):
        """Estimated cameras by name."""
        return self.calibration.cameras

    def predict_uv(self, data: BoardData, camera_names: Sequence[str]):
        """
        Return predicted pixels (M, 2) of ``data``'s observations (NaN for unknown cameras).

        Points are X^ from the estimated mount plus, for the correlated model, the fitted
        field's prediction there - a held-out view's honest prediction.
        """
        pv, pc, pidx = data.point_table()
        X = mount_points(data.poses, self.T_link_target, pv, data.points[pc] * self.scale)
        adj = self.calibration.adjustment
        if adj is not None and adj.prior is not None and adj.prior.kind in ('global', 'dense'):
            # The mount correction is already folded into T_link_target: zero design.
            n_global = 6 if self.mount_std is None else len(self.mount_std)
            X = X + adj.predict_offsets(X, np.zeros((len(X), 3, n_global)))
        out = np.full((len(data), 2), np.nan)
        cams = self.cameras
        for j, name in enumerate(camera_names):
            sel = data.camera == j
            if name in cams and sel.any():
                out[sel] = cams[name].project(X[pidx[sel]])
        return out


def _views_of(data: BoardData, j):
    sel = data.camera == j
    out = {}
    for v in np.unique(data.view[sel]):
        m = sel & (data.view == v)
        out[int(v)] = (data.points[data.corner[m]], data.uv[m])
    return out


def initialise_board_cameras(specs: Sequence[CameraSpec], data: BoardData,
                             free_distortion=('k1', 'k2'), intrinsics=None):
    """
    Return ({name: Camera}, {name: HandEye}, BoardInit) from board views alone.

    ``intrinsics`` optionally maps camera names to (K (3, 3), dist (5,) or None) to use
    instead of Zhang's estimate.  Distortion terms that will not be estimated are zeroed.
    Cameras with fewer than 3 usable views are left out (their message is in ``init.method``).
    """
    cams, hes = {}, {}
    init = BoardInit()
    keep_d = np.array([d in free_distortion for d in DISTORTION_NAMES])
    for j, spec in enumerate(specs):
        views = _views_of(data, j)
        guess = (intrinsics or {}).get(spec.name)
        try:
            # A tag's four corners are a whole target; a board view wants six of its corners.
            vp = board_view_poses(views, spec.width, spec.height,
                                  K=None if guess is None else guess[0],
                                  dist=None if guess is None else guess[1],
                                  min_corners=min(6, len(data.points)))
            keys = sorted(vp.T_cam_target)
            he = hand_eye(data.poses[keys], [vp.T_cam_target[k] for k in keys])
        except ValueError as exc:
            init.method[spec.name] = f'not initialised: {exc}'
            continue
        K = vp.K
        dist = np.where(keep_d, np.asarray(vp.dist, float).reshape(-1)[:5], 0.0)
        cams[spec.name] = Camera(spec.name, spec.width, spec.height, K[0, 0], K[1, 1], K[0, 2],
                                 K[1, 2], dist, he.T_camera_base[:3, :3],
                                 he.T_camera_base[:3, 3])
        hes[spec.name] = he
        init.method[spec.name] = vp.method
        init.view_rms_px[spec.name] = vp.rms_px
    init.hand_eye = hes
    return cams, hes, init


def _mount_prior(model, prior: PriorSettings, mount: MountSettings):
    if model == 'fixed':
        return replace(prior, model='kinematic', point_sigma=mount.fixed_point_sigma)
    if model == 'independent':
        return replace(prior, model='kinematic')
    if model == 'correlated':
        return replace(prior, model='hybrid')
    raise ValueError(f'noise_model {model!r} cannot estimate a board mount from pose input '
                     '(use fixed, independent, correlated or auto)')


def _fits_better(a, b) -> bool:
    """
    Return True when calibration ``a`` fits its images better than ``b``.

    Where each solve estimated the image noise from its own residuals, its cost is whitened by
    that estimate and comes out near its redundancy however well it fits, so the costs of two
    solves are not comparable: the estimates themselves are (the variance factors, each over
    its own redundancy).  Measured on a 16-sample simulated recording with the marker's place
    estimated from a guess 3 cm off: the restart fitted at 0.078 px, the first start at
    0.147 px with one camera 98 mm off, and the whitened costs (52.4 against 50.9) kept the
    first.  With the noise given, both are weighted alike and the costs compare.
    """
    if a.noise_source != 'given' and b.noise_source != 'given' and \
            np.isfinite(a.pixel_sigma) and np.isfinite(b.pixel_sigma):
        return a.pixel_sigma < b.pixel_sigma
    return a.adjustment.cost < b.adjustment.cost


def calibrate_board(specs: Sequence[CameraSpec], data: BoardData, prior: PriorSettings = None,
                    settings: SolverSettings = None, T_link_target=None,
                    mount: MountSettings = None, initial: Optional[Dict[str, Camera]] = None,
                    intrinsics=None, rng=None, scale=1.0) -> BoardCalibrationResult:
    """
    Calibrate ``specs`` from board observations ``data`` (module docstring for the sequence).

    ``T_link_target`` (4, 4) seeds (or, without mount estimation, fixes) the mount; None finds
    it by hand-eye.  ``initial`` warm-starts cameras by name (else they are initialised from
    the board views); ``intrinsics`` maps names to (K, dist) for the view-pose step.  ``scale``
    multiplies the target's points (the seed of the scale when ``mount.estimate_scale``).
    Raises ValueError for unusable input (no camera initialised, no mount without estimation).
    """
    prior = (prior or PriorSettings()).validate()
    settings = (settings or SolverSettings()).validate()
    mount = (mount or MountSettings()).validate()
    if not len(data):
        raise ValueError('board data has no observations')
    if T_link_target is None and not mount.estimate:
        raise ValueError('T_link_target is needed when the mount is not estimated '
                         '(estimate_marker_offset false)')
    initial = dict(initial or {})
    if intrinsics is None and settings.intrinsics:
        # Given intrinsics (SolverSettings.intrinsics) also give the view poses by PnP.
        intrinsics = {k: (p.K, np.asarray(p.dist, float))
                      for k, p in settings.intrinsics.items()}
    if len(data.points) == 1:
        # A point marker: a view has no pose of its own to start from, so the cameras start
        # from the nominal points at the guessed place (calibrate(): DLT, or PnP with given
        # intrinsics) and the guess seeds the mount.
        if T_link_target is None:
            raise ValueError('a point marker\'s place on the link needs a guess to start from '
                             '(marker_offset)')
        hes, init = {}, BoardInit({s.name: 'from the nominal points' for s in specs})
    else:
        scaled = replace(data, points=data.points * scale) if scale != 1.0 else data
        cams_init, hes, init = initialise_board_cameras(specs, scaled, settings.free_distortion,
                                                        intrinsics)
        for name, cam in cams_init.items():
            initial.setdefault(name, cam)
        if not initial:
            raise ValueError('no camera could be initialised from the board views: ' +
                             '; '.join(f'{k}: {v}' for k, v in init.method.items()))
    if T_link_target is not None:
        T = np.asarray(T_link_target, float)
        init.mount_seed = 'given'
    else:
        best = max(hes, key=lambda k: hes[k].n_views)
        T = hes[best].T_link_target
        init.mount_seed = f'hand-eye ({best})'
    pv, pc, pidx = data.point_table()
    obs = Observations(data.camera, pidx, data.uv)
    stages = []

    names = mount.names()

    def solve(model_prior, T, scale, cams, estimate):
        pts = data.points[pc] * scale
        X = mount_points(data.poses, T, pv, pts)
        kin = None
        if estimate:
            J = mount_jacobian(data.poses, T, pv, pts)
            if mount.estimate_scale:
                # d X^ / d scale = R_base_link R_link_target p (the unscaled point).
                R = data.poses[pv][:, :3, :3] @ T[:3, :3]
                J = np.concatenate([J, np.einsum('nij,nj->ni', R, data.points[pc])[:, :, None]],
                                   axis=2)
            kin = KinematicData(J, names, mount.sigma())
        res = calibrate(specs, X, obs, model_prior, settings, initial=cams, rng=rng,
                        kinematics=kin)
        return res, X

    def estimate_mount(model_prior, T, scale, cams):
        res, X, std, k = None, None, None, 0
        for k in range(1, mount.max_rounds + 1):
            res, X = solve(model_prior, T, scale, cams, True)
            adj = res.adjustment
            if adj is None or adj.kinematic_errors is None:
                break
            dp = np.array([adj.kinematic_errors[n] for n in names])
            std = np.array([adj.kinematic_std[n] for n in names])
            T = correct_mount(T, dp[:6])
            if mount.estimate_scale:
                scale = scale + float(dp[6])
            cams = {**cams, **res.cameras}
            stages.append(f'{model_prior.model}+mount round {k}: |dt| '
                          f'{np.linalg.norm(dp[:3]) * 1e3:.3f} mm, |dr| '
                          f'{np.degrees(np.linalg.norm(dp[3:6])):.4f} deg'
                          + (f', scale {scale:.5f}' if mount.estimate_scale else ''))
            if np.max(np.abs(dp)) < mount.tolerance:
                break
        return res, X, T, scale, std, k, cams

    std, rounds, solved = None, 0, prior.model
    if mount.estimate:
        fixed_prior = _mount_prior('fixed', prior, mount)
        T0 = T
        res, X, T, scale, std, rounds, cams = estimate_mount(fixed_prior, T, scale, initial)
        if len(data.points) == 1 and np.linalg.norm(T[:3, 3] - T0[:3, 3]) > 1e-3 and \
                res.adjustment is not None:
            # The cameras started from points at a guess that proved off: start them again
            # from the corrected place and keep whichever solution fits better (the stiff
            # points-on-the-arm problem converges slowly from a poor start).
            again = estimate_mount(fixed_prior, T, scale, dict(initial))
            if again[0].adjustment is not None and _fits_better(again[0], res):
                stages.append('point marker: cameras restarted at the corrected place')
                res, X, T, scale, std, r2, cams = again
                rounds += r2
        if prior.model in ('independent', 'correlated'):
            res, X, T, scale, std, r2, cams = estimate_mount(
                _mount_prior(prior.model, prior, mount), T, scale, cams)
            rounds += r2
            solved = f'{prior.model}+mount'
        elif prior.model == 'auto':
            res, X = solve(prior, T, scale, cams, False)
            stages.append('auto with the mount of the fixed stage')
        elif prior.model != 'fixed':
            _mount_prior(prior.model, prior, mount)       # raises with the reason
        else:
            solved = 'fixed+mount'
    else:
        res, X = solve(prior, T, scale, initial, False)
    return BoardCalibrationResult(res, T, std, init, pv, pc, X, obs, rounds, solved, stages,
                                  scale)
