"""
Change detection: test every new observation against what the current calibration predicts.

A cell changes while it works: a camera is knocked, a lens refocused, a tool changed.  Each new
sample is tested against the current calibration before it is used.

**Prediction.**  For a sample with the arm's measured point X^ and pooled image points uv_o of
the calibrated cameras o, camera c's observation is predicted from every *other* source: the
point

    X~ = argmin_X |X - X^|^2 / s_arm^2 + sum_{o != c} |uv_o - pi_o(X)|^2 / s_o^2

(Gauss-Newton from X^), with H its information matrix, gives

    r_c = uv_c - pi_c(X~),   S_c = s_c^2 I + G_c C_c G_c^T + J_c H^-1 J_c^T,
    d_c^2 = r_c^T S_c^-1 r_c,

with G_c C_c G_c^T what the calibration's parameter covariance puts into the prediction (a
young calibration extrapolates widely).  Given the joint covariance C of every camera's
parameters (what the engine passes), the other cameras are weighted by their image noise alone
and C is propagated with its correlations through the whole prediction, the fused point
included (:func:`_innovation_batch`): the arm fixes the cameras' common frame only to its own
accuracy, so each camera's pose on its own is known far worse than the cameras relative to
one another, and per-camera blocks would credit every prediction with the frame's uncertainty
(measured on the demo cell at the estimated image noise: 0.60 px predicted where new views were
0.13 px off, about 20 times the variance, which hid a 0.5 % focal change entirely).

Leaving camera c out makes r_c independent of c's own error; the other cameras make it
independent of the arm's error along their rays (with three cameras the arm hardly matters).
s_o is each camera's image noise from its residuals; s_arm the RMS per axis of what the
adjustment corrected the arm's points by (at least :data:`ARM_SIGMA_FLOOR`).  With a kinematic
model the engine gives X^ as the model predicts it, X^ + A g (A = J_p(q) diag(sigma_p)), s_arm as
what the model leaves at its own samples, and the model's parameters g in the joint covariance
(rows :data:`ARM`) with their correlations with the cameras: each prediction then carries what
the model does not know about the arm relative to the cameras (:func:`_innovation_batch`).
The predictor is then calibrated on the calibration's own samples: k_c^2 = median(d_c^2) /
(2 ln 2) (the median of chi^2 with 2 degrees of freedom), so d_c^2 / k_c^2 is chi^2(2) when
nothing has changed, whatever the noise model left out (a robust scale; one bad detection
cannot move it).

The scale then follows the camera's recent statistics (:class:`ChangeMonitor`): new views are
predicted a little worse than the calibration's covariance says wherever the images hold errors
the model leaves out.

**Sequential test.**  Page's CUSUM on each camera's statistics: with g = min(d^2 / k^2, cap) - c,

    S_0 = 0,    S_k = max(0, S_(k-1) + g_k),    a change when S_k > h.

Under no change d^2 / k^2 is chi^2_2 (exponential, mean 2), so with the reference c = 4 the drift
is negative and S keeps returning to zero; a camera whose statistics average above c climbs.
h is set so that the average run length under no change is 1 / ``false_alarm`` views (computed
by the Markov-chain method of Brook and Evans, :func:`threshold`): one false alarm per million
views of a camera by default.  The cap 3 c, with h above 2 (cap - c), makes at least three
disagreeing observations necessary, so a lone mis-detection never fires; samples of one place
(consecutive arm points within :data:`SAME_PLACE`) count once, so neither does one pause split
into several samples.  The onset is the first observation after S last stood at zero, refined
by the refit (below).

**Attribution.**  When a CUSUM fires, the samples since the onset are first tested as a whole:
if the arm and every camera agree on them (the fusion's whitened residual sum within its chi^2
quantile at :data:`CONFIRM_ALPHA`), the climb was a disagreement too weak to be anything (a
region the calibration describes a little worse, views that are correlated in space) and that
camera's CUSUM starts again.  Otherwise they are explained in turn:
- a camera moved if, leaving it out, the others and the arm agree, and leaving out any other
  does not;
- the arm or the marker changed if no single camera explains it but the cameras agree with each
  other without the arm (every camera sees the points move the same way: a new tool, a re-homed
  joint);
- when more than one exclusion leaves agreement (two cameras and an arm known to millimetres
  predict each other loosely, view by view; a weak disagreement spread over several cameras),
  each of those cameras is refitted as one rigid change across its views, and if exactly one
  refit explains them, every other having been refitted (enough views), it is that camera;
- failing that, with two cameras that disagree with each other (a new pose of either absorbs
  a few views alike), if leaving one out agrees clearly better than leaving out the other -
  the ratio of their chi^2 per degree of freedom beyond its F quantile at CONFIRM_ALPHA - and
  its refit explains its views, it is that camera: the views of the camera that changed
  disagree with the arm, the other's do not;
- otherwise the change is reported as unexplained, against the camera whose window fired.
A suspect camera is declared changed only if its views from the change point on disagree
with its old calibration taken together - the calibration's error is one error common to them
- and not on one view alone (:func:`joint_disagreement`), and a refit explains them; short of
that it waits, up to :data:`MAX_SUSPECT_VIEWS`, while its latest views still disagree one by
one.
An unexplained climb is judged again at the next view while there are too few views to tell
(fewer than CONFIRM_OBSERVATIONS + ONSET_SLACK, or two cameras that both explain them, up to
:data:`MAX_SUSPECT_VIEWS`), and a suspect camera whose views no refit explains yet keeps
collecting while its latest views still disagree: a change that began inside the climb needs
its own views.
Whether a moved camera's pose or its intrinsics changed is told from a fit of its new
observations (the engine's PnP with the old intrinsics), not here.
"""

from collections import deque
from dataclasses import dataclass, field
from functools import lru_cache
from math import log
from typing import Dict, List, Optional

import cv2
import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2
from scipy.stats import f as f_dist

from armcal_ros.core.camera import Camera, project_with_jacobians

#: Floor of the arm's per-axis error (m) when the model corrected nothing (``fixed``): the
#: repeatability of a good industrial arm (ISO 9283 figures of 0.02-0.1 mm); only the spread
#: of the prediction along rays no other camera constrains depends on it.
ARM_SIGMA_FLOOR = 1e-4
#: Gauss-Newton steps of the fusion: it starts within millimetres, where the projection is
#: nearly linear; two steps leave sub-micrometre changes.
FUSION_ITERATIONS = 3
#: Statistics a camera needs in the calibration's own samples before its scale is trusted;
#: with fewer, the model's own scale (1) is used.
MIN_REFERENCE = 10
MEDIAN_CHI2_2 = 2.0 * log(2.0)
#: Views of a suspect camera from the onset on before it is judged: 12 equations for the 7
#: parameters of a new pose and focal length leave 5 degrees of freedom to tell a moved camera
#: (explained) from a burst of bad detections (not).
CONFIRM_OBSERVATIONS = 6
#: Significance at which the views since a CUSUM's onset must disagree as a whole before any
#: change is considered: the CUSUM has already held the false alarms to its rate; this only
#: turns away climbs on disagreements that are no disagreement on their own (ratios of 0.1-0.2
#: measured on the desk arm under a model that describes it in part).
CONFIRM_ALPHA = 1e-3
#: Views beyond CONFIRM_OBSERVATIONS collected before the judgement, so that the change point
#: can be moved past up to this many old views that happened to start the CUSUM's climb.
ONSET_SLACK = 2
#: Views a suspect may collect while its latest views still disagree with its old calibration
#: and no split explains them yet: a climb that began on old views a little off (a region the
#: calibration describes a little worse) just before a real change leaves too few new views
#: for the refit at first; waiting for them costs less than a reset and a new climb.
MAX_SUSPECT_VIEWS = 3 * CONFIRM_OBSERVATIONS
#: A refit explains a camera's views only with a change a camera can physically undergo: turned
#: by at most this much (a knock, a mount that slipped), its lens by at most MAX_FOCAL_PERCENT
#: (refocus or zoom), its centre by at most MAX_SHIFT_FRACTION of its distance to the views.
#: Views that a camera model fits only by degenerating (a static spot taken for the marker,
#: fitted with a camera 100 km away and a focal length 14 times longer) are not a move.
MAX_ROTATION_DEG = 45.0
MAX_FOCAL_PERCENT = 50.0
MAX_SHIFT_FRACTION = 0.5
#: Views per camera whose statistics rescale the test as it runs (see :class:`ChangeMonitor`):
#: enough for a median within about 15 %; the latest LAG_VIEWS are left out, so that a change
#: cannot soften its own test before the CUSUM (three views at least) and the confirmation
#: (CONFIRM_OBSERVATIONS + ONSET_SLACK) have run.
SCALE_WINDOW = 60
LAG_VIEWS = 12
#: Views whose arm points lie within this distance (m) of the first of a run of consecutive
#: views are one place, counted once by the CUSUM (the mean of their increments): a pause
#: that the front end splits into several samples (an arm creeping below the stillness
#: limit) repeats one error, and three copies of one bad view must not pass for three views.
#: The store's default min_sample_spacing, for the same reason.
SAME_PLACE = 0.005
#: The arm's rows in a joint covariance: (ARM, 'g0'), (ARM, 'g1'), ... are the whitened global
#: parameters g of the arm's error model (the arm's point at a view is X^ + A g, A the view's
#: design); no camera can be called this (ROS names have no angle brackets).
ARM = '<arm>'


