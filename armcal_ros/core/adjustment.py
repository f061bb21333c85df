"""
Levenberg-Marquardt bundle adjustment of cameras and robot-measured points.

Unknowns: every camera's intrinsics [fx, fy, cx, cy], its free distortion terms and its pose
increment (w, dt) (see :mod:`armcal_ros.core.camera`), and - unless the prior is ``fixed`` - the
true points X.  Objective (twice the negative log posterior, up to a constant)::

    F = sum_ij rho(|x_ij - pi(c_j, X_i)|^2) / s_px^2  +  (X - X^)^T P (X - X^)

with rho the robust loss of :mod:`armcal_ros.core.robust` and P the prior precision of
:mod:`armcal_ros.core.priors`.  Gauss-Newton normal equations, in the usual bundle-adjustment
blocks (c: cameras, x: points)::

    [U   W] [dc]     [g_c]
    [W^T V] [dx] = - [g_x]

U is block diagonal over cameras (an observation involves one camera and one point).  V holds the
image terms as 3x3 blocks plus P: block diagonal for ``independent`` (then V^-1 costs O(N)), dense
for the exact ``correlated`` prior (O(N^3) Cholesky - the reference form).  Either way the points
are eliminated by the Schur complement S = U - W V^-1 W^T, S dc = -g_c + W V^-1 g_x,
dx = V^-1 (-g_x - W^T dc).

Levenberg-Marquardt with Marquardt's scaling (Marquardt, 1963; as in Thompson et al., 2004, who
multiply the diagonal of the curvature matrix by (1 + beta)): the damped system replaces every
diagonal entry h_kk by h_kk (1 + lambda), which makes the step invariant to the units of the
parameters - they span about six orders of magnitude here (pixels of focal length against
radians of rotation).  lambda follows Nielsen's (1999) gain-ratio rule.

Convergence: the relative decrease of F below ``ftol``, or the scaled step below ``xtol``, or the
scaled gradient below ``gtol``; failure when ``max_iterations`` is reached.  After convergence,
observations whose pixel residual exceeds ``gate_sigmas`` robust standard deviations (and
``gate_min_px``) are gated out and the problem is re-solved from the current estimate until the
inlier set stops changing.

Parameter uncertainty: the covariance of the camera parameters is S^-1 at the solution (the
Laplace approximation; F is already whitened by s_px and P, so no residual-variance rescaling).

Why by hand rather than a library: the Schur complement over 3x3 point blocks, the dense
correlated prior inside V, the global (kinematic, field) parameters coupled to every point, and
the camera covariance and leverages from the same factorisation are the structure of this
problem.  Measured like with like (bench/solver.py: the same objective, start and tolerance,
every solver at the same minimum; docs/BENCHMARKS.md, "solver-speed"): scipy's least_squares
with the analytic sparse Jacobian is 6-11 x slower at N >= 1000 (it solves the normal equations by
LSMR); Ceres through COLMAP's compiled bundle adjuster, which has none of the priors, is 3-7 x
faster at N = 100 (where this module's per-iteration cost is Python's, about 0.6 ms) and from
N = 1000 on is matched or beaten: the per-iteration work is a few batched numpy passes and two
GEMMs, not an interpreter loop.
"""

import time
from copy import copy
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence

import numpy as np
from scipy.linalg import cho_factor, cho_solve, lapack, LinAlgError
from scipy.spatial.transform import Rotation

from armcal_ros.core.camera import (Camera, DISTORTION_NAMES, INTRINSIC_NAMES,
                                    project_with_jacobians)
from armcal_ros.core.geometry import skew
from armcal_ros.core.intrinsics_prior import IntrinsicsPrior
from armcal_ros.core.kernels import kernel_matrix
from armcal_ros.core.priors import PointPrior, PriorSettings
from armcal_ros.core.robust import check_loss, rho, weights

#: How closely two cameras that share a lens (SolverSettings.shared_lens) are held together:
#: (fx, fy, cx, cy in px; the distortion terms).  Far below what a camera's views resolve (a
#: focal length's standard deviation is 0.1-1 px, k1's 1e-4-1e-2), far above the doubles'
#: resolution beside them: the pair is one lens to the solver without a second layout.
SHARED_LENS_SIGMA = (0.01, 1e-5)
#: How closely two cameras that share a pose (SolverSettings.shared_pose) are held together:
#: (rotation rad, translation m).  A camera's rotation is known to 1e-3-1e-2 rad and its
#: translation to 1e-3-1e-2 m here; 1e-5 is a hundred times tighter, and a tie of precision
#: 1e10 beside image terms of 1e9-1e12 costs nothing in conditioning.
SHARED_POSE_SIGMA = (1e-5, 1e-5)

# Nielsen (1999) shrinks lambda by at most 3 per good step; with steps that match the model well
# a faster shrink saves the long linear tail after an early blow-up (measured: 50 -> 20
# iterations from a DLT start).
LAMBDA_MIN_FACTOR = 1.0 / 3.0


@dataclass
class Observations:
    """
    Image observations: observation m is point ``point[m]`` seen by ``camera[m]`` at ``uv[m]``.

    Shapes: camera (M,) int, point (M,) int, uv (M, 2) pixels.
    """

    camera: np.ndarray
    point: np.ndarray
    uv: np.ndarray

    def __post_init__(self):
        self.camera = np.asarray(self.camera, dtype=np.int64).reshape(-1)
        self.point = np.asarray(self.point, dtype=np.int64).reshape(-1)
        self.uv = np.asarray(self.uv, dtype=float)
        m = self.camera.shape[0]
        if self.point.shape != (m,):
            raise ValueError(f'observations.point must have shape ({m},), got {self.point.shape}')
        if self.uv.shape != (m, 2):
            raise ValueError(f'observations.uv must have shape ({m}, 2), got {self.uv.shape}')
        if not np.all(np.isfinite(self.uv)):
            raise ValueError('observations.uv contains NaN or inf')

    def __len__(self):
        return self.camera.shape[0]

    def subset(self, mask):
        """Return the observations selected by a boolean mask or index array."""
        return Observations(self.camera[mask], self.point[mask], self.uv[mask])


#: Observations per camera whose leverage is computed; above it an even subsample estimates
#: the camera's sum (:meth:`_Problem.leverages`).
LEVERAGE_SAMPLE = 2000


@dataclass
class SolverSettings:
    """
    Settings of the adjustment (defaults and their reasons are in the README).

    pixel_sigma: image noise s_px (px).  free_distortion: which plumb_bob terms are estimated.
    loss / loss_scale: robust loss and its scale (px).  gate_sigmas / gate_min_px: outlier gate.
    intrinsics: camera name -> :class:`~armcal_ros.core.intrinsics_prior.IntrinsicsPrior`, the
    cameras whose intrinsics are given (held fixed or under a prior); the others are estimated.
    """

    pixel_sigma: float = 0.5
    #: Estimate the image noise (pixel_sigma is then the starting value): True for every
    #: model (:func:`~armcal_ros.core.calibration.calibrate`), False never (auto too uses
    #: pixel_sigma), None only where ``auto`` needs it for its evidence.
    estimate_noise: Optional[bool] = None
    free_distortion: Sequence[str] = ('k1', 'k2', 'p1', 'p2')
    loss: str = 'huber'
    loss_scale: float = 2.0
    gate_sigmas: float = 5.0
    gate_min_px: float = 1.0
    max_gate_rounds: int = 3
    max_iterations: int = 100
    ftol: float = 1e-8
    xtol: float = 1e-8
    gtol: float = 1e-10
    initial_lambda: float = 1e-3
    intrinsics: Dict[str, IntrinsicsPrior] = field(default_factory=dict)
    #: Standard deviations (k1, k2, p1, p2, k3) of a weak zero-mean prior on the free
    #: distortion terms of every camera whose intrinsics are estimated; None: no prior.  Why:
    #: a camera whose views cover a corner of its image does not determine its distortion
    #: over the rest, and a young solve can trade a wild k2 for its rotation (measured on the
    #: simulator's desk-4cam cell after 20 samples: k2 47 against 0.04 true, the camera turned
    #: 8.4 deg; docs/BENCHMARKS.md, *changes*).  A plumb_bob lens that is not a fisheye moves
    #: its image corners (normalised radius about 0.5) by well under 30 %: |k1|, |k2|, |k3|
    #: about 1 at most, decentring terms p1, p2 under 0.01.  One standard deviation at those
    #: sizes never binds a camera whose views spread over its image (on the demo bag the
    #: terms' own standard deviations are 0.0001-0.02).
    distortion_sigma: Optional[Sequence[float]] = (1.0, 1.0, 0.1, 0.1, 1.0)
    #: camera name -> the camera whose lens it has: the same camera in an earlier epoch, its
    #: pose changed by a knock but not its lens.  The two cameras' fx, fy, cx, cy and free
    #: distortion terms are held equal (to within SHARED_LENS_SIGMA); each keeps its own pose.
    shared_lens: Dict[str, str] = field(default_factory=dict)
    #: camera name -> the camera whose pose it has: the same camera in an earlier epoch, its
    #: lens changed by a refocus or a zoom but not its pose.  The two cameras' rotations and
    #: translations are held equal (to within SHARED_POSE_SIGMA); each keeps its own lens.
    shared_pose: Dict[str, str] = field(default_factory=dict)

    def validate(self):
        """Raise ValueError naming the first bad setting; return self."""
        if not self.pixel_sigma > 0:
            raise ValueError(f'pixel_sigma must be > 0, got {self.pixel_sigma}')
        bad = [d for d in self.free_distortion if d not in DISTORTION_NAMES]
        if bad:
            raise ValueError(f'free_distortion has unknown terms {bad}; '
                             f'allowed: {DISTORTION_NAMES}')
        check_loss(self.loss, self.loss_scale)
        if not self.gate_sigmas > 0:
            raise ValueError(f'gate_sigmas must be > 0, got {self.gate_sigmas}')
        if self.distortion_sigma is not None:
            ds = np.asarray(self.distortion_sigma, float)
            if ds.shape != (len(DISTORTION_NAMES),) or not np.all(ds > 0):
                raise ValueError(f'distortion_sigma must be {len(DISTORTION_NAMES)} numbers > 0 '
                                 f'{DISTORTION_NAMES} or None, got {self.distortion_sigma!r}')
        if self.max_iterations < 1:
            raise ValueError(f'max_iterations must be >= 1, got {self.max_iterations}')
        bad = [k for k, v in self.intrinsics.items() if not isinstance(v, IntrinsicsPrior)]
        if bad:
            raise ValueError(f'intrinsics of {bad} must be IntrinsicsPrior objects')
        for label, shared in (('shared_lens', self.shared_lens),
                              ('shared_pose', self.shared_pose)):
            bad = [k for k, v in shared.items()
                   if not isinstance(k, str) or not isinstance(v, str) or k == v]
            if bad:
                raise ValueError(f'{label} must map a camera name to another camera name; '
                                 f'bad entries for {bad}')
        return self


@dataclass
class CameraEstimate:
    """One camera's estimate, its standard deviations and fit statistics."""

    camera: Camera
    std: Dict[str, float] = field(default_factory=dict)
    n_observations: int = 0
    n_inliers: int = 0
    rms_px: float = float('nan')
    #: 'ok'; 'degenerate' for a fit that is no calibration (:func:`_camera_sanity`, the
    #: message says why); 'failed' when the adjustment failed.
    status: str = 'ok'
    message: str = ''
    #: Degrees of freedom left in the camera's residuals, 2 n - sum of its leverages.
    redundancy: float = float('nan')
    #: The camera's own image noise estimate (px per axis): sqrt(sum w |r|^2 / redundancy),
    #: NaN without redundancy (a camera whose data its parameters can fit exactly).
    sigma_px: float = float('nan')


@dataclass
class AdjustmentResult:
    """
    Outcome of an adjustment.

    ``status``: 'converged', 'max_iterations', 'failed'.  ``cost`` is F at the solution;
    ``points`` the adjusted points (N, 3) (the measured points for ``fixed``); ``inliers`` a
    boolean mask over the observations; ``covariance`` the camera-parameter covariance with
    ``parameter_names`` labelling its rows.
    """

    success: bool
    status: str
    message: str
    cost: float
    initial_cost: float
    iterations: int
    time_s: float
    cameras: Dict[str, CameraEstimate]
    points: np.ndarray
    inliers: np.ndarray
    model: str = ''
    covariance: Optional[np.ndarray] = None
    parameter_names: List[str] = field(default_factory=list)
    gate_px: float = float('nan')
    log_evidence: float = float('nan')
    global_parameters: Optional[np.ndarray] = None
    global_covariance: Optional[np.ndarray] = None
    #: The covariance between the camera parameters (rows, as ``covariance``) and the global
    #: parameters (columns, as ``global_covariance``).
    global_cross_covariance: Optional[np.ndarray] = None
    kinematic_errors: Optional[Dict[str, float]] = None
    kinematic_std: Optional[Dict[str, float]] = None
    prior: Optional[PointPrior] = None
    prior_settings: Optional[PriorSettings] = None

    def predict_offsets(self, measured, jacobian=None):
        """
        Return the fitted prior's prediction of X - X^ at other robot points (M, 3).

        ``measured`` (M, 3) are robot-measured points, ``jacobian`` (M, 3, P) their kinematic
        Jacobian (needed by 'kinematic' and 'hybrid').  For the exact correlated prior this is
        the Gaussian-process posterior mean of the bias; for the lattice field its interpolant;
        for the kinematic part J_p dp.  Used for held-out checks.
        """
        measured = np.asarray(measured, float)
        out = np.zeros_like(measured)
        pr = self.prior
        if pr is None or pr.kind in ('fixed', 'block'):
            return out
        if pr.kind == 'dense':
            st = pr.settings
            Ks = st.bias_sigma ** 2 * kernel_matrix(measured, pr.measured, st.coherence_length,
                                                    st.kernel)
            return Ks @ pr.gradient_half(self.points)
        g = self.global_parameters
        if 'kinematic' in pr.global_slices:
            if jacobian is None:
                raise ValueError('predict_offsets needs the jacobian for a kinematic prior')
            dp = g[pr.global_slices['kinematic']] * pr.kinematics.sigma * \
                pr.settings.kinematic_scale
            out += np.asarray(jacobian, float) @ dp
        if 'field' in pr.global_slices:
            out += pr.field.evaluate(measured, g[pr.global_slices['field']])
        return out

    def camera_list(self):
        """Return the estimated cameras in input order."""
        return [e.camera for e in self.cameras.values()]


class _Layout:
    """Where each camera's parameters sit in the reduced parameter vector."""

    def __init__(self, n_cameras, free_distortion):
        self.dist_idx = np.array([DISTORTION_NAMES.index(d) for d in free_distortion], dtype=int)
        self.per_camera = 4 + len(self.dist_idx) + 6
        self.n_cameras = n_cameras
        self.size = n_cameras * self.per_camera

    def names(self, camera_names):
        local = list(INTRINSIC_NAMES) + [DISTORTION_NAMES[i] for i in self.dist_idx] + \
            ['wx', 'wy', 'wz', 'tx', 'ty', 'tz']
        return [f'{c}/{p}' for c in camera_names for p in local]

    def camera_jacobian(self, J):
        """Stack d_intr, free d_dist and d_pose into (M, 2, per_camera)."""
        return np.concatenate([J.d_intr, J.d_dist[:, :, self.dist_idx], J.d_pose], axis=2)

    def intrinsic_vector(self, cam: Camera):
        """Return (fx, fy, cx, cy, free distortion terms): the head of a camera's block."""
        return np.concatenate([cam.intrinsics(), cam.dist[self.dist_idx]])