@dataclass
class ChangeSettings:
    """The CUSUM's reference (in units of chi^2_2) and its false alarms per view."""

    reference: float = 4.0
    false_alarm: float = 1e-6

    def validate(self):
        """Check the settings; return self."""
        if not (np.isfinite(self.reference) and self.reference > 2.0):
            raise ValueError('change reference must be > 2 (the mean of chi^2_2 under no '
                             f'change), got {self.reference}')
        if not 0 < self.false_alarm <= 1e-2:
            raise ValueError(f'change false_alarm must be in (0, 0.01] per view (a false alarm '
                             f'every 100 views or fewer is no test), got {self.false_alarm}')
        h = threshold(self.reference, self.false_alarm)
        if h <= 2.0 * (cap_of(self.reference) - self.reference):
            raise ValueError(f'change false_alarm {self.false_alarm} is too high for reference '
                             f'{self.reference}: two views could raise an alarm (threshold '
                             f'{h:.1f})')
        return self


def _arl(h, reference, cap, cells=200):
    """
    Return the CUSUM's average run length under no change (Brook and Evans, 1972).

    S is discretised on ``cells`` points of [0, h); the increment g = min(X, cap) - c with X
    exponential of mean 2 (chi^2_2) has the CDF F(x) = 1 - exp(-(x + c) / 2) below cap - c and
    1 above; L solves (I - Q) L = 1 with Q the transitions among the states below h.
    """
    w = h / cells
    v = np.arange(cells) * w

    def cdf(x):
        x = np.asarray(x, float)
        out = 1.0 - np.exp(-np.maximum(x + reference, 0.0) / 2.0)
        return np.where(x >= cap - reference, 1.0, out)

    edges = (np.arange(cells + 1) - 0.5) * w             # state k holds [k - 1/2, k + 1/2) w
    edges[0] = -np.inf
    F = cdf(edges[None, 1:] - v[:, None])               # P(v + g < upper edge of k)
    lower = np.concatenate([np.zeros((cells, 1)), F[:, :-1]], axis=1)
    Q = F - lower
    L = np.linalg.solve(np.eye(cells) - Q, np.ones(cells))
    return float(L[0])


def cap_of(reference):
    """Return the clip of one view's statistic: 3 c (chi^2_2 beyond it: 0.25 % at c = 4)."""
    return 3.0 * reference


@lru_cache(maxsize=32)
def threshold(reference, false_alarm):
    """
    Return the CUSUM threshold h whose false alarms come once per 1 / ``false_alarm`` views.

    The average run length under no change (:func:`_arl`, cap :func:`cap_of`) rises
    monotonically with h; h is found by bisection on log h.
    """
    lo, hi = 1e-3, 1e3
    for _ in range(60):
        mid = np.sqrt(lo * hi)
        if _arl(mid, reference, cap_of(reference)) * false_alarm < 1.0:
            lo = mid
        else:
            hi = mid
    return float(hi)


@dataclass
class PredictionModel:
    """The current calibration as a predictor: cameras, their image noise, the arm's error."""

    cameras: Dict[str, Camera]
    sigma_px: Dict[str, float]
    #: The arm's error per axis (m) beyond what its model predicts: with a joint covariance
    #: that has the arm's rows (:data:`ARM`), the model's own uncertainty is propagated with
    #: its correlations with the cameras; elsewhere ``arm_model_sigma`` (m per axis, the
    #: model's prediction on its own) is added to it.
    arm_sigma: float
    #: Per camera (its parameters' names - fx, fy, cx, cy, the fitted distortion terms, wx, wy,
    #: wz, tx, ty, tz - and their covariance): what the calibration does not know adds
    #: J_c C J_c^T to each prediction.  Cameras without one are taken as exact.
    parameter_covariance: Dict[str, tuple] = field(default_factory=dict)
    #: The calibration's covariance over every camera's parameters at once, with the
    #: correlations between cameras: ([(camera, parameter)], C).  When given, the
    #: leave-one-out innovation propagates it through the prediction (:func:`innovation`)
    #: instead of adding each camera's block on its own.
    joint_covariance: Optional[tuple] = None
    arm_model_sigma: float = 0.0
    #: Where the arm is at a view: a callable (measured point (3,), joint angles or None) ->
    #: (point (3,), design (3, G)) or None, whose ``predict`` does many views at once (the
    #: engine's ArmPrediction), or None for the measured point itself.  Kept with the model
    #: so that a change is later sized against the arm the test found it with.
    arm_prediction: Optional[object] = None

    def __post_init__(self):
        for name, s in self.sigma_px.items():
            if not (np.isfinite(s) and s > 0):
                raise ValueError(f'sigma_px[{name!r}] must be finite and > 0, got {s}')
        if not (np.isfinite(self.arm_sigma) and self.arm_sigma > 0):
            raise ValueError(f'arm_sigma must be finite and > 0 (m), got {self.arm_sigma}')
        if self.joint_covariance is not None:
            names, C = self.joint_covariance
            C = np.asarray(C, float)
            if C.shape != (len(names), len(names)):
                raise ValueError(f'joint_covariance must be ([(camera, parameter)] of n, C (n, '
                                 f'n)), got {len(names)} names and C {C.shape}')

    def without(self, camera) -> 'PredictionModel':
        """Return this model without ``camera`` (its parameters out of the covariances too)."""
        rest = [n for n in self.cameras if n != camera]
        return PredictionModel(
            {n: self.cameras[n] for n in rest}, {n: self.sigma_px[n] for n in rest},
            self.arm_sigma,
            {n: v for n, v in self.parameter_covariance.items() if n != camera},
            joint_subset(self.joint_covariance, rest), self.arm_model_sigma,
            self.arm_prediction)


def joint_subset(joint, cameras):
    """
    Return a joint covariance ([(camera, parameter)], C) restricted to ``cameras`` (or None).

    The arm's rows (:data:`ARM`) are kept.
    """
    if joint is None:
        return None
    names, C = joint
    keep = [i for i, (c, _) in enumerate(names) if c in cameras or c == ARM]
    return [names[i] for i in keep], np.asarray(C)[np.ix_(keep, keep)]


_DIST = ('k1', 'k2', 'p1', 'p2', 'k3')


def _parameter_jacobian(pj, names):
    """Return d uv / d(parameters ``names``) (N, 2, p) from a projection with its Jacobians."""
    cols = []
    for p in names:
        if p in ('fx', 'fy', 'cx', 'cy'):
            cols.append(pj.d_intr[:, :, ('fx', 'fy', 'cx', 'cy').index(p)])
        elif p in _DIST:
            cols.append(pj.d_dist[:, :, _DIST.index(p)])
        else:
            cols.append(pj.d_pose[:, :, ('wx', 'wy', 'wz', 'tx', 'ty', 'tz').index(p)])
    return np.stack(cols, axis=2)


def _joint_index(names):
    """Return camera -> (its parameter names, their rows) of a joint covariance's names."""
    index = {}
    for i, (cam, p) in enumerate(names):
        index.setdefault(cam, ([], []))
        index[cam][0].append(p)
        index[cam][1].append(i)
    return index


def _project(model: PredictionModel, name, X):
    cam = model.cameras[name]
    return project_with_jacobians(cam.intrinsics(), cam.dist, cam.rotation, cam.translation, X)


def _predict_batch(model: PredictionModel, name, X, scale=1.0, parameters=True, extra=0.0):
    """
    Return :func:`predict` for many points X (N, 3): uv, d uv / dX, Sigma (N, 2, 2), depth.

    Without ``parameters`` Sigma is the image noise alone; ``extra`` (scalar or (N,)) is a
    variance per axis (px^2) added to the image noise of each point's view (:class:`View`).
    """
    pj = _project(model, name, X)
    Sigma = np.zeros((X.shape[0], 2, 2))
    Sigma[:, 0, 0] = Sigma[:, 1, 1] = scale * model.sigma_px[name] ** 2 + extra
    got = model.parameter_covariance.get(name) if parameters else None
    if got is not None:
        names, C = got
        Jc = _parameter_jacobian(pj, names)
        Sigma = Sigma + np.einsum('nap,pq,nbq->nab', Jc, C, Jc)
    return pj.uv, pj.d_point, Sigma, pj.depth


def predict(model: PredictionModel, name, X, scale=1.0):
    """
    Return camera ``name``'s prediction of point X (3,): (uv (2,), d uv / dX (2, 3), Sigma (2, 2)).

    Sigma = scale s^2 I + J_c C J_c^T: the image noise (times ``scale``, the k^2 of the module
    docstring) and the calibration's own uncertainty through the camera's parameter Jacobian.
    """
    uv, J, Sigma, depth = _predict_batch(model, name, np.asarray(X, float).reshape(1, 3), scale)
    return uv[0], J[0], Sigma[0], depth[0]


@dataclass
class Fusion:
    """A point fused from the arm and some cameras: X (3,), H^-1 (3, 3), whitened chi^2, dof."""

    X: np.ndarray
    cov: np.ndarray
    chi2: float
    dof: int


def fuse(model: PredictionModel, X0, uvs: Dict[str, np.ndarray], scales=None,
         use_arm=True, extra=None) -> Optional[Fusion]:
    """
    Fuse the arm's point ``X0`` (3,) with the cameras' points ``uvs`` (name -> (2,)).

    Minimises |X - X0|^2 / s_arm^2 (if ``use_arm``) + sum_o r_o^T Sigma_o^-1 r_o, r_o = uv_o -
    pi_o(X), Sigma_o from :func:`predict`, by Gauss-Newton; ``scales`` maps cameras to k_o^2
    (default 1), ``extra`` cameras to a variance added to their image noise (:class:`View`).
    The chi^2 is the whitened
    residual sum at the solution, with 2 m + 3 - 3 degrees of freedom (m cameras) with the arm,
    2 m - 3 without.  None when the cameras alone cannot fix the point (fewer than two).
    """
    X0 = np.asarray(X0, float).reshape(3)
    names = [n for n in uvs if n in model.cameras]
    if not use_arm and len(names) < 2:
        return None
    X, cov, chi, ok = _fuse_batch(
        model, X0[None], {n: np.asarray(uvs[n], float).reshape(1, 2) for n in names},
        {n: np.ones(1, bool) for n in names}, scales, use_arm, extra=_batch_extra(extra, 1))
    if not ok[0]:
        return None
    return Fusion(X[0], cov[0], float(chi[0]), 2 * len(names) - (0 if use_arm else 3))


def agreement(model: PredictionModel, X0, uvs: Dict[str, np.ndarray], scales=None,
              use_arm=True, extra=None, arm_design=None):
    """
    Return (chi^2, dof) of the arm and the cameras ``uvs`` agreeing on one point, or None.

    Without a joint covariance, :func:`fuse`'s chi^2.  With one, the point is fused with the
    image noise alone and its residuals e = y - f(X~) (the cameras' points and, with the arm,
    its point) are judged with their covariance under no change,

        Cov(e) = P (N + G C G^T) P^T,   P = I - F H^-1 F^T W,

    F = [J_o; I] the residuals' derivative in X, G = [J_theta_o; 0] in the cameras'
    parameters, N = W^-1 the noise (k_o^2 s_o^2 per camera, s_arm^2), C the joint covariance:
    chi^2 = e^T Cov(e)^+ e over its rank (2 m with the arm, 2 m - 3 without).  As in
    :func:`_innovation_batch`, the calibration's uncertainty counts with its correlations, so
    the cameras' common freedom (the frame the arm fixes only to its own accuracy) is not
    mistaken for room to disagree.  ``extra``: as for :func:`fuse`.  With the arm's rows in
    the joint covariance and the view's ``arm_design`` A (3, G), the arm's point X^ + A g
    moves with its model's parameters g: its rows of G are -A (the cameras' rows hold
    +J_theta, the negative of their residuals' derivative, and the sign must agree).
    """
    joint = model.joint_covariance
    extra = extra or {}
    if joint is None:
        f = fuse(model, X0, uvs, scales, use_arm, extra)
        return None if f is None else (f.chi2, f.dof)
    X0 = np.asarray(X0, float).reshape(3)
    names = [n for n in uvs if n in model.cameras]
    if len(names) < (1 if use_arm else 2):
        return None
    X, cov, _, ok = _fuse_batch(model, X0[None],
                                {n: np.asarray(uvs[n], float).reshape(1, 2) for n in names},
                                {n: np.ones(1, bool) for n in names}, scales, use_arm,
                                parameters=False, extra=_batch_extra(extra, 1))
    if not ok[0]:
        return None
    cams, C = joint
    index = _joint_index(cams)
    rows = 2 * len(names) + (3 if use_arm else 0)
    e, F, G, noise = (np.zeros(rows), np.zeros((rows, 3)), np.zeros((rows, len(cams))),
                      np.zeros(rows))
    for j, n in enumerate(names):
        pj = _project(model, n, X)
        sl = slice(2 * j, 2 * j + 2)
        e[sl] = np.asarray(uvs[n], float).reshape(2) - pj.uv[0]
        F[sl] = pj.d_point[0]
        noise[sl] = (1.0 if scales is None else scales.get(n, 1.0)) * model.sigma_px[n] ** 2 \
            + extra.get(n, 0.0)
        if n in index:
            G[sl, index[n][1]] = _parameter_jacobian(pj, index[n][0])[0]
    if use_arm:
        e[-3:], F[-3:], noise[-3:] = X0 - X[0], np.eye(3), model.arm_sigma ** 2
        if arm_design is not None and ARM in index:
            G[-3:, index[ARM][1]] = -np.asarray(arm_design, float).reshape(3, -1)
    P = np.eye(rows) - F @ cov[0] @ F.T / noise[None, :]
    V = P @ (np.diag(noise) + G @ np.asarray(C, float) @ G.T) @ P.T
    w, U = np.linalg.eigh(0.5 * (V + V.T))
    keep = w > 1e-9 * w[-1]
    dof = rows - 3
    keep[:max(0, len(w) - dof)] = False
    if not np.any(keep):
        return None
    proj = U[:, keep].T @ e
    return float(np.sum(proj ** 2 / w[keep])), int(np.sum(keep))


def _batch_extra(extra, n):
    """Return a view's added variances (name -> px^2) as arrays for a batch of ``n`` points."""
    return {k: np.full(n, float(v)) for k, v in (extra or {}).items()}


def _fuse_batch(model: PredictionModel, X0, uv, seen, scales=None, use_arm=True,
                parameters=True, extra=None):
    """
    :func:`fuse` for N points at once: X0 (N, 3), per camera uv (N, 2) and seen (N,) bool.

    ``extra`` maps cameras to (N,) variances added to their image noise (:class:`View`).

    Returns (X (N, 3), H^-1 (N, 3, 3), chi^2 (N,), ok (N,)); a point whose information matrix
    is singular or not finite is not ok (its entries are NaN).  Without ``parameters`` the
    cameras are weighted by their image noise alone and the arm by ``arm_sigma`` alone (the
    calibration's uncertainty is then propagated by the caller).
    """
    N = X0.shape[0]
    arm_var = model.arm_sigma ** 2 + (model.arm_model_sigma ** 2 if parameters else 0.0)
    w_arm = 1.0 / arm_var if use_arm else 0.0
    X = X0.copy()
    ok = np.ones(N, bool)

    def invertible(H):
        return ok & np.all(np.isfinite(H), axis=(1, 2)) & (
            np.abs(np.linalg.det(np.where(ok[:, None, None], H, np.eye(3)))) > 0)
    with np.errstate(all='ignore'):
        for it in range(FUSION_ITERATIONS + 1):
            H = np.zeros((N, 3, 3))
            H[:, [0, 1, 2], [0, 1, 2]] = w_arm
            g = w_arm * (X0 - X)
            chi = w_arm * np.sum((X - X0) ** 2, axis=1)
            for n, m in seen.items():
                if not np.any(m):
                    continue
                k = 1.0 if scales is None else scales.get(n, 1.0)
                ex = extra[n][m] if extra and n in extra else 0.0
                u, J, Sigma, _ = _predict_batch(model, n, X[m], k, parameters, ex)
                W = _inv2(Sigma)
                r = uv[n][m] - u
                JtW = np.einsum('nak,nab->nkb', J, W)
                H[m] += np.einsum('nkb,nbl->nkl', JtW, J)
                g[m] += np.einsum('nkb,nb->nk', JtW, r)
                chi[m] += np.einsum('na,nab,nb->n', r, W, r)
                ok[m] &= np.all(np.isfinite(W), axis=(1, 2))
            ok &= invertible(H)
            if it < FUSION_ITERATIONS:
                X[ok] = X[ok] + np.linalg.solve(H[ok], g[ok][:, :, None])[:, :, 0]
        cov = np.full((N, 3, 3), np.nan)
        cov[ok] = np.linalg.inv(H[ok])
    return X, cov, chi, ok