def _pose_difference(a: Camera, b: Camera):
    """Return (log(R_a R_b^T), t_a - t_b) (6,): zero where two cameras have one pose."""
    dR = Rotation.from_matrix(a.rotation @ b.rotation.T).as_rotvec()
    return np.concatenate([dR, a.translation - b.translation])


def _apply_camera_step(cam: Camera, step, layout: _Layout):
    new = cam.copy()
    new.set_intrinsics(cam.intrinsics() + step[:4])
    nd = len(layout.dist_idx)
    dist = cam.dist.copy()
    dist[layout.dist_idx] += step[4:4 + nd]
    new.dist = dist
    new.apply_pose_increment(step[4 + nd:7 + nd], step[7 + nd:10 + nd])
    return new


class _Problem:
    """Linearisation and cost of one adjustment, with fixed camera set and observations."""

    def __init__(self, cameras, measured, obs, prior, settings, active):
        self.cameras = cameras
        self.measured = measured
        self.obs = obs
        self.prior = prior
        self.s = settings
        self.layout = _Layout(len(cameras), settings.free_distortion)
        self.active = active              # boolean mask of observations in use
        self.n = measured.shape[0]
        self.optimise_points = prior.kind != 'fixed'
        self.by_camera = [np.flatnonzero((obs.camera == j) & active)
                          for j in range(len(cameras))]
        # Whether each camera sees each point at most once (then scatter-adds are plain writes).
        self.unique = [np.unique(obs.point[idx]).size == idx.size for idx in self.by_camera]
        if prior.kind == 'dense':
            self.P_dense = np.kron(prior.scalar_precision(), np.eye(3))
        self.n_global = prior.n_global if prior.kind == 'global' else 0
        # Per camera (mean, 1 / sigma^2) over its block's head: given intrinsics (fixed or under
        # a prior), else the weak distortion prior (zero precision on K), or None.
        self.intrinsic_terms = [settings.intrinsics[c.name].terms(self.layout.dist_idx)
                                if c.name in settings.intrinsics else
                                self._distortion_prior(settings) for c in cameras]
        index = {c.name: j for j, c in enumerate(cameras)}
        self.shared = [(j, index[settings.shared_lens[c.name]]) for j, c in enumerate(cameras)
                       if settings.shared_lens.get(c.name) in index]
        head = 4 + len(self.layout.dist_idx)
        self.shared_precision = 1.0 / np.concatenate([
            np.full(4, SHARED_LENS_SIGMA[0]), np.full(head - 4, SHARED_LENS_SIGMA[1])]) ** 2
        self.shared_pose = [(j, index[settings.shared_pose[c.name]])
                            for j, c in enumerate(cameras)
                            if settings.shared_pose.get(c.name) in index]
        self.shared_pose_precision = 1.0 / np.repeat(SHARED_POSE_SIGMA, 3) ** 2
        if self.n_global:
            p = prior.precision
            # H_gg = sum_i p_i A_i^T A_i + I does not depend on the state (A is fixed).
            self.H_gg = prior.design.gram(p[:, None, None] * np.eye(3)) + np.eye(self.n_global)
            self.H_gg_diag = np.diag(self.H_gg).copy()

    def _distortion_prior(self, settings):
        """Return (mean, precision) of the weak distortion prior over a camera's block head."""
        idx = self.layout.dist_idx
        if settings.distortion_sigma is None or not len(idx):
            return None
        precision = np.zeros(4 + len(idx))
        precision[4:] = 1.0 / np.asarray(settings.distortion_sigma, float)[idx] ** 2
        return np.zeros(4 + len(idx)), precision

    def linearised(self, cams, X):
        """
        Return [(j, idx, pts, J, r, w)] per camera with active observations.

        idx the observations, pts their points, J their projection Jacobians at (cams, X),
        r the residuals and w the weights (robust weight / s_px^2).  The list also carries
        the image part of the cost (``image_cost``), so the LM loop evaluates a trial point
        once and reuses it as the next linearisation when the step is accepted.
        """
        inv_s2 = 1.0 / self.s.pixel_sigma ** 2
        out = _Linearisation()
        for j, idx in enumerate(self.by_camera):
            if idx.size == 0:
                continue
            c = cams[j]
            pts = self.obs.point[idx]
            J = project_with_jacobians(c.intrinsics(), c.dist, c.rotation, c.translation,
                                       X[pts])
            r = J.uv - self.obs.uv[idx]
            d2 = np.sum(r * r, axis=1)
            w = weights(d2, self.s.loss, self.s.loss_scale) * inv_s2
            out.image_cost += float(np.sum(rho(d2, self.s.loss, self.s.loss_scale))) * inv_s2
            out.append((j, idx, pts, J, r, w))
        return out

    def residuals(self, cams, X):
        """Squared pixel residual norms per active observation, by camera."""
        out = []
        for j, idx in enumerate(self.by_camera):
            c = cams[j]
            uv = c.project(X[self.obs.point[idx]])
            out.append(np.sum((uv - self.obs.uv[idx]) ** 2, axis=1))
        return out

    def cost(self, cams, X, g=None, lin=None):
        """F at (cams, X, g); ``lin`` a linearisation at the same point supplies its image part."""
        if lin is not None:
            total = lin.image_cost
        else:
            s2 = self.s.pixel_sigma ** 2
            total = sum(float(np.sum(rho(s, self.s.loss, self.s.loss_scale))) for s in
                        self.residuals(cams, X)) / s2
        if self.prior.kind == 'global':
            total += self.prior.global_cost(X, g)
        elif self.optimise_points:
            total += self.prior.cost(X)
        for c, t in zip(cams, self.intrinsic_terms):
            if t is not None:
                total += float(np.sum(t[1] * (self.layout.intrinsic_vector(c) - t[0]) ** 2))
        for j, k in self.shared:
            d = self.layout.intrinsic_vector(cams[j]) - self.layout.intrinsic_vector(cams[k])
            total += float(np.sum(self.shared_precision * d ** 2))
        for j, k in self.shared_pose:
            e = _pose_difference(cams[j], cams[k])
            total += float(np.sum(self.shared_pose_precision * e ** 2))
        return total

    def normal_equations(self, cams, X, g=None, lin=None):
        """
        Assemble U (block), W, V (blocks or dense), g_c, g_x, g_g.

        W is returned point-major and transposed, Wt (n, 3, C) with Wt_i = W_i^T: then
        W V^-1 W^T = sum_i (V_i^-1 Wt_i)^T Wt_i is one batched 3x3 product and one GEMM over
        (3n, C) views, with no transposed copies (the camera-major (C, n, 3) layout cost
        2.7 ms per step at n = 3000, this one 1.1 ms).
        """
        lay = self.layout
        pc = lay.per_camera
        n = self.n
        U = np.zeros((lay.size, lay.size))
        g_c = np.zeros(lay.size)
        Wt = np.zeros((n, 3, lay.size)) if self.optimise_points else None
        Vb = np.zeros((n, 3, 3))
        g_x = np.zeros((n, 3))
        for j, idx, pts, J, r, w in (lin if lin is not None else self.linearised(cams, X)):
            Jc = lay.camera_jacobian(J)                          # (m, 2, pc)
            wJc = Jc * w[:, None, None]
            sl = slice(j * pc, (j + 1) * pc)
            m2 = 2 * idx.size
            U[sl, sl] = wJc.reshape(m2, pc).T @ Jc.reshape(m2, pc)
            g_c[sl] = wJc.reshape(m2, pc).T @ r.reshape(m2)
            if self.optimise_points:
                Jx = J.d_point
                wJx = Jx * w[:, None, None]
                blocks = np.matmul(wJx.transpose(0, 2, 1), Jc)   # (m, 3, pc): W_i^T
                vb = np.matmul(wJx.transpose(0, 2, 1), Jx)
                gx = np.matmul(wJx.transpose(0, 2, 1), r[:, :, None])[:, :, 0]
                if self.unique[j]:
                    Wt[pts, :, sl] = blocks
                    Vb[pts] += vb
                    g_x[pts] += gx
                else:
                    np.add.at(Wt, (pts, slice(None), sl), blocks)
                    np.add.at(Vb, pts, vb)
                    np.add.at(g_x, pts, gx)
        for j, t in enumerate(self.intrinsic_terms):
            if t is not None:
                k = np.arange(j * pc, j * pc + len(t[0]))
                U[k, k] += t[1]
                g_c[k] += t[1] * (lay.intrinsic_vector(cams[j]) - t[0])
        # A shared lens: the term p (a_j - a_k)^2 over the two cameras' block heads.
        p = self.shared_precision
        for j, k in self.shared:
            a, b = np.arange(j * pc, j * pc + len(p)), np.arange(k * pc, k * pc + len(p))
            d = p * (lay.intrinsic_vector(cams[j]) - lay.intrinsic_vector(cams[k]))
            U[a, a] += p
            U[b, b] += p
            U[a, b] -= p
            U[b, a] -= p
            g_c[a] += d
            g_c[b] -= d
        # A shared pose: p |e|^2 with e = (log(R_j R_k^T), t_j - t_k), whose Jacobian in the
        # increments (R <- exp(w) R, t <- t + dt) is (I, -I) where the tie holds e near 0.
        p = self.shared_pose_precision
        head = pc - 6
        for j, k in self.shared_pose:
            a, b = np.arange(j * pc + head, (j + 1) * pc), np.arange(k * pc + head, (k + 1) * pc)
            d = p * _pose_difference(cams[j], cams[k])
            U[a, a] += p
            U[b, b] += p
            U[a, b] -= p
            U[b, a] -= p
            g_c[a] += d
            g_c[b] -= d
        g_g = np.zeros(self.n_global)
        if self.prior.kind == 'global':
            p = self.prior.precision
            pr = p[:, None] * (X - self.measured - self.prior.global_offsets(g))
            g_x += pr
            if self.n_global:
                g_g = g - self.prior.design.apply_T(pr)
        elif self.optimise_points:
            g_x += self.prior.gradient_half(X)
        return U, g_c, Wt, Vb, g_x, g_g

    def scaled_gradient(self, U, g_c, Vb, g_x, g_g=None):
        """Return max_k |g_k| / sqrt(h_kk): the gradient in Marquardt-scaled units."""
        g = np.abs(g_c) / np.sqrt(np.maximum(np.diag(U), 1e-300))
        out = float(np.max(g)) if g.size else 0.0
        if self.optimise_points and g_x.size:
            if self.prior.kind == 'block':
                h = np.diagonal(Vb, axis1=1, axis2=2) + 1.0 / self.prior.settings.point_sigma ** 2
            elif self.prior.kind == 'global':
                h = np.diagonal(Vb, axis1=1, axis2=2) + self.prior.precision[:, None]
            else:
                h = np.diagonal(Vb, axis1=1, axis2=2) + \
                    np.diag(self.prior.scalar_precision())[:, None]
            out = max(out, float(np.max(np.abs(g_x) / np.sqrt(h))))
        if self.n_global:
            out = max(out, float(np.max(np.abs(g_g) / np.sqrt(self.H_gg_diag))))
        return out

    def _global_system(self, U, g_c, Wt, Vb, g_x, g_g, lam):
        """
        Reduced system over (cameras, globals) after eliminating the 3x3 point blocks.

        With p_i the point precision, V_i = Vb_i + p_i I, E_i = V_i^-1 (damped), H_xg_i =
        -p_i A_i^T:  S_cc = U - sum W_i E_i W_i^T,  S_gc = sum p_i A_i^T E_i W_i^T,
        S_gg = sum A_i^T (p_i I - p_i^2 E_i) A_i + I,  rhs_c = -g_c + sum W_i E_i g_x_i,
        rhs_g = -g_g - sum p_i A_i^T E_i g_x_i.
        """
        n = self.n
        C = self.layout.size
        p = self.prior.precision
        V = Vb + p[:, None, None] * np.eye(3)
        if lam:
            dV = np.diagonal(V, axis1=1, axis2=2).copy()
            V[:, [0, 1, 2], [0, 1, 2]] += lam * np.maximum(dV, 1e-12)
        E = _inv3(V)
        EWt = np.matmul(E, Wt).reshape(3 * n, C)             # rows (E_i W_i^T) = (W_i E_i)^T
        dU = np.diag(U).copy()
        dU[dU <= 0] = 1e-12
        S_cc = U + np.diag(lam * dU) - EWt.T @ Wt.reshape(3 * n, C)
        rhs_c = -g_c + EWt.T @ g_x.reshape(3 * n)
        G = self.n_global
        if not G:
            return S_cc, rhs_c, E
        design = self.prior.design
        Cg = p[:, None, None] * np.eye(3) - (p * p)[:, None, None] * E
        S_gg = design.gram(Cg) + np.eye(G) + np.diag(lam * self.H_gg_diag)
        S_gc = design.cross(p[:, None, None] * EWt.reshape(n, 3, C))
        rhs_g = -g_g - design.apply_T(p[:, None] * np.einsum('nkl,nl->nk', E, g_x))
        S = np.empty((C + G, C + G))
        S[:C, :C] = S_cc
        S[C:, C:] = S_gg
        S[C:, :C] = S_gc
        S[:C, C:] = S_gc.T
        return S, np.concatenate([rhs_c, rhs_g]), E

    def solve_step(self, U, g_c, Wt, Vb, g_x, lam, g_g=None):
        """Solve the damped system for the camera step dc, the point step dx (and dg)."""
        if self.prior.kind == 'global':
            S, rhs, E = self._global_system(U, g_c, Wt, Vb, g_x, g_g, lam)
            d = _spd_solve(S, rhs)
            C = self.layout.size
            dc, dg = d[:C], d[C:]
            t = -g_x - (Wt.reshape(-1, C) @ dc).reshape(-1, 3)
            if self.n_global:
                t += self.prior.precision[:, None] * self.prior.design.apply(dg)
            dx = np.einsum('nkl,nl->nk', E, t)
            return dc, dx, dg
        dc, dx = self._solve_step_plain(U, g_c, Wt, Vb, g_x, lam)
        return dc, dx, np.zeros(0)

    def _solve_step_plain(self, U, g_c, Wt, Vb, g_x, lam):
        dU = np.diag(U).copy()
        dU[dU <= 0] = 1e-12
        Ud = U + np.diag(lam * dU)
        if not self.optimise_points:
            dc = _spd_solve(Ud, -g_c)
            return dc, None
        n = self.n
        Wr = Wt.reshape(3 * n, self.layout.size)                   # rows W_i^T, stacked
        if self.prior.kind == 'block':
            V = Vb + self.prior.block_precision()
            dV = np.diagonal(V, axis1=1, axis2=2).copy()
            Vd = V.copy()
            Vd[:, [0, 1, 2], [0, 1, 2]] += lam * np.maximum(dV, 1e-12)
            Vinv = _inv3(Vd)
            ViWr = np.matmul(Vinv, Wt).reshape(3 * n, -1)           # rows (W V^-1)^T
            S = Ud - ViWr.T @ Wr
            rhs = -g_c + ViWr.T @ g_x.reshape(-1)
            dc = _spd_solve(S, rhs)
            dx = np.einsum('nkl,nl->nk', Vinv, -g_x - (Wr @ dc).reshape(n, 3))
            return dc, dx
        V = self.P_dense.copy()
        ii = np.arange(n)
        for a in range(3):
            for b in range(3):
                V[3 * ii + a, 3 * ii + b] += Vb[:, a, b]
        dV = np.diag(V).copy()
        V[np.diag_indices_from(V)] += lam * np.maximum(dV, 1e-12)
        F = cho_factor(V, lower=True, check_finite=False)
        ViWt = cho_solve(F, Wr, check_finite=False)
        Vig = cho_solve(F, g_x.reshape(-1), check_finite=False)
        S = Ud - Wr.T @ ViWt
        dc = _spd_solve(S, -g_c + Wr.T @ Vig)
        dx = (-Vig - ViWt @ dc).reshape(n, 3)
        return dc, dx

    def reduced_matrix(self, cams, X, g=None):
        """Undamped Schur complement S at (cams, X[, g]): the inverse (camera, global) cov."""
        return self.reduced_and_logdet(cams, X, g)[0]

    def reduced_and_logdet(self, cams, X, g=None):
        """
        Return (S, log det of the eliminated point block V, log det of the prior precision).

        The two log-determinants feed the Laplace approximation of the evidence.
        """
        U, g_c, Wt, Vb, g_x, g_g = self.normal_equations(cams, X, g)
        if not self.optimise_points:
            return U, 0.0, 0.0
        n = self.n
        if self.prior.kind == 'global':
            S, _, _ = self._global_system(U, g_c, Wt, Vb, g_x, g_g, 0.0)
            p = self.prior.precision
            V = Vb + p[:, None, None] * np.eye(3)
            return S, float(np.sum(np.linalg.slogdet(V)[1])), 3.0 * float(np.sum(np.log(p)))
        Wr = Wt.reshape(3 * n, self.layout.size)
        if self.prior.kind == 'block':
            V = Vb + self.prior.block_precision()
            ViWr = np.matmul(np.linalg.inv(V), Wt).reshape(3 * n, -1)
            ps2 = self.prior.settings.point_sigma ** 2
            return (U - ViWr.T @ Wr, float(np.sum(np.linalg.slogdet(V)[1])),
                    -3.0 * n * np.log(ps2))
        V = self.P_dense.copy()
        ii = np.arange(n)
        for a in range(3):
            for b in range(3):
                V[3 * ii + a, 3 * ii + b] += Vb[:, a, b]
        F = cho_factor(V, lower=True, check_finite=False)
        logdet_v = 2.0 * float(np.sum(np.log(np.diag(F[0]))))
        logdet_p = -3.0 * 2.0 * float(np.sum(np.log(np.diag(self.prior._chol[0]))))
        return U - Wr.T @ cho_solve(F, Wr, check_finite=False), logdet_v, logdet_p

    def _point_blocks(self, cams, X, g, T, points=None):
        """
        Return L (m, T, 3), L_i = B_i V^-1 restricted to point i, and (V^-1)_ii (m, 3, 3).

        For the points ``points`` (indices; default all, m = n).  B_i (T x 3) couples point i
        to the cameras (W_i) and, under a global prior, to the global parameters
        (-p_i A_i^T); T is the size of the reduced (camera, global) system.  Under the exact
        correlated prior V is dense and L_i takes every point's column.
        """
        _, _, Wt, Vb, _, _ = self.normal_equations(cams, X, g)
        C, n = self.layout.size, self.n
        sub = np.arange(n) if points is None else np.asarray(points)
        if self.prior.kind == 'dense':
            V = self.P_dense.copy()
            ii = np.arange(n)
            for a in range(3):
                for b in range(3):
                    V[3 * ii + a, 3 * ii + b] += Vb[:, a, b]
            # The inverse from the Cholesky factor (LAPACK potri: half the work of solving
            # against the identity); potri fills the lower triangle only.
            Vinv, info = lapack.dpotri(cho_factor(V, lower=True, check_finite=False)[0],
                                       lower=1)
            if info:
                raise LinAlgError(f'dpotri failed ({info})')
            Vinv = np.tril(Vinv) + np.tril(Vinv, -1).T
            Einv = np.stack([Vinv[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in sub])
            cols = (3 * sub[:, None] + np.arange(3)).reshape(-1)
            L = (Wt.reshape(3 * n, C).T @ Vinv[:, cols]).reshape(C, sub.size, 3).transpose(1, 0, 2)
            return L, Einv
        if self.prior.kind == 'block':
            V = Vb[sub] + self.prior.block_precision()[sub]
        else:
            V = Vb[sub] + self.prior.precision[sub, None, None] * np.eye(3)
        Einv = np.linalg.inv(V)
        L = np.matmul(Einv, Wt[sub]).transpose(0, 2, 1)    # (m, C, 3): W_i E_i, E_i symmetric
        G = T - C
        if G:
            # B_g,i = -p_i A_i^T: the prior couples point i to the globals.
            Lg = -self.prior.precision[sub, None, None] * np.matmul(
                self.prior.design_matrix()[sub].transpose(0, 2, 1), Einv)  # (m, G, 3)
            L = np.concatenate([L, Lg], axis=1)
        return L, Einv

    def camera_sensitivity(self, cams, X, g, cov):
        """
        Return D (C, n, 3): how the estimated camera parameters move with the robot's points.

        D_i = d c^ / d X^_i at the solution, from the derivative of the stationarity
        condition: without points to adjust (``fixed``) D = -S^-1 W (the cameras see X^
        directly); with points, X^ enters only through the prior (x - X^ - A g)^T P (...), so
        d phi^ / d X^ = Sigma [0; -A^T P; P] over (cameras, globals, points) and the camera
        rows are (Sigma_cx - Sigma_cg A^T) P.  ``cov`` is S^-1 over (cameras, globals).
        """
        lay = self.layout
        C, n = lay.size, self.n
        if not self.optimise_points:
            W = np.zeros((C, n, 3))
            pc = lay.per_camera
            for j, idx, pts, J, r, w in self.linearised(cams, X):
                blocks = np.matmul((lay.camera_jacobian(J) * w[:, None, None]).transpose(
                    0, 2, 1), J.d_point)                                  # (m, pc, 3)
                np.add.at(W, (slice(j * pc, (j + 1) * pc), pts), blocks.transpose(1, 0, 2))
            return -np.einsum('cd,dnk->cnk', cov[:C, :C], W)
        L, _ = self._point_blocks(cams, X, g, cov.shape[0])
        Sx = -np.einsum('ct,ntk->cnk', cov[:C, :], L)                    # Sigma_cx
        kind = self.prior.kind
        if kind == 'dense':
            return (Sx.reshape(C, 3 * n) @ self.P_dense).reshape(C, n, 3)
        if kind == 'block':
            return np.einsum('cnk,nkl->cnl', Sx, self.prior.block_precision())
        if cov.shape[0] > C:
            Sx = Sx - np.einsum('cg,nkg->cnk', cov[:C, C:], self.prior.design_matrix())
        return Sx * self.prior.precision[None, :, None]

    def leverages(self, cams, X, g, cov, max_per_camera=LEVERAGE_SAMPLE):
        """
        Return the leverage h_k of each observation: its share of the fit (NaN if unused).

        With the whole posterior covariance Sigma = N^-1 over (cameras, globals, points),
        h_k = w_k tr(J_k Sigma_k J_k^T), J_k = [J_c J_x] the observation's derivatives with
        respect to its camera and point and w_k its weight (robust weight / s_px^2).  The sum
        of h_k over a camera's observations is the number of parameters its data pay for, so
        r_j = 2 n_j - sum h_k is the camera's redundancy: the degrees of freedom left in its
        residuals (Foerstner's redundancy numbers).  It counts what a prior or a held value
        restrains - a fixed intrinsic, a point held by its prior, a global parameter under its
        prior - at its real weight, which counting parameters cannot.

        Sigma is never formed: with the points eliminated (N = [[A, B], [B^T, V]], S = A - B
        V^-1 B^T, ``cov`` = S^-1 over (cameras, globals)) and L_i = B_i V_i^-1, the blocks
        needed are Sigma_cc = S^-1, Sigma_cx_i = -S^-1 L_i and Sigma_xx_ii = (V^-1)_ii +
        L_i^T S^-1 L_i.  V is block-diagonal except under the exact correlated prior, whose
        dense V^-1 is formed once here.

        Cost: the point blocks take O(T^2) per observation (T the reduced system's size), so
        above ``max_per_camera`` observations a camera's leverages are computed for an even
        subsample only (the others are NaN) and its sum is estimated from their mean: a
        relative sampling error of about 1 % over 2,000, below the variance factor's own
        (sqrt(2 / r)).  Without that cap, N = 30,000 hybrid doubled the warm solve time.
        """
        lay = self.layout
        pc = lay.per_camera
        h = np.full(len(self.obs), np.nan)
        h[self.active] = 0.0
        strides = [max(1, -(-idx.size // max_per_camera)) for idx in self.by_camera]
        if self.optimise_points:
            # The sampled observations' points only; row[i] is point i's row in L and Sxx.
            need = np.unique(np.concatenate(
                [self.obs.point[idx[::k]] for idx, k in zip(self.by_camera, strides)]))
            row = np.full(self.n, -1)
            row[need] = np.arange(need.size)
            L, Einv = self._point_blocks(cams, X, g, cov.shape[0], need)
            # Sigma_xx_ii = (V^-1)_ii + L_i^T S^-1 L_i (one GEMM).
            T = L.shape[1]
            LtS = (L.transpose(0, 2, 1).reshape(3 * need.size, T) @ cov).reshape(-1, 3, T)
            Sxx = Einv + np.matmul(LtS, L)
        for j, idx, pts, J, r, w in self.linearised(cams, X):
            k = slice(None, None, strides[j])
            Jc = lay.camera_jacobian(J)[k]                                # (m, 2, pc)
            sl = slice(j * pc, (j + 1) * pc)
            hk = np.einsum('mak,kl,mal->m', Jc, cov[sl, sl], Jc)
            if self.optimise_points:
                Jx, p = J.d_point[k], row[pts[k]]                         # (m, 2, 3)
                Scx = -np.matmul(cov[sl, :], L[p])                        # (m, pc, 3)
                hk = hk + 2.0 * np.einsum('mak,mkl,mal->m', Jc, Scx, Jx) + \
                    np.einsum('mak,mkl,mal->m', Jx, Sxx[p], Jx)
            if strides[j] > 1:
                h[idx] = np.nan
            h[idx[k]] = w[k] * hk
        return h

    def step(self, cams, X, dc, dx, g=None, dg=None):
        pc = self.layout.per_camera
        new_cams = [_apply_camera_step(c, dc[j * pc:(j + 1) * pc], self.layout)
                    for j, c in enumerate(cams)]
        new_X = X + dx if dx is not None else X
        new_g = g + dg if dg is not None and dg.size else g
        return new_cams, new_X, new_g


class _Linearisation(list):
    """Per-camera (j, idx, pts, J, r, w) at one point of parameter space, and F's image part."""

    image_cost = 0.0


def _inv3(V):
    """
    Invert a stack of 3x3 matrices (n, 3, 3) by the adjugate: V^-1 = adj(V) / det(V).

    Eight times faster than the batched LAPACK call for these tiny blocks (0.07 against
    0.56 ms for 3,000).  The cofactors lose about cond(V)^2 eps where LU loses cond(V) eps, so
    blocks whose determinant is below 1e-6 of the cube of their largest entry (a condition
    number of about 10^5 and more: a point seen by one camera under a very weak prior) are
    inverted by LAPACK instead; damped point blocks under any working prior are far from it.
    """
    # Each block scaled to a largest entry of 1 first: the cofactors are cubes of the entries,
    # which overflow for the heavily damped blocks of a step LM keeps rejecting.
    scale = np.max(np.abs(V), axis=(1, 2))
    scale[~(scale > 0)] = 1.0
    Vs = V / scale[:, None, None]
    a, b, c = Vs[:, 0, 0], Vs[:, 0, 1], Vs[:, 0, 2]
    d, e, f = Vs[:, 1, 0], Vs[:, 1, 1], Vs[:, 1, 2]
    g, h, i = Vs[:, 2, 0], Vs[:, 2, 1], Vs[:, 2, 2]
    out = np.empty_like(V)
    out[:, 0, 0] = e * i - f * h
    out[:, 1, 0] = f * g - d * i
    out[:, 2, 0] = d * h - e * g
    out[:, 0, 1] = c * h - b * i
    out[:, 1, 1] = a * i - c * g
    out[:, 2, 1] = b * g - a * h
    out[:, 0, 2] = b * f - c * e
    out[:, 1, 2] = c * d - a * f
    out[:, 2, 2] = a * e - b * d
    det = a * out[:, 0, 0] + b * out[:, 1, 0] + c * out[:, 2, 0]
    poor = ~(np.abs(det) > 1e-6)
    out /= (np.where(poor, 1.0, det) * scale)[:, None, None]
    if np.any(poor):
        out[poor] = np.linalg.inv(V[poor])
    return out


def _spd_solve(A, b):
    try:
        return cho_solve(cho_factor(A, check_finite=False), b, check_finite=False)
    except LinAlgError:
        return np.linalg.lstsq(A, b, rcond=None)[0]


def _scaled_norm(cams, X, dc, dx, layout):
    """Step size relative to the parameters, for the xtol test."""
    pc = layout.per_camera
    rel = 0.0
    for j, c in enumerate(cams):
        s = dc[j * pc:(j + 1) * pc]
        scale_f = max(abs(c.fx), 1.0)
        rel = max(rel, float(np.max(np.abs(s[:4]))) / scale_f)
        rel = max(rel, float(np.max(np.abs(s[4 + len(layout.dist_idx):7 + len(layout.dist_idx)]))))
        rel = max(rel, float(np.max(np.abs(s[-3:]))) / max(np.linalg.norm(c.translation), 1e-3))
    if dx is not None and dx.size:
        rel = max(rel, float(np.max(np.abs(dx))) / max(float(np.max(np.abs(X))), 1e-3))
    return rel


def _levenberg_marquardt(problem: _Problem, cams, X, g):
    s = problem.s
    lam = s.initial_lambda
    nu = 2.0
    lin = problem.linearised(cams, X)
    cost = problem.cost(cams, X, g, lin)
    initial = cost
    status, message = 'max_iterations', f'reached max_iterations={s.max_iterations}'
    it = 0
    for it in range(1, s.max_iterations + 1):
        U, g_c, Wt, Vb, g_x, g_g = problem.normal_equations(cams, X, g, lin)
        if problem.scaled_gradient(U, g_c, Vb, g_x, g_g) < \
                s.gtol * np.sqrt(max(cost, 1e-300)):
            status, message = 'converged', 'scaled gradient below gtol'
            it -= 1
            break
        accepted = False
        for _ in range(30):
            dc, dx, dg = problem.solve_step(U, g_c, Wt, Vb, g_x, lam, g_g)
            new_cams, new_X, new_g = problem.step(cams, X, dc, dx, g, dg)
            new_lin = problem.linearised(new_cams, new_X)
            new_cost = problem.cost(new_cams, new_X, new_g, new_lin)
            # Predicted decrease of the Gauss-Newton model, for the gain ratio.
            pred = -(dc @ g_c) - float(dg @ g_g)
            if dx is not None:
                pred -= float(np.sum(dx * g_x))
            actual = cost - new_cost
            if np.isfinite(new_cost) and actual > 0:
                gain = actual / max(pred, 1e-300)
                lam *= max(LAMBDA_MIN_FACTOR, 1.0 - (2.0 * gain - 1.0) ** 3)
                nu = 2.0
                accepted = True
                break
            lam *= nu
            nu *= 2.0
        if not accepted:
            status, message = 'converged', 'no step decreases the cost (at a minimum)'
            break
        rel_step = _scaled_norm(cams, X, dc, dx, problem.layout)
        if dg.size:
            rel_step = max(rel_step, float(np.max(np.abs(dg))) /
                           max(float(np.max(np.abs(g))), 1.0))
        rel_decrease = (cost - new_cost) / max(cost, 1e-300)
        cams, X, g, cost, lin = new_cams, new_X, new_g, new_cost, new_lin
        if rel_decrease < s.ftol:
            status, message = 'converged', f'relative cost decrease {rel_decrease:.2e} < ftol'
            break
        if rel_step < s.xtol:
            status, message = 'converged', f'relative step {rel_step:.2e} < xtol'
            break
    return cams, X, g, cost, initial, it, status, message


#: A camera's residuals estimate its image noise only with at least this many degrees of
#: freedom left (one: with less, the estimate is a ratio of two numbers near zero).
REDUNDANCY_FLOOR = 1.0
#: Below this share of its observations kept as inliers a camera's fit is not a calibration:
#: a robust fit can be trusted only while what it keeps is the majority (the breakdown point
#: of the gate and the M-estimator), and a fit that explains a third of its points is one
#: that bent the camera to suit a few (measured on a lamp-lit PUMA cell: 6 of 18 kept, fx
#: 153 px, fy 51 px where the camera has 764, a residual RMS of 0.000 px).
MIN_INLIER_FRACTION = 0.5


def _robust_sigma(d):
    """Per-axis pixel sigma from residual norms: the Rayleigh median is 1.1774 sigma."""
    return float(np.median(d)) / 1.1774 if d.size else float('nan')


def adjust(cameras: Sequence[Camera], measured, obs: Observations,
           prior_settings: PriorSettings = None, settings: SolverSettings = None,
           points_init=None, inliers=None, kinematics=None, globals_init=None,
           prior: Optional[PointPrior] = None, redundancy: bool = True) -> AdjustmentResult:
    """
    Adjust ``cameras`` (initial estimates) and the points under the chosen prior.

    ``measured`` are the robot's points X^ (N, 3); ``obs`` index into ``cameras`` and the points.
    ``points_init`` (N, 3) warm-starts the points (default X^); ``inliers`` an initial mask.
    ``kinematics`` (:class:`~armcal_ros.core.kinematic_prior.KinematicData`) is needed by the
    'kinematic' and 'hybrid' models; ``globals_init`` warm-starts their global parameters (the
    ``global_parameters`` of an earlier result with the same prior); ``prior`` passes a
    prebuilt :class:`PointPrior` for these settings (to reuse its lattice).  ``redundancy``
    False skips the leverages (CameraEstimate.redundancy and sigma_px stay NaN): a model
    search's candidates do not need them, and under the exact correlated prior they cost a
    dense inverse.
    Returns an :class:`AdjustmentResult`; never raises on numerical failure (status 'failed').
    """
    t0 = time.perf_counter()
    prior_settings = (prior_settings or PriorSettings()).validate()
    settings = (settings or SolverSettings()).validate()
    measured = np.asarray(measured, float)
    if measured.ndim != 2 or measured.shape[1] != 3:
        raise ValueError(f'measured must have shape (N, 3), got {measured.shape}')
    if not np.all(np.isfinite(measured)):
        raise ValueError('measured contains NaN or inf')
    n = measured.shape[0]
    if len(obs) and (obs.point.max() >= n or obs.point.min() < 0):
        raise ValueError(f'observations.point must index {n} points')
    if len(obs) and (obs.camera.max() >= len(cameras) or obs.camera.min() < 0):
        raise ValueError(f'observations.camera must index {len(cameras)} cameras')
    cams = [c.copy() for c in cameras]
    X = measured.copy() if points_init is None else np.array(points_init, float)
    if X.shape != measured.shape:
        raise ValueError(f'points_init must have shape {measured.shape}, got {X.shape}')
    if prior is None:
        prior = PointPrior(measured, prior_settings, kinematics)
    n_global = prior.n_global if prior.kind == 'global' else 0
    g = np.zeros(n_global)
    if globals_init is not None:
        gi = np.asarray(globals_init, float).reshape(-1)
        if gi.shape != (n_global,):
            raise ValueError(f'globals_init must have shape ({n_global},), got {gi.shape}')
        g = gi.copy()
    active = np.ones(len(obs), bool) if inliers is None else np.asarray(inliers, bool).copy()

    total_it = 0
    initial_cost = None
    gate = float('nan')
    status, message, cost = 'failed', 'not run', float('nan')
    try:
        rounds = max(1, settings.max_gate_rounds + 1)
        for k in range(rounds):
            problem = _Problem(cams, measured, obs, prior, settings, active)
            cams, X, g, cost, c0, it, status, message = _levenberg_marquardt(problem, cams, X, g)
            initial_cost = c0 if initial_cost is None else initial_cost
            total_it += it
            d = _all_residual_norms(cams, X, obs)
            gate = max(settings.gate_sigmas * _robust_sigma(d[active]), settings.gate_min_px)
            new_active = d <= gate
            if np.array_equal(new_active, active) or k == rounds - 1:
                break
            active = new_active
            problem = None
        if problem is None or not np.array_equal(problem.active, active):
            problem = _Problem(cams, measured, obs, prior, settings, active)
        S, logdet_v, logdet_p = problem.reduced_and_logdet(cams, X, g)
        full_cov = _safe_inverse(S)
        log_evidence = _laplace_evidence(cost, S, logdet_v, logdet_p)
    except (LinAlgError, FloatingPointError, ValueError) as exc:
        return AdjustmentResult(False, 'failed', f'numerical failure: {exc}', float('nan'),
                                float('nan') if initial_cost is None else initial_cost,
                                total_it, time.perf_counter() - t0,
                                {c.name: CameraEstimate(c, status='failed', message=str(exc))
                                 for c in cams}, X, active, prior_settings.model)
    C = problem.layout.size
    cov = full_cov[:C, :C]
    names = problem.layout.names([c.name for c in cams])
    try:
        lev = problem.leverages(cams, X, g, full_cov) \
            if redundancy and np.all(np.isfinite(full_cov)) else None
    except (LinAlgError, FloatingPointError, ValueError):
        lev = None
    estimates = _camera_estimates(cams, obs, X, active, cov, problem.layout, lev, settings)
    ok = status == 'converged' and np.all(np.isfinite(cov.diagonal()))
    result = AdjustmentResult(
        success=bool(ok), status=status, message=message, cost=float(cost),
        initial_cost=float(initial_cost), iterations=total_it,
        time_s=time.perf_counter() - t0, cameras=estimates, points=X, inliers=active,
        model=prior_settings.model, covariance=cov, parameter_names=names, gate_px=gate,
        log_evidence=log_evidence, prior=prior, prior_settings=prior_settings)
    if n_global:
        result.global_parameters = g
        result.global_covariance = full_cov[C:, C:]
        result.global_cross_covariance = full_cov[:C, C:]
        if 'kinematic' in prior.global_slices:
            sl = prior.global_slices['kinematic']
            sig = prior.kinematics.sigma * prior_settings.kinematic_scale
            std = np.sqrt(np.maximum(np.diag(full_cov[C:, C:])[sl], 0.0)) * sig
            result.kinematic_errors = dict(zip(prior.kinematics.names, g[sl] * sig))
            result.kinematic_std = dict(zip(prior.kinematics.names, std))
    return result


def _laplace_evidence(cost, S, logdet_v, logdet_p):
    """
    Laplace approximation of log p(images, robot points | model), up to a model-free constant.

    log Z = -F/2 - (log det V + log det S)/2 + (log det P)/2: F the objective at the optimum,
    V the eliminated point block and S the reduced (camera, global) matrix - together the
    Hessian of F/2 - and P the prior precision of the points and globals (the pixel-noise
    normaliser and the flat camera prior are the same for every model and dropped).  The
    ``fixed`` model is the limit of vanishing point sigma and has only -F/2 - log det S / 2.
    """
    sign, logdet_s = np.linalg.slogdet(S)
    if sign <= 0:
        return float('nan')
    return float(-0.5 * cost - 0.5 * (logdet_v + logdet_s) + 0.5 * logdet_p)


def _all_residual_norms(cams, X, obs):
    d = np.empty(len(obs))
    for j, c in enumerate(cams):
        idx = np.flatnonzero(obs.camera == j)
        if idx.size:
            d[idx] = np.linalg.norm(c.project(X[obs.point[idx]]) - obs.uv[idx], axis=1)
    return d


def _safe_inverse(S):
    try:
        return cho_solve(cho_factor(S, check_finite=False), np.eye(S.shape[0]),
                         check_finite=False)
    except LinAlgError:
        return np.linalg.pinv(S)


def _camera_std(c, C, layout):
    """Return the standard deviations of a camera's parameters, centre and rotation (block C)."""
    nd = len(layout.dist_idx)
    sd = np.sqrt(np.maximum(np.diag(C), 0.0))
    std = dict(zip(INTRINSIC_NAMES, sd[:4]))
    for k, i in enumerate(layout.dist_idx):
        std[DISTORTION_NAMES[i]] = float(sd[4 + k])
    # Camera centre C = -R^T t with R <- exp(w) R, t <- t + dt:
    # dC/dw = -R^T [t]x, dC/dt = -R^T (first order at w = 0).
    Jc = np.hstack([-c.rotation.T @ skew(c.translation), -c.rotation.T])
    Cp = C[4 + nd:, 4 + nd:]
    cc = Jc @ Cp @ Jc.T
    for a, ax in enumerate('xyz'):
        std[f'center_{ax}'] = float(np.sqrt(max(cc[a, a], 0.0)))
        std[f'rot_{ax}'] = float(sd[4 + nd + a])
    return {k: float(v) for k, v in std.items()}


def _error_quadratic(D, terms):
    """Return D Sigma D^T (C, C) for D (C, n, 3) and a prior's error covariance ``terms``."""
    kind, data = terms
    if kind == 'none':
        return np.zeros((D.shape[0], D.shape[0]))
    if kind == 'blocks':
        return np.einsum('cnk,nkl,dnl->cd', D, data, D, optimize=True)
    if kind == 'kron':
        M = np.einsum('nm,dmk->dnk', data, D, optimize=True)
        return np.einsum('cnk,dnk->cd', D, M, optimize=True)
    var, A = data
    DA = np.einsum('cnk,nkg->cg', D, A, optimize=True)
    return np.einsum('cnk,n,dnk->cd', D, var, D, optimize=True) + DA @ DA.T


def covariance_under(result: 'AdjustmentResult', measured, obs: Observations,
                     settings: 'SolverSettings', reference: PointPrior) -> np.ndarray:
    """
    Camera covariance of ``result``'s estimate if the robot's point errors follow ``reference``.

    The estimate c^ depends on the robot's points X^ through D = dc^/dX^
    (:meth:`_Problem.camera_sensitivity`).  Its reported covariance S^-1 assumes the errors
    X^ - X have the covariance of the model's own prior, Sigma_own (zero for ``fixed``); if
    they have Sigma_ref instead, the estimate's covariance is, to first order,

        S^-1 + D (Sigma_ref - Sigma_own) D^T

    (the sandwich of a misspecified linear-Gaussian model).  So a model that leaves part of
    the arm's error undescribed - ``fixed`` under any arm error, ``kinematic`` under a smooth
    bias field - widens by what that part does to its cameras, given a ``reference`` prior that
    describes the errors (the evidence's choice, :mod:`armcal_ros.core.model_selection`).
    ``settings`` must carry the image noise ``result`` was weighted with.  Returns the camera
    block (C, C); the correction is kept where it widens (its positive part) and dropped
    where the model's own prior already covers more than the reference.
    """
    cams = result.camera_list()
    prior = result.prior
    problem = _Problem(cams, np.asarray(measured, float), obs, prior, settings, result.inliers)
    g = result.global_parameters
    S = problem.reduced_matrix(cams, result.points, g)
    cov = _safe_inverse(S)
    D = problem.camera_sensitivity(cams, result.points, g, cov)
    C = problem.layout.size
    extra = _error_quadratic(D, reference.error_covariance()) - \
        _error_quadratic(D, prior.error_covariance())
    # Only widen: where the model's own prior is the wider one, its covariance stands (the
    # reference's scale is tuned on what the images see, not on what they cannot).
    w, V = np.linalg.eigh(0.5 * (extra + extra.T))
    return cov[:C, :C] + (V * np.maximum(w, 0.0)) @ V.T


def with_covariance(result: 'AdjustmentResult', cov) -> 'AdjustmentResult':
    """Return a copy of ``result`` whose camera covariance and standard deviations are ``cov``."""
    out = copy(result)
    out.covariance = np.asarray(cov, float)
    # The free distortion terms are those named in the first camera's block.
    first = next(iter(result.cameras), '') + '/'
    local = [p[len(first):] for p in result.parameter_names if p.startswith(first)]
    layout = _Layout(len(result.cameras), [p for p in local if p in DISTORTION_NAMES])
    pc = layout.per_camera
    out.cameras = {}
    for j, (name, e) in enumerate(result.cameras.items()):
        e2 = copy(e)
        e2.std = _camera_std(e.camera, out.covariance[j * pc:(j + 1) * pc, j * pc:(j + 1) * pc],
                             layout)
        out.cameras[name] = e2
    return out


def _camera_sanity(c, n_observations, n_inliers, n_parameters):
    """
    Return ('ok', '') or ('degenerate', why) for a camera's fit that is no calibration.

    Degenerate: focal lengths that are not positive; fewer inlier equations (2 per point)
    than the ``n_parameters`` the images alone must determine (all of the camera's, or its
    pose's 6 where its intrinsics are given), so that its fit is not determined by them (its
    residuals near zero, its covariance meaningless); or fewer than
    :data:`MIN_INLIER_FRACTION` of its observations kept.
    """
    if not (np.isfinite(c.fx) and np.isfinite(c.fy) and c.fx > 0 and c.fy > 0):
        return 'degenerate', f'focal lengths fx {c.fx:.4g}, fy {c.fy:.4g} px are not positive'
    if 2 * n_inliers < n_parameters:
        return 'degenerate', (f'{n_inliers} inliers give {2 * n_inliers} equations for its '
                              f'{n_parameters} parameters')
    if n_inliers < MIN_INLIER_FRACTION * n_observations:
        return 'degenerate', (f'only {n_inliers} of its {n_observations} observations fit '
                              f'(fewer than {MIN_INLIER_FRACTION:.0%})')
    return 'ok', ''


def _camera_estimates(cams, obs, X, active, cov, layout, leverage=None, settings=None):
    d = _all_residual_norms(cams, X, obs)
    if leverage is not None:
        # Robust weights (no 1/s^2): a down-weighted residual counts as the loss counts it.
        w_rob = weights(d ** 2, settings.loss, settings.loss_scale)
    pc = layout.per_camera
    out = {}
    for j, c in enumerate(cams):
        sel = obs.camera == j
        inl = sel & active
        std = _camera_std(c, cov[j * pc:(j + 1) * pc, j * pc:(j + 1) * pc], layout)
        rms = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else float('nan')
        est = CameraEstimate(c, std, int(sel.sum()), int(inl.sum()), rms)
        # Given intrinsics (a prior term, fixed or not) determine all but the pose.
        given = settings is not None and c.name in settings.intrinsics
        est.status, est.message = _camera_sanity(c, est.n_observations, est.n_inliers,
                                                 6 if given else pc)
        if leverage is not None and inl.any():
            # The mean over the computed leverages (all, or an even subsample) times the count.
            est.redundancy = float(inl.sum() * (2.0 - np.nanmean(leverage[inl])))
            if est.redundancy > REDUNDANCY_FLOOR:
                # |r|^2 sums both axes and the redundancy counts scalar equations.
                est.sigma_px = float(np.sqrt(np.sum(w_rob[inl] * d[inl] ** 2) /
                                             est.redundancy))
        out[c.name] = est
    return out