def _innovation_batch(model: PredictionModel, left, X0, uv, seen, extra=None, arm_design=None,
                      gradient=False):
    """
    Return camera ``left``'s leave-one-out innovations over N samples: r (N, 2), S (N, 2, 2), d^2.

    ``X0`` (N, 3) the arm's points, ``uv`` and ``seen`` per other camera ((N, 2), (N,) bool),
    ``uv[left]`` the observations tested.  Without a joint covariance, each camera's own
    parameter covariance is added to its Sigma (the module docstring).  With one (C over the
    parameters theta of every camera), the fusion weights the other cameras by their image
    noise alone and the calibration's uncertainty is propagated with its correlations: at the
    fused point the implicit function theorem gives dX~/dtheta_o = -H^-1 J_o^T W_o J_theta_o,
    so with g the gradient of r_c,

        g_c = -J_theta_c,   g_o = J_c H^-1 J_o^T W_o J_theta_o,   S_c += g C g^T.

    The cameras' poses are far better known relative to one another than each on its own (the
    arm fixes the frame only to its own accuracy, and the frame moves them all together): the
    blocks alone would credit every prediction with the frame's uncertainty too.  d^2 is NaN
    where the fusion is singular or the point is behind the camera.  ``extra`` maps cameras
    to (N,) variances added to their image noise (:class:`View`).  The arm's point X^ + A g
    moves with its model's parameters g when the joint covariance has them (:data:`ARM`)
    and ``arm_design`` (N, 3, G) gives each view's A: dX~/dg = H^-1 A / s_arm^2, so
    g_arm = -J_c H^-1 A / s_arm^2.
    With ``gradient`` g (N, 2, P) is returned too, as a fourth value (None without a joint
    covariance).
    """
    joint = model.joint_covariance
    g = None
    extra = extra or {}
    others = {n: m for n, m in seen.items() if n != left}
    X, cov, _, ok = _fuse_batch(model, X0, {n: uv[n] for n in others}, others,
                                parameters=joint is None, extra=extra)
    N = X0.shape[0]
    with np.errstate(all='ignore'):
        u, J, Sigma, depth = _predict_batch(model, left, X, parameters=joint is None,
                                            extra=extra.get(left, 0.0))
        r = uv[left] - u
        S = Sigma + np.einsum('nak,nkl,nbl->nab', J, cov, J)
        if joint is not None:
            names, C = joint
            index = _joint_index(names)
            g = np.zeros((N, 2, len(names)))
            if left in index:
                g[:, :, index[left][1]] = -_parameter_jacobian(_project(model, left, X),
                                                               index[left][0])
            JH = np.einsum('nak,nkl->nal', J, np.nan_to_num(cov))
            for n, m in others.items():
                if n not in index or not np.any(m):
                    continue
                pj = _project(model, n, X[m])
                # The fusion's weight of camera n at these points: its image noise and
                # what the views add to it.
                w = 1.0 / (model.sigma_px[n] ** 2 + (extra[n][m] if n in extra else 0.0))
                Jt = _parameter_jacobian(pj, index[n][0])
                g[np.ix_(m, [0, 1], index[n][1])] += np.einsum(
                    'n,nal,nbl,nbp->nap', np.broadcast_to(w, (int(np.sum(m)),)), JH[m],
                    pj.d_point, Jt)
            if arm_design is not None and ARM in index:
                g[:, :, index[ARM][1]] -= np.einsum('nal,nlg->nag', JH, np.asarray(
                    arm_design, float)) / model.arm_sigma ** 2
            S = S + np.einsum('nap,pq,nbq->nab', g, np.asarray(C, float), g)
        d2 = np.einsum('na,nab,nb->n', r, _inv2(S), r)
    d2[~ok | ~(depth > 0) | ~np.isfinite(d2)] = np.nan
    if gradient:
        return r, S, d2, g
    return r, S, d2


def innovation(model: PredictionModel, X0, uvs: Dict[str, np.ndarray], camera, extra=None,
               arm_design=None):
    """
    Return (r (2,), S (2, 2), d^2) of ``camera``'s observation predicted from the rest.

    See the module docstring and :func:`_innovation_batch`; None when the camera is not in the
    model or not in ``uvs``, or when the rest cannot predict it.  ``extra``, ``arm_design``: as
    in :class:`View`.
    """
    if camera not in model.cameras or camera not in uvs:
        return None
    names = [n for n in uvs if n in model.cameras]
    uv = {n: np.asarray(uvs[n], float).reshape(1, 2) for n in names}
    r, S, d2 = _innovation_batch(model, camera, np.asarray(X0, float).reshape(1, 3), uv,
                                 {n: np.ones(1, bool) for n in names}, _batch_extra(extra, 1),
                                 None if arm_design is None else
                                 np.asarray(arm_design, float)[None])
    if not np.isfinite(d2[0]):
        return None
    return r[0], S[0], float(d2[0])


def joint_disagreement(model: PredictionModel, views, camera, scale=1.0, leave_worst=True):
    """
    Return (chi^2, dof) of ``camera``'s innovations over ``views`` taken together, or None.

    Each view's innovation r_i (:func:`_innovation_batch`) has covariance
    S_i = D_i + g_i C g_i^T, D_i what the image noise and the fused point put in, g_i C g_i^T
    what the calibration's parameter covariance C does.  The calibration's error is one error,
    common to every view: stacked, r = (r_1 .. r_n) has covariance

        Sigma = blockdiag(D_i) + G C G^T,   G = (g_1; ..; g_n),
        chi^2 = r^T Sigma^-1 r / ``scale``   (2 n degrees of freedom),

    where a sum of the d_i^2 counts a shift the calibration allows once per view (a young
    calibration, or one fitted to a few views a little off, predicts a whole region alike and
    a little wrong).  With ``leave_worst`` the view of largest d_i^2 is left out (2 n - 2):
    the disagreement must not rest on one view, as the CUSUM, which counts no view beyond its
    cap, does not (a lone detection pulled by clutter touching the marker).  Without a joint
    covariance the views are taken as independent (Sigma block-diagonal).  None with fewer
    than two views that can be predicted.
    """
    r, D, G, d2 = [], [], [], []
    C = None if model.joint_covariance is None else np.asarray(model.joint_covariance[1],
                                                               float)
    for v in views:
        if camera not in v.uvs or camera not in model.cameras:
            continue
        names = [n for n in v.uvs if n in model.cameras]
        got = _innovation_batch(
            model, camera, np.asarray(v.X0, float).reshape(1, 3),
            {n: np.asarray(v.uvs[n], float).reshape(1, 2) for n in names},
            {n: np.ones(1, bool) for n in names}, _batch_extra(v.extra, 1),
            None if v.arm_design is None else np.asarray(v.arm_design, float)[None],
            gradient=True)
        if not np.isfinite(got[2][0]):
            continue
        r.append(got[0][0])
        d2.append(got[2][0])
        # g is given exactly when the model has a joint covariance (C).
        G.append(got[3][0] if C is not None else np.zeros((2, 0)))
        D.append(got[1][0] - G[-1] @ C @ G[-1].T if C is not None else got[1][0])
    if leave_worst and len(r) > 2:
        worst = int(np.argmax(d2))
        r, D, G = (x[:worst] + x[worst + 1:] for x in (r, D, G))
    n = len(r)
    if n < 2:
        return None
    Sigma = np.zeros((2 * n, 2 * n))
    for i, Di in enumerate(D):
        Sigma[2 * i:2 * i + 2, 2 * i:2 * i + 2] = Di
    if C is not None:
        Gs = np.concatenate(G, axis=0)
        Sigma += Gs @ C @ Gs.T
    rs = np.concatenate(r)
    try:
        total = float(rs @ np.linalg.solve(Sigma, rs)) / scale
    except np.linalg.LinAlgError:
        return None
    return total, 2 * n


def statistics(model: PredictionModel, X0, uvs: Dict[str, np.ndarray],
               extra=None, arm_design=None) -> Dict[str, float]:
    """Return d^2 of every modelled camera in ``uvs`` (see :func:`innovation`)."""
    out = {}
    for name in uvs:
        got = innovation(model, X0, uvs, name, extra, arm_design)
        if got is not None and np.isfinite(got[2]):
            out[name] = got[2]
    return out


def _inv2(S):
    """Invert a stack of 2x2 matrices (N, 2, 2); non-invertible ones come back non-finite."""
    det = S[:, 0, 0] * S[:, 1, 1] - S[:, 0, 1] * S[:, 1, 0]
    out = np.empty_like(S)
    out[:, 0, 0], out[:, 1, 1] = S[:, 1, 1], S[:, 0, 0]
    out[:, 0, 1], out[:, 1, 0] = -S[:, 0, 1], -S[:, 1, 0]
    with np.errstate(divide='ignore', invalid='ignore'):
        return out / det[:, None, None]


def statistics_batch(model: PredictionModel, points, observations,
                     arm_design=None) -> Dict[str, np.ndarray]:
    """
    Return every modelled camera's d^2 over many samples: name -> (N,), NaN where not seen.

    The same leave-one-camera-out innovation as :func:`innovation` (the same Gauss-Newton
    fusion of the arm and the other cameras, ``FUSION_ITERATIONS`` steps, then the camera's
    prediction), computed for all samples at once: a per-sample loop spent 0.5 s in Python
    per solve on 300 samples, this one a few milliseconds.  Samples where a fusion is singular
    or the point is behind the camera are NaN, as :func:`statistics` leaves them out.
    ``arm_design`` (N, 3, G): each sample's arm design (:func:`_innovation_batch`).
    """
    X0 = np.asarray(points, float).reshape(-1, 3)
    N = X0.shape[0]
    names = [n for n in model.cameras if any(n in o for o in observations)]
    seen = {n: np.array([n in o for o in observations]) for n in names}
    uv = {n: np.array([np.asarray(o[n], float).reshape(2) if n in o else (np.nan, np.nan)
                       for o in observations]).reshape(N, 2) for n in names}
    out = {}
    for left in names:
        rows = np.flatnonzero(seen[left])
        if rows.size == 0:
            continue
        _, _, d2 = _innovation_batch(model, left, X0[rows], {n: uv[n][rows] for n in names},
                                     {n: seen[n][rows] for n in names}, None,
                                     None if arm_design is None else arm_design[rows])
        full = np.full(N, np.nan)
        full[rows] = d2
        out[left] = full
    return out


def reference_scales(model: PredictionModel, points, observations,
                     retained: Dict[str, float] = None) -> Dict[str, float]:
    """
    Return k_c^2 per camera from the calibration's own samples (module docstring).

    ``points`` (N, 3) the arm's points, ``observations`` a list of N dicts name -> uv (2,).
    ``retained``: name -> the share of camera c's residual degrees of freedom the fit left,
    rho_c = r_c / (2 n_c) with r_c its redundancy counted by leverage.  A fitted residual has
    E[e^2] = sigma^2 (1 - h): on the samples a camera was fitted to its misfits are pulled in by
    the share of them its parameters (and the points and the arm's model) absorbed, and a new
    view, which nothing was fitted to, is not.  So the scale is divided by rho_c:
    k_c^2 = median(d_c^2) / (2 ln 2) / rho_c.  Over many samples rho_c is near 1; on a first
    solve of 20 samples a model with many parameters leaves a fraction (0.15-0.23 measured on
    a two-camera cell), and without it the misfits of new views in another part of the
    workspace read 3-4 times their expectation and declared unchanged cameras changed.
    Counting the points' share too makes this conservative (the leave-one-out prediction
    re-fuses the point without the camera): a new view is tested at most as strictly as the
    fit's own residuals warrant.
    """
    out = {}
    for name, d2 in statistics_batch(model, points, observations).items():
        v = d2[np.isfinite(d2)]
        out[name] = float(np.median(v)) / MEDIAN_CHI2_2 if v.size >= MIN_REFERENCE else 1.0
        rho = (retained or {}).get(name, 1.0)
        if v.size >= MIN_REFERENCE and np.isfinite(rho) and 0.0 < rho < 1.0:
            out[name] /= rho
    return out


@dataclass
class ChangeEvent:
    """
    A declared change.

    ``kind``: 'camera' (``camera`` moved or changed its lens; ``fit`` says by how much), 'arm'
    (the arm or the marker changed: every camera sees it), 'unexplained', or 'disagreement'
    (one camera's views disagree but no new pose explains them: bad detections, not a change;
    nothing is retired); ``onset_ns`` the stamp of the first
    observation that disagreed, ``detected_ns`` the stamp at which the test fired;
    ``statistic`` the CUSUM that fired against ``threshold``;
    ``evidence`` what the attribution measured (chi^2 over its quantile per hypothesis).
    """

    kind: str
    camera: Optional[str]
    onset_ns: int
    detected_ns: int
    statistic: float
    threshold: float
    samples: int
    evidence: Dict[str, float] = field(default_factory=dict)
    fit: Optional['CameraChangeFit'] = None
    #: The predictor the change was found with (the changed camera's old calibration among
    #: the others): what the new views are later compared with, in the same frame.
    model: Optional['PredictionModel'] = None


@dataclass
class View:
    """
    One sample as the monitor sees it: stamp, the arm's point, camera name -> uv.

    ``extra`` maps cameras to a variance per axis (px^2) added to that camera's image noise in
    this view alone: what its point is known to beyond the calibration's image noise (a light
    correction carried to a place it was not measured at, see change_tracking.py).
    ``arm_design`` (3, G): how the arm's point moves with its error model's parameters (the
    :data:`ARM` rows of the joint covariance), or None.
    """

    stamp_ns: int
    X0: np.ndarray
    uvs: Dict[str, np.ndarray]
    extra: Dict[str, float] = field(default_factory=dict)
    arm_design: Optional[np.ndarray] = None


@dataclass
class CameraChangeFit:
    """
    A suspect camera refitted to its new views.

    ``rotation_deg``, ``translation_mm`` the pose change (rotation angle, optical-centre shift),
    ``focal_percent`` the focal-length change; ``ratio`` the refit's chi^2 over its quantile at
    the false-alarm probability (at most 1: the change explains the views); ``used`` the
    stamps of the views.
    """

    rotation_deg: float
    translation_mm: float
    focal_percent: float
    ratio: float
    used: List[int]
    old_d2: np.ndarray = None       # each view's whitened residual^2, the old camera
    new_d2: np.ndarray = None       # and the refitted one
    depth_m: float = float('nan')   # the views' median depth in the old camera

    @property
    def plausible(self) -> bool:
        """Return True if the change is one a camera can undergo (MAX_ROTATION_DEG etc.)."""
        return bool(self.rotation_deg <= MAX_ROTATION_DEG
                    and abs(self.focal_percent) <= MAX_FOCAL_PERCENT
                    and 1e-3 * self.translation_mm <= MAX_SHIFT_FRACTION * self.depth_m)

    @property
    def explains(self) -> bool:
        """Return True if the refit explains the views (ratio <= 1) with a plausible change."""
        return bool(self.ratio <= 1.0 and self.plausible)


def explain_by_camera_change(model: PredictionModel, camera, seen, scales=None,
                             false_alarm=1e-6, iterations=8, fit_focal=True) -> CameraChangeFit:
    """
    Refit ``camera``'s pose and focal length to its views in ``seen``; say if that explains them.

    Each view's point is fused from the arm and the other cameras (:func:`fuse`), with
    covariance P_i; the residual r_i = uv_i - pi(R(w) , t + dt, s f; X_i) is whitened by
    S_i = k^2 s^2 I + J_i P_i J_i^T, and Gauss-Newton finds (w, dt, s) from the old camera.
    The 2 n - 7 degrees of freedom left judge the fit; without ``fit_focal`` the focal length
    stays (2 n - 6).
    """
    cam0 = model.cameras[camera]
    k2 = 1.0 if scales is None else scales.get(camera, 1.0)
    pts, uv, covs, used, added = [], [], [], [], []
    for s in seen:
        f = fuse(model, s.X0, {n: v for n, v in s.uvs.items() if n != camera}, extra=s.extra)
        if f is None:
            continue
        pts.append(f.X)
        covs.append(f.cov)
        uv.append(s.uvs[camera])
        used.append(s.stamp_ns)
        added.append(s.extra.get(camera, 0.0))
    X, uv, P = np.array(pts).reshape(-1, 3), np.array(uv).reshape(-1, 2), np.array(covs)
    noise = (model.sigma_px[camera] ** 2 * k2 + np.array(added, float))[:, None, None] * \
        np.eye(2)
    n = len(X)

    def whitened(c, sc):
        intr = np.array([c.fx * sc, c.fy * sc, c.cx, c.cy])
        pj = project_with_jacobians(intr, c.dist, c.rotation, c.translation, X)
        S = noise + pj.d_point @ P @ np.transpose(pj.d_point, (0, 2, 1))
        L = np.linalg.cholesky(np.linalg.inv(S))            # L L^T = S^-1
        Lt = np.transpose(L, (0, 2, 1))
        r = np.einsum('nij,nj->ni', Lt, uv - pj.uv)
        J = np.concatenate([pj.d_pose, (pj.uv - intr[2:])[:, :, None] / sc], axis=2)
        return r.reshape(-1), np.einsum('nij,njk->nik', Lt, J).reshape(-1, 7)

    def refine(cam):
        scale = 1.0
        for _ in range(iterations):
            r, J = whitened(cam, scale)
            if not fit_focal:
                J = J[:, :6]
            step = np.linalg.lstsq(J, r, rcond=None)[0]
            if not fit_focal:
                step = np.append(step, 0.0)
            cam.apply_pose_increment(step[:3], step[3:6])
            scale += step[6]
            if np.max(np.abs(step[:6])) < 1e-10 and abs(step[6]) < 1e-12:
                break
        r, _ = whitened(cam, scale)
        return cam, scale, r

    r_old, _ = whitened(cam0, 1.0)
    # From the old pose (a knock of a few degrees), and from a PnP with the old lens (a camera
    # moved further than Gauss-Newton reaches from there); the better fit is kept.
    starts = [cam0.copy()]
    if n >= 4:
        ok, rvec, tvec = cv2.solvePnP(X.reshape(-1, 1, 3), uv.reshape(-1, 1, 2), cam0.K,
                                      cam0.dist, flags=cv2.SOLVEPNP_EPNP)
        if ok:
            start = cam0.copy()
            start.rotation = cv2.Rodrigues(rvec)[0]
            start.translation = np.asarray(tvec, float).reshape(3)
            starts.append(start)
    fits = []
    for start in starts:
        try:
            fits.append(refine(start))
        except np.linalg.LinAlgError:
            continue
    if not fits:
        return CameraChangeFit(float('nan'), float('nan'), float('nan'), float('inf'), used,
                               np.sum(r_old.reshape(-1, 2) ** 2, axis=1),
                               np.full(n, np.inf))
    cam, scale, r = min(fits, key=lambda f: float(f[2] @ f[2]) if np.all(np.isfinite(f[2]))
                        else np.inf)
    dof = 2 * n - (7 if fit_focal else 6)
    ratio = (float(r @ r) / float(chi2.isf(false_alarm, dof)) if dof > 0 else float('nan'))
    angle = np.linalg.norm(Rotation.from_matrix(cam.rotation @ cam0.rotation.T).as_rotvec())
    depth = float(np.median((X @ cam0.rotation.T + cam0.translation)[:, 2])) if n else np.nan
    return CameraChangeFit(float(np.degrees(angle)),
                           float(1e3 * np.linalg.norm(cam.center - cam0.center)),
                           float(100.0 * (scale - 1.0)), ratio, used,
                           np.sum(r_old.reshape(-1, 2) ** 2, axis=1),
                           np.sum(r.reshape(-1, 2) ** 2, axis=1), depth)


def size_change(model: PredictionModel, camera, seen, scales=None, false_alarm=1e-6,
                own_scale=False):
    """
    Return (what, fit) for a changed camera's new views ``seen`` against its old calibration.

    Both refits of :func:`explain_by_camera_change` are made: with the focal length free and
    held.  The lens changed ('lens') if freeing it lowers chi^2 by more than chance allows at
    ``false_alarm``: an F test, gain / (chi^2_free / (2 n - 7)) against F(1, 2 n - 7).  The
    denominator matters: over many views the old calibration is itself off by more than the
    noise somewhere in the new region (its intrinsics are held), and the focal length, free,
    absorbs part of that; the gain must stand out against the misfit the refit leaves, not
    against the image noise alone.  A focus change and a move along the optical axis look
    alike over a shallow workspace: then it is called 'pose', the size being what a pose
    alone would have to change by.

    Without ``own_scale`` the residual variance factor is taken as 1 where it is below (the
    monitor's refits: at detection a free focal length lets a refit slide along the axis, and
    the conservative side is wanted).  With it the test is the textbook F test, free of the
    predicted noise's scale (the sizing of a declared change: the predictor's whitening of
    points fused from the arm and the other cameras overstates a refit's misfit 2-50 times on
    the simulated cells, which hid every 0.5 % refocus behind the noise taken as 1).
    """
    free = explain_by_camera_change(model, camera, seen, scales, false_alarm)
    held = explain_by_camera_change(model, camera, seen, scales, false_alarm, fit_focal=False)
    gain = float(np.sum(held.new_d2) - np.sum(free.new_d2))
    dof = 2 * len(free.used) - 7
    if dof > 0 and np.isfinite(gain):
        factor = float(np.sum(free.new_d2)) / dof
        if not own_scale:
            factor = max(1.0, factor)
        if factor > 0 and gain / factor > float(f_dist.isf(false_alarm, 1, dof)):
            return 'lens', free
    return 'pose', held


def _rises_later(d2, alpha=CONFIRM_ALPHA) -> bool:
    """
    Return True if the misfits ``d2`` (n,) step up after their first view, beyond chance.

    Under one level each d2 is about exponential (chi^2 with 2 degrees of freedom times a
    scale); the likelihood ratio of a step from mean m1 (views before k) to m2 > m1 (from k on)
    against one mean m is 2 (n ln m - k ln m1 - (n - k) ln m2), compared with chi^2_1 at
    ``alpha`` at each split k = 1 .. n - 1 (the largest of n - 1 ratios exceeds it more often
    than ``alpha``; a false "rises" costs the suspect one more view of waiting).
    """
    x = np.maximum(np.asarray(d2, float), 1e-12)
    n = x.size
    if n < 2 or not np.all(np.isfinite(x)):
        return False
    m = float(np.mean(x))
    c = np.cumsum(x)
    k = np.arange(1, n)
    m1, m2 = c[:-1] / k, (c[-1] - c[:-1]) / (n - k)
    lr = 2.0 * (n * np.log(m) - k * np.log(m1) - (n - k) * np.log(m2))
    return bool(np.any((m2 > m1) & (lr > float(chi2.isf(alpha, 1)))))


class ChangeMonitor:
    """
    The sequential test of every camera against a :class:`PredictionModel`.

    :meth:`observe` takes each new sample; it returns a :class:`ChangeEvent` when a change is
    declared.  After a camera's change it is no longer tested until :meth:`reset` gives a new
    calibration; the others go on (an arm change is judged by the caller from repeated events).

    The scale k_c^2 comes first from the calibration's own samples (``scales``); as new views
    are tested it becomes the larger of that and the median scale of the camera's recent
    statistics (the last :data:`SCALE_WINDOW` but the latest :data:`LAG_VIEWS`, carried over
    from the monitor this one replaces).  Views the calibration was not fitted to are predicted
    a little worse than its covariance says wherever the images hold errors the model leaves
    out (a detector's bias that varies over the image, an arm model that describes the arm in
    part): measured on the bundled demo bag, the median of d^2 / k^2 was 2 to 4 times that of
    chi^2_2 on new views while the calibration's own samples set k.  A test whose scale
    follows its recent past keeps its stated false-alarm rate there; what it gives up is a
    change slower than the window (a creeping mount), which the refits then follow.
    """

    def __init__(self, model: PredictionModel, scales: Dict[str, float],
                 settings: ChangeSettings = None):
        self.model = model
        self.scales = {n: max(float(scales.get(n, 1.0)), 1e-12) for n in model.cameras}
        self.settings = (settings or ChangeSettings()).validate()
        s = self.settings
        self.threshold = threshold(s.reference, s.false_alarm)
        self.cap = cap_of(s.reference)
        #: camera -> [S, stamp of the first observation of the current climb]
        self.windows = {n: [0.0, None] for n in model.cameras}
        self.recent: deque = deque(maxlen=200)
        self.paused = False
        self.tested = 0
        self.suspect: Optional[dict] = None
        #: Alarms the views since their onset did not confirm (:meth:`_attribute`).
        self.unconfirmed = 0
        #: camera -> the latest raw statistics d^2 (for the running scale)
        self.history = {n: deque(maxlen=SCALE_WINDOW + LAG_VIEWS) for n in model.cameras}
        #: the current place's first arm point, and per camera (S before it, its increments)
        self._place = None
        self._place_terms: Dict[str, list] = {}

    def carry_over(self, old: 'ChangeMonitor'):
        """Take the recent statistics of the monitor this one replaces (its cameras only)."""
        for name, h in old.history.items():
            if name in self.history:
                self.history[name].extend(h)

    def scale(self, name) -> float:
        """Return camera ``name``'s current k^2 (the class docstring)."""
        h = list(self.history.get(name, ()))[:-LAG_VIEWS]
        if len(h) < MIN_REFERENCE:
            return self.scales[name]
        return max(self.scales[name], float(np.median(h)) / MEDIAN_CHI2_2)

    def current_scales(self) -> Dict[str, float]:
        """Return every camera's current k^2."""
        return {n: self.scale(n) for n in self.scales}

    def observe(self, X0, uvs: Dict[str, np.ndarray], stamp_ns: int,
                extra: Dict[str, float] = None, arm_design=None) -> Optional[ChangeEvent]:
        """
        Test one new sample (arm point ``X0``, name -> uv); return an event or None.

        ``extra``: name -> a variance per axis (px^2) added to that camera's image noise in
        this sample; ``arm_design`` (3, G) the arm's design there (:class:`View`).
        """
        if self.paused or not self.model.cameras:
            return None
        uvs = {n: np.asarray(uv, float).reshape(2) for n, uv in uvs.items()
               if n in self.model.cameras}
        if not uvs:
            return None
        X0 = np.asarray(X0, float).reshape(3)
        extra = {n: float(v) for n, v in (extra or {}).items() if n in uvs and v > 0}
        seen = View(int(stamp_ns), X0, uvs, extra, arm_design)
        self.recent.append(seen)
        self.tested += 1
        if self.suspect is not None:
            return self._confirm(seen)
        stats = statistics(self.model, X0, uvs, extra, arm_design)
        if self._place is None or np.linalg.norm(X0 - self._place) >= SAME_PLACE:
            self._place, self._place_terms = X0, {}
        fired = None
        for name, d2 in stats.items():
            w = self.windows[name]
            g = min(d2 / self.scale(name), self.cap) - self.settings.reference
            self.history[name].append(d2)
            base, terms = self._place_terms.setdefault(name, [w[0], []])
            terms.append(g)
            new = max(0.0, base + float(np.mean(terms)))
            if new > 0 and w[0] == 0.0:
                w[1] = int(stamp_ns)
            w[0] = new
            if fired is None and w[0] > self.threshold:
                fired = (name, w[1], w[0])
        if fired is None:
            return None
        name, onset, stat = fired
        since = [s for s in self.recent if s.stamp_ns >= onset]
        kind, camera, evidence = self._attribute(since, name)
        if kind is None:
            # The views since the onset agree with the calibration at the false-alarm
            # probability: the CUSUM climbed on a disagreement too weak to be anything (a
            # region the model describes a little worse).  Not a change; that camera starts
            # again.
            self._start_again(name)
            return None
        if kind == 'unexplained' and (len(since) < CONFIRM_OBSERVATIONS + ONSET_SLACK or (
                evidence.get('ambiguous') and len(since) < MAX_SUSPECT_VIEWS)):
            # Too few views yet to tell one camera from another (a small move, one that began
            # inside the climb, or two cameras that each explain it so far): the CUSUM stays
            # up and asks again at the next view.
            return None
        if kind == 'camera':
            # Confirm before declaring: a moved camera's new views are explained by a new
            # pose (and focal length); a burst of bad detections is not.
            self.suspect = dict(camera=camera, onset=onset, statistic=stat, evidence=evidence,
                                seen=[s for s in since if camera in s.uvs], waited=0)
            return self._confirm(None)
        event = ChangeEvent(kind, camera, onset, int(stamp_ns), stat, self.threshold,
                            len(since), evidence)
        self._clear()
        return event

    @property
    def busy(self):
        """Return True while a camera's statistics climb or a suspect is being judged."""
        return self.suspect is not None or any(w[0] > self.settings.reference
                                               for w in self.windows.values())

    def _clear(self):
        self._place, self._place_terms = None, {}
        for w in self.windows.values():
            w[0], w[1] = 0.0, None
        self.recent.clear()
        self.suspect = None

    def _confirm(self, seen: Optional[View]) -> Optional[ChangeEvent]:
        """Collect the suspect camera's views; once there are enough, explain them or not."""
        sus = self.suspect
        camera = sus['camera']
        if seen is not None and camera in seen.uvs:
            sus['seen'].append(seen)
            sus['waited'] += 1
        if len(sus['seen']) < CONFIRM_OBSERVATIONS + ONSET_SLACK:
            return None
        scales = self.current_scales()
        fit = self._refit(camera, sus['seen'], scales)
        # The CUSUM's climb may start on old views that happened to disagree: the change
        # point is the split that explains the views best, the views before it by the old
        # camera and those after by the refitted one (at least CONFIRM_OBSERVATIONS of them).
        best, best_cost = 0, float(np.sum(fit.new_d2))
        last = len(sus['seen']) - CONFIRM_OBSERVATIONS
        for k in range(1, last + 1):
            f = self._refit(camera, sus['seen'][k:], scales)
            cost = float(np.sum(fit.old_d2[:k]) + np.sum(f.new_d2))
            if cost < best_cost:
                best, best_cost = k, cost
        if best > 0:
            sus['seen'] = sus['seen'][best:]
            sus['onset'] = sus['seen'][0].stamp_ns
            fit = self._refit(camera, sus['seen'], scales)
        if (0 < best == last or _rises_later(fit.old_d2)) and \
                sus['waited'] < MAX_SUSPECT_VIEWS:
            # The change point is the latest the search may place, or the old calibration's
            # misfit rises again after it: the change may have begun later still, and a
            # refit over views from before it (a rigid refit absorbs a few of them) would
            # carry them into the new epoch.  One more view lets the search look further;
            # the patience counts from the CUSUM's firing (a climb may have begun many views
            # before the change).
            return None
        # A refit explains views that did not move as well as views that did: the views from
        # the change point on must also disagree with the old camera, as the test itself
        # sees them (k^2 and the joint covariance) but taken together, the calibration's
        # error being common to them, and not on one view alone (joint_disagreement), at
        # the false-alarm rate.
        disagree = True
        if fit.explains:
            got = joint_disagreement(self.model, sus['seen'], camera, self.scale(camera))
            disagree = got is None or got[0] > float(chi2.isf(self.settings.false_alarm,
                                                              got[1]))
        if not (fit.explains and disagree) and len(sus['seen']) < MAX_SUSPECT_VIEWS:
            # Not explained, or too little disagreement taken together, yet: wait while the
            # latest views still disagree with the old calibration one by one (the change
            # may have begun after the climb did; a small change, a 0.5 % refocus near the
            # image centre, shows over more views), keeping the suspect's change point
            # rather than a new climb's, views later.
            latest = fit.old_d2[-CONFIRM_OBSERVATIONS:]
            if float(np.sum(latest)) > float(chi2.isf(self.settings.false_alarm,
                                                      2 * len(latest))):
                return None
        if fit.explains and not disagree:
            # The climb was a disagreement too weak to be a change.
            self.suspect = None
            self._start_again(camera)
            return None
        stamp = sus['seen'][-1].stamp_ns
        evidence = dict(sus['evidence'])
        evidence['unexplained after refitting the camera'] = fit.ratio
        self._clear()
        if not fit.plausible:
            evidence.update({'implausible refit: rotation deg': fit.rotation_deg,
                             'implausible refit: centre mm': fit.translation_mm,
                             'implausible refit: focal %': fit.focal_percent})
        if fit.explains:
            event = ChangeEvent('camera', camera, sus['onset'], stamp, sus['statistic'],
                                self.threshold, len(fit.used), evidence, fit, self.model)
            self.model = self.model.without(camera)
            self.windows.pop(camera, None)
            return event
        return ChangeEvent('disagreement', camera, sus['onset'], stamp, sus['statistic'],
                           self.threshold, len(fit.used), evidence, fit)

    def _start_again(self, camera):
        """Count a climb of ``camera``'s CUSUM that was no change, and start it again."""
        self.unconfirmed += 1
        self.windows[camera][0], self.windows[camera][1] = 0.0, None
        self._place_terms.pop(camera, None)

    def _refit(self, camera, seen, scales) -> CameraChangeFit:
        """
        Refit ``camera`` to ``seen``: its pose, and its focal length where the views ask for it.

        The focal length is freed only when that lowers chi^2 beyond chance
        (:func:`size_change`'s F test).  Freed always, it and a move along the optical axis
        trade off over a shallow workspace, and a refit could explain a disagreement of a
        pixel by sliding along that direction: on a lamp-lit, textured two-camera recording
        read by intensity centroids, a camera "moved" by 344 mm and 1.5 deg to explain views
        about a pixel off, where the pose alone explained nothing.
        """
        return size_change(self.model, camera, seen, scales, self.settings.false_alarm)[1]

    def _agreement(self, seen: List[View], leave_out=None, use_arm=True, alpha=None):
        """chi^2 / its quantile at the false-alarm probability, over ``seen`` (nan: untestable)."""
        total, dof = self._chi2(seen, leave_out, use_arm)
        if dof == 0:
            return float('nan')
        return total / float(chi2.isf(alpha or self.settings.false_alarm, dof))

    def _chi2(self, seen: List[View], leave_out=None, use_arm=True):
        """(chi^2, dof) of the arm and the cameras but ``leave_out`` agreeing over ``seen``."""
        total, dof, scales = 0.0, 0, self.current_scales()
        for s in seen:
            uvs = {n: uv for n, uv in s.uvs.items() if n != leave_out}
            got = agreement(self.model, s.X0, uvs, scales, use_arm=use_arm, extra=s.extra,
                            arm_design=s.arm_design)
            if got is None or got[1] <= 0:
                continue
            total += got[0]
            dof += got[1]
        return total, dof

    def _clearly_best(self, seen: List[View], candidates):
        """
        Return (camera, F) if leaving one camera out agrees clearly better than any other, or None.

        Asked of two cameras (:meth:`_attribute`).  Two cameras and an arm known to
        millimetres each agree with the arm alone, view by view, whichever of them changed,
        and each one's refit explains its views: a new pose of either camera absorbs a few
        views.  But leaving out the camera that changed leaves views that agree; leaving out
        the other leaves the changed camera's views against the arm.  With chi^2_n the
        agreement without camera n over d_n degrees of freedom, the camera b of least
        chi^2_b / d_b is named if every other o has

            F = (chi^2_o / d_o) / (chi^2_b / d_b) > F^-1(1 - alpha; d_o, d_b),

        alpha = :data:`CONFIRM_ALPHA`: with nothing changed (or b changed) the ratio is at most
        that of two chi^2 variables (positively correlated through the arm's points they
        share, which narrows it), and a scale common to both (an arm's error over- or
        under-stated) cancels.  The camera is then confirmed as any other (its views must
        disagree with its old calibration at the false-alarm rate).
        """
        sums = {n: self._chi2(seen, leave_out=n) for n in candidates}
        sums = {n: v for n, v in sums.items() if v[1] > 0}
        if len(sums) < 2:
            return None
        best = min(sums, key=lambda n: sums[n][0] / sums[n][1])
        cb, db = sums[best]
        if cb <= 0:
            return None
        ratios = [((c / d) / (cb / db), float(f_dist.isf(CONFIRM_ALPHA, d, db)))
                  for n, (c, d) in sums.items() if n != best]
        if all(f > needed for f, needed in ratios):
            return best, min(f for f, _ in ratios)
        return None

    def _attribute(self, seen: List[View], fired: str):
        """
        Say which change explains ``seen``: (kind, camera, evidence) (module docstring).

        Nothing (kind None) if the views agree with the calibration as a whole: the chi^2 of
        the arm and every camera together within its quantile at the false-alarm probability.
        A camera is named only if leaving it out explains the views and leaving out any other
        does not: when several exclusions explain them, the disagreement is too weak to point
        anywhere (an arm error a little beyond its model, views of several cameras a little
        off) unless exactly one of those cameras' refits explains it, or, of two cameras, leaving
        one out agrees clearly better than leaving out the other (:meth:`_clearly_best`);
        otherwise it is 'unexplained'.
        With one camera there is nothing to compare it with: it is the suspect, and the refit
        decides.
        """
        cams = sorted({n for s in seen for n in s.uvs})
        evidence = {'all': self._agreement(seen, alpha=CONFIRM_ALPHA)}
        if np.isfinite(evidence['all']) and evidence['all'] <= 1.0:
            return None, None, evidence
        evidence.update({f'without {n}': self._agreement(seen, leave_out=n) for n in cams})
        free = evidence['cameras without the arm'] = self._agreement(seen, use_arm=False)
        if len(cams) == 1:
            return 'camera', cams[0], evidence
        testable = {n: evidence[f'without {n}'] for n in cams
                    if np.isfinite(evidence[f'without {n}'])}
        ok = {n: v for n, v in testable.items() if v <= 1.0}
        if len(ok) == 1 and len(testable) > 1:
            return 'camera', next(iter(ok)), evidence
        if len(ok) > 1 and len(seen) >= CONFIRM_OBSERVATIONS + ONSET_SLACK:
            # More than one exclusion leaves agreement, view by view: a disagreement too weak
            # to point at one camera (two cameras and an arm known to millimetres predict each
            # other loosely; a few views of several cameras each a little off).
            # A camera that moved is one rigid change across its views: refit each to its
            # views (but the first few, which may precede the change), and if exactly one
            # refit explains them, it is that one.
            scales = self.current_scales()
            for n in ok:
                views = [v for v in seen if n in v.uvs][ONSET_SLACK:]
                fit = (self._refit(n, views, scales)
                       if len(views) >= CONFIRM_OBSERVATIONS else None)
                evidence[f'refit {n}'] = fit.ratio if fit is not None else float('nan')
                if fit is not None and not fit.plausible:
                    evidence[f'refit {n}'] = float('inf')
            explained = [n for n in ok if evidence[f'refit {n}'] <= 1.0]
            # A camera with too few views to be refitted is not ruled out: the explanation
            # is unique only among cameras that were all tried.
            untried = [n for n in ok if np.isnan(evidence[f'refit {n}'])]
            if len(explained) == 1 and not untried:
                return 'camera', explained[0], evidence
            # Only between two cameras, and only where they disagree with each other.  With
            # three or more, every exclusion leaves cameras that place the point without the
            # arm, and several exclusions agreeing is a weak disagreement spread over them (a
            # likelihood-ratio choice among them named cameras falsely, docs/ARCHITECTURE.md).
            # And a change of the arm or marker along one camera's rays leaves that camera
            # agreeing with the arm and the other not, as a change of the other would, but
            # the two cameras agree without the arm.
            clear = (self._clearly_best(seen, ok)
                     if len(cams) == 2 and np.isfinite(free) and free > 1.0 else None)
            if clear is not None:
                evidence['agreement without it, F against the next'] = clear[1]
                if clear[0] in explained:
                    return 'camera', clear[0], evidence
            evidence['ambiguous'] = float(len(explained) + len(untried) > 1)
        if not ok and np.isfinite(free) and free <= 1.0:
            return 'arm', None, evidence
        return 'unexplained', fired, evidence

    def reset(self, model: PredictionModel, scales: Dict[str, float]):
        """Start again on a new calibration."""
        self.__init__(model, scales, self.settings)
