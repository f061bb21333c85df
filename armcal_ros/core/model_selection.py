"""
``noise_model: auto``: choose the prior and its hyperparameters from the data.

Candidates are the models the data allow (``kinematic`` and ``hybrid`` need joint angles, i.e. a
kinematic Jacobian) with hyperparameters on a small grid (:data:`DEFAULT_GRID`).  Each is
adjusted from the same warm start (the ``fixed`` solution) on the same inlier set, and scored by
the Laplace approximation of its marginal likelihood (the evidence, see
:func:`armcal_ros.core.adjustment._laplace_evidence`): the probability of the images and the
robot's points under the model with every camera, point and global parameter integrated out.
It rewards fit and penalises a prior that is looser than the data need, so it can pick a
coherence length or a bias sigma where the fit alone would always prefer the loosest prior.
A more complex model must beat a simpler one by ``OCCAM_MARGIN`` (3 in natural log) to be chosen:
in the accuracy benchmark, hybrid's gain over kinematic on pure linkage errors stayed within
+-3 while its cameras were a few per cent worse.

The hyperparameters are searched one coordinate at a time, about twenty-five adjustments in
all.  Field: coherence length, then bias sigma, on the grid.  Kinematic: the common multiplier
of the kinematic sigmas by an evidence-maximising 1-D search (the grid, extended until the
maximum is bracketed, then parabolic refinement in log scale: the evidence is smooth in it),
then the per-point sigma s_n on its grid, then the multiplier once more at that s_n.
``hybrid``: its kinematic part starts at the kinematic model's optimum (multiplier and s_n);
the field is searched on top, and two limits are candidates too: the field switched off
(sigma -> 0, the best kinematic model itself) and the kinematic part switched off (the best
correlated model); from the best of these the multiplier is searched once more.  Both limits
are exactly those models (the same prior, hence the same solve and evidence), so hybrid's best
evidence is never below either.

Measured on the accuracy benchmark (PUMA 560, N = 1000, five seeds): the s_n search moves the
kinematic models' s_n from the 0.2 mm default to 0.02-0.05 mm (7-26 more log evidence on pure
linkage errors); with the continuous scale it brings the evidence-chosen kinematic model within
2 % of the default's shape on non-geometric errors (the grid alone left it 4 % worse).
Per-group scales (offsets, translations, rotations, mount translation and rotation, by
coordinate ascent of the evidence) were tried: 1-7 more log evidence, the same shape error
(0.1207 against 0.1196 mm), so they are not used.

Check: held-out reprojection, part of the Occam rule.  The points are split once into
``HOLDOUT_FOLDS`` folds (the same split for every candidate, so the comparisons are paired);
for a fold, the model is fitted on the other points, the fold's points are predicted from the
robot's measurement (X^ plus the model's predicted correction: J_p dp, the field's posterior
mean) and projected with the fitted cameras.  The report gives, for the best candidate of each
model, the RMS pixel error on the first fold (a fifth of the points): how well the model
predicts where the arm really is.  The choice runs down the complexity ladder: the evidence
choice c (above) is compared with the evidence choice s among the strictly simpler candidates
(all of which are nested in c: a sigma switched off), on all folds, i.e. every point held out
once.  With e_k the squared pixel error of held-out observation k, d_i = sum over the
observations of point i of (e_k(c) - e_k(s)), and M observations in all, c's excess is
D = sum_i d_i / M with standard error sqrt(n) std(d_i) / M (the observations of one point share
its prediction error, so the point is the sampling unit).  c is kept unless D > ``HOLDOUT_Z``
standard errors; otherwise s replaces it and is checked the same way against the candidates
simpler than itself.  So a more complex model must win the evidence by the margin and must not
predict unseen points measurably worse than the simpler model it replaces.

Measured (accuracy benchmark, four scenarios, N = 300 and 1000, five seeds each): the check
never overturned the evidence.  Every winner predicted better than the simpler model it
replaced: kinematic or correlated against independent by 10-24 standard errors at N = 1000
(0.015-0.16 px^2) and 5.6-12 at N = 300, hybrid on ``mixed`` against its field-off limit by
7.5-13 (0.011-0.026 px^2) and 2.8-5.6.  On ``nongeometric`` seed 0 (N = 1000), where the
evidence puts a field (0.3 mm, 0.6 m) on the kinematic model and the cameras get worse (shape
0.183 against 0.168 mm), the field also predicts unseen points slightly better (0.4332 against
0.4336 px, -0.0004 +- 0.0002 px^2): it fits real structure of the non-geometric errors, and
neither the evidence nor held-out reprojection sees what it costs the cameras.  The check does
reject a wrong complex model: a kinematic model whose joint states are each paired with the
neighbouring sample predicts held-out points worse than ``independent`` (+3.7 and +2.1 standard
errors on two of four geometric seeds at N = 300; within the noise on the other two, where its
prior keeps the wrong correction small).  Five folds rather than one: the paired difference of
the right kinematic model against ``independent`` is 5-12 standard errors on five folds against
2-4.5 on one (geometric, N = 300, four seeds); the cost is eight more fits per search (``auto``
at N = 1000 on ``gp-prior``: 8.5 s against 6.8 s with the check on one fold and 5.5 s with no
held-out fits).

Image noise.  The evidence weighs the image term against the prior through the pixel sigma
s_px, so it is only as good as s_px: with s_px several times the real noise the images barely
tell the models apart and the Occam penalty hands the choice to the simplest (measured on
pooled detections, accurate to ~0.01-0.06 px, against the 0.5 px default).  So ``auto`` first
estimates s_px itself (:func:`estimate_pixel_sigma`): the a-posteriori variance factor of a
free-network adjustment, in which every point may move far more than any arm's bias (a 10 mm
prior), so the residuals hold image noise only, divided by the redundancy:

    s_px^2 = sum |r_k|^2 / (2 M - (C - 7) - sum_i d_i)

over the M inlier observations, C camera parameters (less the 7 of the similarity the images
cannot fix) and d_i = 3 unknowns per point seen at least twice (2 if seen once).  That model
does not depend on which noise model is true, so one estimate serves every candidate; the
search then runs with it (and starts from the free network's cameras and points, which sit
next to every candidate's optimum).

With one camera (or cameras that never see the same sample) the free network has no
redundancy: each point can move to fit its single view exactly.  Then the engine may pass the
scatter of the pooled detections (:func:`pooled_pixel_sigma`): each observation pools n_k
frames of one dwell, whose RMS distance from their mean is d_k, so the per-frame noise per axis
is s_f^2 = sum n_k d_k^2 / (2 sum (n_k - 1)) and the pooled observation's is s_f^2 / n_k.  It
is a lower bound - an error that stays put for a dwell (marker appearance, a detector's bias
for one view) does not scatter - so it is used only where the free network cannot be, and the
held-out check still guards the choice.  On the demo bag the two agree (0.0105 px from the
scatter against 0.0099 px from the free network, measured).
"""

import time
from dataclasses import dataclass, field, replace
from typing import Dict, List, Optional

import numpy as np

from armcal_ros.core.adjustment import (AdjustmentResult, Observations, SolverSettings,
                                        adjust)
from armcal_ros.core.priors import KINEMATIC_MODELS, PriorSettings

#: Complexity order for the Occam rule: among candidates within ``occam_margin`` of the best
#: evidence the simplest model is chosen.
COMPLEXITY = {'fixed': 0, 'independent': 1, 'kinematic': 2, 'correlated': 2, 'hybrid': 3}
#: Evidence margin (natural log units) below which a more complex model is not preferred:
#: ln B < 3 is "not worth more than a bare mention" to "positive" (Kass and Raftery, 1995).
OCCAM_MARGIN = 3.0
#: Folds of the held-out check (each point is held out once; the report uses the first fold).
HOLDOUT_FOLDS = 5
#: Folds the Occam check compares on (the first ones; the report always uses the first).
HOLDOUT_CHECK_FOLDS = 5
#: A more complex candidate is rejected when its held-out squared error exceeds the simpler
#: one's by more than this many standard errors of the paired difference (module doc): one
#: standard error, as in the one-standard-error rule of cross-validation.
HOLDOUT_Z = 1.0

#: Point sigma (m) of the free-network adjustment that estimates the image noise: far looser
#: than any arm's bias, so the points follow the images, yet a regulariser for points seen once.
FREE_POINT_SIGMA = 0.01
#: Iteration cap and relative cost tolerance of a candidate's adjustment (the chosen one is
#: re-run with the caller's settings).  1e-6 of a cost of a few thousand is ~1e-2 in the log
#: evidence, far below the Occam margin; it halves the iterations of the search.
CANDIDATE_MAX_ITERATIONS = 30
CANDIDATE_FTOL = 1e-6

#: Hyperparameter grid of ``auto`` (metres; the kinematic scale multiplies the default sigmas).
#: ``kinematic_point_sigma`` is the per-point term s_n of the kinematic models: what the
#: kinematic parameters leave (linearisation, non-geometric errors), typically far below the
#: 0.2 mm default that suits the field models.
DEFAULT_GRID = {
    'coherence_length': (0.15, 0.3, 0.6),
    'bias_sigma': (0.3e-3, 1e-3, 3e-3),
    'hybrid_bias_sigma': (0.1e-3, 0.3e-3, 1e-3),
    'kinematic_scale': (0.5, 1.0, 2.0),
    'kinematic_point_sigma': (0.02e-3, 0.05e-3, 0.2e-3),
}
#: hybrid's field is for local structure: its coherence length is at most this multiple of the
#: samples' RMS radius about their centroid.  A field correlated across the whole sampled
#: workspace (L near its diameter, twice that radius) is close to a global smooth deformation,
#: which the kinematic part and the cameras' similarity gauge already span, so it trades with
#: the cameras instead of describing the arm (measured: on the demo bag and `nongeometric`
#: seed 0 the evidence chose L = 0.6 m over a 0.3 m RMS radius, and the cameras' shape error grew
#: 9-17 % over the kinematic model's; BENCHMARKS.md).  ``correlated`` alone keeps the whole grid:
#: there the field is the only model of the bias.
HYBRID_MAX_L_FRACTION = 1.5

#: The 1-D search of the kinematic scale: the grid is extended by factors of two until the best
#: value is bracketed (at most this many times each way), then refined by successive parabolic
#: interpolation of the log evidence in log scale until the step is below ``SCALE_TOLERANCE``
#: (relative) or ``SCALE_REFINEMENTS`` evaluations are spent.
SCALE_EXTENSIONS = 2
SCALE_REFINEMENTS = 3
SCALE_TOLERANCE = 0.05
#: Range of the kinematic scale search.  Beyond 8 x the default sigmas (0.8 deg offsets, 4 mm
#: link errors) the kinematic model is not describing an arm any more but absorbing whatever
#: the data hold (on the ``gp-prior`` benchmark, a position field it cannot represent, the
#: evidence runs to the bound, hundreds of log units below the correlated model); an arm that
#: really is that far off needs its own scales.
SCALE_BOUNDS = (0.125, 8.0)


@dataclass
class Candidate:
    """One adjusted candidate: its settings, evidence and held-out check."""

    settings: PriorSettings
    log_evidence: float
    time_s: float
    success: bool
    holdout_px: float = float('nan')
    holdout_note: str = ''                  # the held-out comparison that rejected it, if any
    result: Optional[AdjustmentResult] = None
    cameras: Optional[list] = None          # the candidate's estimated cameras

    def label(self):
        """Return a short description: model and hyperparameters."""
        s = self.settings
        parts = [s.model]
        if s.model in ('correlated', 'hybrid'):
            parts.append(f's_b={s.bias_sigma * 1e3:.2g}mm L={s.coherence_length:.2g}m')
        if s.model in KINEMATIC_MODELS:
            parts.append(f'kin_scale={s.kinematic_scale:.3g} s_n={s.point_sigma * 1e3:.2g}mm')
        return ' '.join(parts)

    def as_dict(self):
        """Plain dictionary for reports."""
        s = self.settings
        return {'model': s.model, 'bias_sigma': s.bias_sigma,
                'coherence_length': s.coherence_length, 'kinematic_scale': s.kinematic_scale,
                'point_sigma': s.point_sigma, 'log_evidence': self.log_evidence,
                'holdout_px': self.holdout_px, 'time_s': self.time_s, 'success': self.success,
                'label': self.label()}


@dataclass
class ModelSelection:
    """The choice: ``settings`` and its ``result``, every candidate, and why."""

    settings: PriorSettings
    result: AdjustmentResult
    candidates: List[Candidate] = field(default_factory=list)
    reason: str = ''
    time_s: float = 0.0
    pixel_sigma: float = float('nan')       # the image noise the evidence was computed with
    noise: Optional['NoiseEstimate'] = None
    within: Dict[str, Candidate] = field(default_factory=dict)   # choice_of per model
    #: The held-out comparisons made by the Occam rule: complex and simpler label, excess
    #: squared error (px^2) and its standard error, both RMS (px), and whether it rejected.
    holdout_checks: List[dict] = field(default_factory=list)

    def best_of(self, model):
        """Return the best (highest-evidence) candidate of ``model``, or None."""
        c = [x for x in self.candidates if x.settings.model == model and x.success]
        return max(c, key=lambda x: x.log_evidence) if c else None

    def choice_of(self, model):
        """
        Return the candidate of ``model`` that ``auto`` would choose were it the only model.

        The Occam rule of :func:`select_model` applied within the model: among its candidates
        within the margin of its best evidence, the simplest (a hybrid with its field or its
        kinematic part switched off counts as that simpler model) with the best evidence, and
        a more complex one only if the held-out check did not reject it (recorded by
        :func:`select_model`).  None when ``model`` has no successful candidate.
        """
        return self.within.get(model)


@dataclass
class NoiseEstimate:
    """Image noise from a free-network adjustment (:func:`estimate_pixel_sigma`)."""

    pixel_sigma: float
    redundancy: float
    n_observations: int
    result: AdjustmentResult

    @property
    def success(self):
        """Whether the estimate is usable (finite, positive, with redundancy left)."""
        return bool(np.isfinite(self.pixel_sigma) and self.pixel_sigma > 0 and
                    self.redundancy > 0 and self.result.status != 'failed')


def pooled_pixel_sigma(spread_px, n_frames) -> float:
    """
    Image noise (px per axis) of pooled observations from the scatter of their frames.

    ``spread_px`` (M,) is each observation's RMS distance of its pooled detections from the
    pooled value, ``n_frames`` (M,) how many frames it pooled (module doc):

        s_f^2 = sum_k n_k d_k^2 / (2 sum_k (n_k - 1)),   s_px = sqrt(mean_k s_f^2 / n_k).

    NaN when no observation pooled two frames or more.
    """
    d = np.asarray(spread_px, float).reshape(-1)
    n = np.asarray(n_frames, float).reshape(-1)
    if d.shape != n.shape:
        raise ValueError(f'spread_px and n_frames must have one entry per observation, got '
                         f'{d.shape} and {n.shape}')
    ok = np.isfinite(d) & (n >= 2)
    dof = 2.0 * np.sum(n[ok] - 1.0)
    if dof <= 0:
        return float('nan')
    frame_var = float(np.sum(n[ok] * d[ok] ** 2) / dof)
    return float(np.sqrt(np.mean(frame_var / n[ok])))


def estimate_pixel_sigma(cameras, measured, obs: Observations, settings: SolverSettings = None,
                         inliers=None, point_sigma: float = FREE_POINT_SIGMA) -> NoiseEstimate:
    """
    Estimate the image noise s_px (px per axis) from a free-network adjustment (module doc).

    ``cameras`` are warm-start estimates, ``inliers`` the observations to use (default all).
    The points get an independent prior of ``point_sigma`` (m), much looser than the images,
    so the residuals are image noise; their sum of squares over the redundancy
    2 M - (C - 7) - sum_i d_i is the a-posteriori variance factor of photogrammetry.
    """
    if not point_sigma > 0:
        raise ValueError(f'point_sigma must be > 0, got {point_sigma}')
    settings = settings or SolverSettings()
    measured = np.asarray(measured, float)
    res = adjust(cameras, measured, obs, PriorSettings('independent', point_sigma=point_sigma),
                 replace(settings, max_gate_rounds=0), inliers=inliers)
    active = res.inliers
    m = int(np.count_nonzero(active))
    if res.status == 'failed' or m == 0:
        return NoiseEstimate(float('nan'), 0.0, m, res)
    rss = sum(e.rms_px ** 2 * e.n_inliers for e in res.cameras.values() if e.n_inliers)
    seen = np.bincount(obs.point[active], minlength=measured.shape[0])
    point_dof = 3.0 * np.count_nonzero(seen >= 2) + 2.0 * np.count_nonzero(seen == 1)
    n_cam = len(res.parameter_names)
    redundancy = 2.0 * m - max(n_cam - 7, 0) - point_dof
    sigma = float(np.sqrt(rss / redundancy)) if redundancy > 0 else float('nan')
    return NoiseEstimate(sigma, float(redundancy), m, res)


def select_model(cameras, measured, obs: Observations, base: PriorSettings = None,
                 settings: SolverSettings = None, kinematics=None, inliers=None,
                 grid: Optional[Dict] = None, models=None, holdout=True,
                 rng=None, occam_margin: float = OCCAM_MARGIN,
                 estimate_noise: bool = True,
                 pooled_sigma_px: Optional[float] = None) -> ModelSelection:
    """
    Choose the noise model and hyperparameters by the Laplace evidence (module docstring).

    ``cameras`` are warm-start estimates (normally the ``fixed`` solution), ``inliers`` its
    inlier mask (kept for every candidate so that their evidences compare the same data).
    ``base`` supplies the settings not searched (point sigma, kernel, lattice options).
    ``models`` restricts the candidates; kinematic ones are dropped without ``kinematics``.
    Among candidates within ``occam_margin`` (natural log) of the best evidence, the simplest
    model (:data:`COMPLEXITY`) wins: a difference that small is noise in the Laplace estimate,
    and the simpler model is the safer bet.  With ``holdout`` the winner must also not predict
    held-out points worse than the simpler model it replaces (by more than ``HOLDOUT_Z``
    standard errors over ``HOLDOUT_FOLDS`` folds; module doc), and the best candidate of each
    model gets its held-out RMS (``Candidate.holdout_px``, the first fold); ``rng`` draws the
    folds.  With ``estimate_noise`` the image noise is first
    estimated (:func:`estimate_pixel_sigma`) and replaces ``settings.pixel_sigma`` in every
    candidate and in the returned result (``ModelSelection.pixel_sigma``); where the free
    network has no redundancy (one camera), ``pooled_sigma_px`` (:func:`pooled_pixel_sigma`),
    if given and positive, is used instead.
    """
    t0 = time.perf_counter()
    base = replace(base or PriorSettings(), model='fixed')
    settings = settings or SolverSettings()
    grid = {**DEFAULT_GRID, **(grid or {})}
    rng = rng if rng is not None else np.random.default_rng(0)
    allowed = list(models or ('fixed', 'independent', 'correlated', 'kinematic', 'hybrid'))
    if kinematics is None:
        allowed = [m for m in allowed if m not in KINEMATIC_MODELS]
    noise = None
    noise_from_scatter = False
    points0 = None
    quiet = replace(settings, max_gate_rounds=0, ftol=max(settings.ftol, CANDIDATE_FTOL),
                    max_iterations=min(settings.max_iterations, CANDIDATE_MAX_ITERATIONS))
    if estimate_noise:
        noise = estimate_pixel_sigma(cameras, measured, obs, quiet, inliers, FREE_POINT_SIGMA)
        if noise.success:
            settings = replace(settings, pixel_sigma=noise.pixel_sigma)
            quiet = replace(quiet, pixel_sigma=noise.pixel_sigma)
            cameras = noise.result.camera_list()
            points0 = noise.result.points
        elif pooled_sigma_px is not None and np.isfinite(pooled_sigma_px) \
                and pooled_sigma_px > 0:
            settings = replace(settings, pixel_sigma=float(pooled_sigma_px))
            quiet = replace(quiet, pixel_sigma=float(pooled_sigma_px))
            noise_from_scatter = True
    cands: List[Candidate] = []
    seen = {}
    last_kin = {}

    def run(**kw):
        ps = replace(base, **kw)
        key = _prior_key(ps)
        if (ps.model, key) in seen:
            return seen[ps.model, key]
        twin = seen.get((key[0], key))
        if twin is not None and ps.model == 'hybrid':
            # Hybrid with one part switched off is that simpler model: reuse its solve.
            c = Candidate(ps, twin.log_evidence, 0.0, twin.success, result=twin.result,
                          cameras=twin.cameras)
            cands.append(c)
            seen[ps.model, key] = c
            return c
        t = time.perf_counter()
        g0 = None
        if ps.model == 'kinematic' and last_kin and ps.kinematic_scale > 0:
            # Same physical errors dp = g sigma scale: rescale the whitened start.
            prev = last_kin['c']
            g0 = prev.result.global_parameters * (prev.settings.kinematic_scale /
                                                  ps.kinematic_scale)
        res = adjust(cameras, measured, obs, ps, quiet, inliers=inliers,
                     points_init=None if ps.model == 'fixed' else points0, globals_init=g0,
                     kinematics=kinematics if ps.model in KINEMATIC_MODELS else None)
        ok = bool(res.status != 'failed' and np.isfinite(res.log_evidence))
        c = Candidate(ps, res.log_evidence if ok else -np.inf, time.perf_counter() - t, ok,
                      result=res, cameras=res.camera_list())
        cands.append(c)
        seen[ps.model, key] = c
        if ps.model == 'kinematic' and ok and res.global_parameters is not None:
            last_kin['c'] = c
        return c

    def best(cs):
        return max(cs, key=lambda c: c.log_evidence)

    for m in ('fixed', 'independent'):
        if m in allowed:
            run(model=m)
    kin = None
    if 'kinematic' in allowed or 'hybrid' in allowed:
        kin = _search_scale(lambda k, ps: run(model='kinematic', kinematic_scale=k,
                                              point_sigma=ps),
                            grid['kinematic_scale'], base.point_sigma)
        kin = best([kin] + [run(model='kinematic', kinematic_scale=kin.settings.kinematic_scale,
                                point_sigma=ps) for ps in grid['kinematic_point_sigma']])
        k = kin.settings.kinematic_scale
        kin = _search_scale(lambda k, ps: run(model='kinematic', kinematic_scale=k,
                                              point_sigma=ps),
                            (0.5 * k, k, 2.0 * k), kin.settings.point_sigma)
    corr = None
    if 'correlated' in allowed or 'hybrid' in allowed:
        sb0 = base.bias_sigma if base.bias_sigma > 0 else 1e-3
        L = best([run(model='correlated', bias_sigma=sb0, coherence_length=L)
                  for L in grid['coherence_length']]).settings.coherence_length
        corr = best([run(model='correlated', bias_sigma=sb, coherence_length=L)
                     for sb in grid['bias_sigma']]).settings
    if 'hybrid' in allowed:
        # Coordinate ascent from the kinematic optimum with a small field, compared with the
        # two limits: the field off (the best kinematic model) and the kinematic part off (the
        # best correlated model), so hybrid can only gain on either.
        ks, ps = kin.settings.kinematic_scale, kin.settings.point_sigma
        sbh = sorted(grid['hybrid_bias_sigma'])[len(grid['hybrid_bias_sigma']) // 2]
        h = best([run(model='hybrid', bias_sigma=sbh, coherence_length=L, kinematic_scale=ks,
                      point_sigma=ps) for L in _local_lengths(grid['coherence_length'], measured)])
        h = best([h] + [run(model='hybrid', bias_sigma=sb, kinematic_scale=ks, point_sigma=ps,
                            coherence_length=h.settings.coherence_length)
                        for sb in grid['hybrid_bias_sigma']])
        h = best([h, run(model='hybrid', bias_sigma=0.0, kinematic_scale=ks, point_sigma=ps,
                         coherence_length=h.settings.coherence_length)])
        if corr is not None:
            h = best([h, run(model='hybrid', bias_sigma=corr.bias_sigma, kinematic_scale=0.0,
                             coherence_length=corr.coherence_length,
                             point_sigma=corr.point_sigma)])
        hs = h.settings
        if hs.kinematic_scale > 0 and hs.bias_sigma > 0:
            best([h] + [run(model='hybrid', bias_sigma=hs.bias_sigma, kinematic_scale=k,
                            coherence_length=hs.coherence_length, point_sigma=hs.point_sigma)
                        for k in grid['kinematic_scale']])
    if 'correlated' not in allowed:
        cands = [c for c in cands if c.settings.model != 'correlated']
    if 'kinematic' not in allowed:
        cands = [c for c in cands if c.settings.model != 'kinematic']
    ok = [c for c in cands if c.success]
    if not ok:
        raise ValueError('no candidate model could be adjusted: ' +
                         '; '.join(c.result.message for c in cands))
    top = best(ok)
    check = _HeldOut(cameras, measured, obs, quiet, kinematics, inliers, rng, points0) \
        if holdout else None
    chosen = _occam_choice(ok, occam_margin, check)
    models_ok = list(dict.fromkeys(c.settings.model for c in ok))
    within = {m: _occam_choice([c for c in ok if c.settings.model == m], occam_margin, check)
              for m in models_ok}
    if check is not None:
        for c in [best([x for x in ok if x.settings.model == m]) for m in models_ok] + \
                list(within.values()):
            if not np.isfinite(c.holdout_px):
                c.holdout_px = check.rms(c)
    reason = _reason(chosen, ok)
    if noise is not None and noise.success:
        reason += (f'; image noise {noise.pixel_sigma:.3g} px estimated from the free-network '
                   f'residuals ({noise.n_observations} observations, redundancy '
                   f'{noise.redundancy:.0f}) and used for every candidate')
    elif noise_from_scatter:
        reason += (f'; image noise {settings.pixel_sigma:.3g} px from the scatter of the pooled '
                   'detections (the free network has no redundancy, e.g. one camera; a lower '
                   'bound) and used for every candidate')
    else:
        reason += f'; image noise {settings.pixel_sigma:.3g} px (as configured)'
    rejected = [c for c in ok if c.holdout_note and
                c.log_evidence > chosen.log_evidence + occam_margin]
    for c in sorted(rejected, key=lambda c: -c.log_evidence):
        reason += f'; {c.label()} ({c.log_evidence - chosen.log_evidence:+.1f}) ' + \
            c.holdout_note
    if chosen is not top and top not in rejected:
        reason += (f'; {top.label()} had {top.log_evidence - chosen.log_evidence:.1f} more log '
                   f'evidence, under the Occam margin of {occam_margin:g}: the simpler model '
                   'was kept')
    final = adjust(chosen.result.camera_list(), measured, obs, chosen.settings, settings,
                   points_init=chosen.result.points, inliers=inliers,
                   kinematics=kinematics if chosen.settings.model in KINEMATIC_MODELS else None,
                   globals_init=chosen.result.global_parameters,
                   prior=chosen.result.prior)
    for c in cands:
        c.result = None if c is not chosen else c.result
    return ModelSelection(chosen.settings, final, cands, reason, time.perf_counter() - t0,
                          settings.pixel_sigma, noise, within,
                          check.log if check is not None else [])


def _complexity(c):
    """Complexity of a candidate's prior: a hybrid with one part off is the simpler model."""
    s = c.settings
    if s.model == 'hybrid' and (s.kinematic_scale == 0 or s.bias_sigma == 0):
        return COMPLEXITY['kinematic']
    return COMPLEXITY.get(s.model, 9)


def _prior_key(ps):
    """Identify the prior a candidate solves: hybrid with one part switched off is that model."""
    model = _canonical(ps).model
    field_part = (ps.bias_sigma, ps.coherence_length) if model in (
        'correlated', 'hybrid') else None
    kin = ps.kinematic_scale if model in KINEMATIC_MODELS else None
    return (model, field_part, kin, ps.point_sigma if model != 'fixed' else None)


def _canonical(ps):
    """Return the settings of the model a hybrid with one part switched off is."""
    if ps.model == 'hybrid' and ps.kinematic_scale == 0:
        return replace(ps, model='correlated')
    if ps.model == 'hybrid' and ps.bias_sigma == 0:
        return replace(ps, model='kinematic')
    return ps


def _occam_choice(cands, margin, check=None):
    """
    Return the Occam choice among ``cands``: evidence margin, then the held-out check.

    The evidence choice c (:func:`_evidence_choice`) is compared with the evidence choice s
    among the strictly simpler candidates by ``check`` (a :class:`_HeldOut`, module doc); if
    c predicts the held-out points worse, the choice is made again among the simpler ones.
    """
    c = _evidence_choice(cands, margin)
    if check is None:
        return c
    simpler = [x for x in cands if _complexity(x) < _complexity(c)]
    if simpler and check.rejects(c, _evidence_choice(simpler, margin)):
        return _occam_choice(simpler, margin, check)
    return c


def _evidence_choice(cands, margin):
    """Among ``cands`` within ``margin`` of the best evidence, the best of the simplest."""
    top = max(c.log_evidence for c in cands)
    near = [c for c in cands if c.log_evidence >= top - margin]
    simplest = min(_complexity(c) for c in near)
    # ties (a hybrid limit and the model it equals) go to the plain model: lower table rank
    return max((c for c in near if _complexity(c) == simplest),
               key=lambda c: (c.log_evidence, -COMPLEXITY.get(c.settings.model, 9)))


def _local_lengths(lengths, points):
    """Return the coherence lengths within ``HYBRID_MAX_L_FRACTION`` x the points' RMS radius."""
    P = np.asarray(points, float).reshape(-1, 3)
    radius = float(np.sqrt(np.mean(np.sum((P - P.mean(axis=0)) ** 2, axis=1))))
    kept = [L for L in lengths if L <= HYBRID_MAX_L_FRACTION * radius]
    return kept or [min(lengths)]


def _search_scale(evaluate, grid, point_sigma):
    """
    Evidence-maximising 1-D search of the kinematic scale; returns the best candidate.

    ``evaluate(scale, point_sigma)`` returns a :class:`Candidate`.  The ``grid`` is extended by
    factors of two while its best value sits at an end (``SCALE_EXTENSIONS`` times, within
    ``SCALE_BOUNDS``), then the maximum is refined by successive parabolic interpolation of the
    log evidence against log scale through the best point and its two neighbours
    (``SCALE_REFINEMENTS`` steps, until the step is under ``SCALE_TOLERANCE``).
    """
    ev = {}

    def at(k):
        ev[float(k)] = evaluate(float(k), point_sigma)

    def value(k):
        c = ev[k]
        return c.log_evidence if c.success and np.isfinite(c.log_evidence) else -np.inf

    lo, hi = SCALE_BOUNDS
    for k in grid:
        at(min(max(k, lo), hi))
    for _ in range(SCALE_EXTENSIONS):
        ks = sorted(ev)
        top = max(ks, key=value)
        if top == ks[0] and np.isfinite(value(top)) and ks[0] > lo:
            at(max(ks[0] / 2.0, lo))
        elif top == ks[-1] and np.isfinite(value(top)) and ks[-1] < hi:
            at(min(ks[-1] * 2.0, hi))
        else:
            break
    tol = np.log1p(SCALE_TOLERANCE)
    for _ in range(SCALE_REFINEMENTS):
        ks = sorted(ev)
        i = int(np.argmax([value(k) for k in ks]))
        if i == 0 or i == len(ks) - 1:
            break
        x = np.log(ks[i - 1:i + 2])
        y = np.array([value(k) for k in ks[i - 1:i + 2]])
        if not np.all(np.isfinite(y)):
            break
        # Vertex of the parabola through three points (concave, since the middle is highest).
        d1, d2 = (y[1] - y[0]) / (x[1] - x[0]), (y[2] - y[1]) / (x[2] - x[1])
        curv = (d2 - d1) / (x[2] - x[0])
        if not curv < 0:
            break
        xv = 0.5 * (x[0] + x[1]) - d1 / (2.0 * curv)
        xv = float(np.clip(xv, x[0] + tol, x[2] - tol))
        if min(abs(xv - np.log(k)) for k in ks) < tol:
            break
        at(np.exp(xv))
    return max(ev.values(), key=lambda c: c.log_evidence if c.success else -np.inf)


def _reason(chosen, ok):
    per_model = {}
    for c in ok:
        m = c.settings.model
        if m not in per_model or c.log_evidence > per_model[m].log_evidence:
            per_model[m] = c
    ranked = sorted(per_model.values(), key=lambda c: -c.log_evidence)
    text = f'chose {chosen.label()} by the Laplace evidence (log {chosen.log_evidence:.1f})'
    if len(ranked) > 1:
        r = ranked[1]
        text += f'; next best model {r.label()} at {r.log_evidence - chosen.log_evidence:+.1f}'
    held = [c for c in ranked if np.isfinite(c.holdout_px)]
    if held:
        hb = min(held, key=lambda c: c.holdout_px)
        text += '; held-out reprojection ' + ', '.join(
            f'{c.settings.model} {c.holdout_px:.3f} px' for c in held)
        if hb.settings.model != chosen.settings.model and \
                hb.holdout_px < 0.97 * chosen.holdout_px:
            text += f' (the held-out check prefers {hb.settings.model})'
    return text


def holdout_reprojection(cameras, measured, obs: Observations, prior: PriorSettings,
                         settings: SolverSettings, kinematics=None, inliers=None, rng=None,
                         fraction=0.2):
    """
    RMS pixel error of held-out points predicted by the model fitted on the rest (module doc).

    A random ``fraction`` of the points is held out; the model is adjusted on the others
    (warm-started from ``cameras``); each held-out point is predicted as X^ + the model's
    correction and projected with the fitted cameras.
    """
    rng = rng if rng is not None else np.random.default_rng(0)
    measured = np.asarray(measured, float)
    n = measured.shape[0]
    held = np.zeros(n, bool)
    held[rng.choice(n, max(1, int(round(fraction * n))), replace=False)] = True
    train = np.flatnonzero(~held)
    remap = -np.ones(n, int)
    remap[train] = np.arange(train.size)
    active = np.ones(len(obs), bool) if inliers is None else np.asarray(inliers, bool)
    sel = ~held[obs.point] & active
    sub = Observations(obs.camera[sel], remap[obs.point[sel]], obs.uv[sel])
    kin = kinematics.subset(train) if kinematics is not None and \
        prior.model in KINEMATIC_MODELS else None
    res = adjust(cameras, measured[train], sub, prior, settings, kinematics=kin)
    if res.status == 'failed':
        return float('nan')
    hidx = np.flatnonzero(held)
    jac = kinematics.jacobian[hidx] if kin is not None else None
    pred = measured[hidx] + res.predict_offsets(measured[hidx], jac)
    where = -np.ones(n, int)
    where[hidx] = np.arange(hidx.size)
    test = held[obs.point] & active
    cams = res.camera_list()
    err = []
    for j, c in enumerate(cams):
        m = test & (obs.camera == j)
        if m.any():
            uv = c.project(pred[where[obs.point[m]]])
            err.append(np.sum((uv - obs.uv[m]) ** 2, axis=1))
    if not err:
        return float('nan')
    return float(np.sqrt(np.mean(np.concatenate(err))))


class _HeldOut:
    """
    Paired held-out comparison of candidates on one split of the points into folds.

    Every candidate is scored on the same folds (``HOLDOUT_FOLDS``, drawn once from ``rng``);
    a fold's fit is cached by the prior it solves, so a hybrid limit and the model it equals
    share it.  ``rms`` is the report's number (the first fold), ``rejects`` the Occam check
    (module doc).
    """

    def __init__(self, cameras, measured, obs, settings, kinematics, inliers, rng,
                 points0=None, folds=HOLDOUT_FOLDS, z=HOLDOUT_Z,
                 check_folds=None):
        self.cameras, self.obs, self.settings = cameras, obs, settings
        self.measured = np.asarray(measured, float)
        self.kinematics, self.points0, self.z = kinematics, points0, z
        n = self.measured.shape[0]
        self.folds = folds
        self.check_folds = min(folds, check_folds or HOLDOUT_CHECK_FOLDS)
        self.fold = rng.permutation(n) % folds
        self.active = np.ones(len(obs), bool) if inliers is None else np.asarray(inliers, bool)
        self._sq = {}
        self._verdict = {}
        self.log = []

    def squared(self, cand, f):
        """Squared pixel error of each observation of fold ``f`` (NaN elsewhere)."""
        ps = _canonical(cand.settings)
        key = (_prior_key(ps), f)
        if key not in self._sq:
            self._sq[key] = self._fit_fold(cand, ps, f)
        return self._sq[key]

    def _fit_fold(self, cand, ps, f):
        obs, measured = self.obs, self.measured
        n = measured.shape[0]
        held = self.fold == f
        train = np.flatnonzero(~held)
        remap = -np.ones(n, int)
        remap[train] = np.arange(train.size)
        sel = ~held[obs.point] & self.active
        sub = Observations(obs.camera[sel], remap[obs.point[sel]], obs.uv[sel])
        kin = self.kinematics.subset(train) if self.kinematics is not None and \
            ps.model in KINEMATIC_MODELS else None
        g0 = None
        if ps.model == 'kinematic' and cand.result is not None and \
                cand.result.global_parameters is not None:
            g0 = cand.result.global_parameters
        p0 = self.points0[train] if self.points0 is not None and ps.model != 'fixed' else None
        out = np.full(len(obs), np.nan)
        res = adjust(self.cameras, measured[train], sub, ps, self.settings, kinematics=kin,
                     points_init=p0, globals_init=g0)
        if res.status == 'failed':
            return out
        hidx = np.flatnonzero(held)
        jac = self.kinematics.jacobian[hidx] if kin is not None else None
        pred = measured[hidx] + res.predict_offsets(measured[hidx], jac)
        where = -np.ones(n, int)
        where[hidx] = np.arange(hidx.size)
        test = held[obs.point] & self.active
        for j, c in enumerate(res.camera_list()):
            m = test & (obs.camera == j)
            if m.any():
                uv = c.project(pred[where[obs.point[m]]])
                out[m] = np.sum((uv - obs.uv[m]) ** 2, axis=1)
        return out

    def rms(self, cand, folds=(0,)):
        """RMS pixel error of ``cand`` over the held-out observations of ``folds``."""
        e = np.concatenate([self.squared(cand, f)[self.fold[self.obs.point] == f]
                            for f in folds])
        e = e[np.isfinite(e)]
        return float(np.sqrt(np.mean(e))) if e.size else float('nan')

    def all_folds(self, cand, folds=None):
        """Squared pixel error of the observations of the first ``folds`` folds (NaN else)."""
        of = self.fold[self.obs.point]
        e = np.full(len(self.obs), np.nan)
        for f in range(self.folds if folds is None else folds):
            m = of == f
            e[m] = self.squared(cand, f)[m]
        return e

    def compare(self, c, s):
        """
        Return (D, se, rms_c, rms_s) on the check's folds: c's excess squared error and its SE.

        D = sum_i d_i / M (px^2) over the points i, d_i summing e(c) - e(s) over the point's
        held-out observations (M in all); se = sqrt(n) std(d_i) / M over the n points, the
        point being the sampling unit (its observations share one predicted position).
        """
        ec, es = self.all_folds(c, self.check_folds), self.all_folds(s, self.check_folds)
        ok = np.isfinite(ec) & np.isfinite(es)
        m = int(np.count_nonzero(ok))
        if m == 0:
            return float('nan'), float('nan'), float('nan'), float('nan')
        pts = self.obs.point[ok]
        d = np.bincount(pts, ec[ok] - es[ok], minlength=self.measured.shape[0])
        d = d[np.bincount(pts, minlength=self.measured.shape[0]) > 0]
        se = float(np.sqrt(d.size) * np.std(d, ddof=1) / m) if d.size > 1 else float('inf')
        return (float(d.sum() / m), se, float(np.sqrt(np.mean(ec[ok]))),
                float(np.sqrt(np.mean(es[ok]))))

    def rejects(self, c, s):
        """Whether ``c`` predicts held-out points worse than ``s`` by more than z SE."""
        pair = (_prior_key(_canonical(c.settings)), _prior_key(_canonical(s.settings)))
        if pair[0] == pair[1]:
            return False
        if pair in self._verdict:
            if self._verdict[pair]:
                c.holdout_note = self._verdict[pair]
            return bool(self._verdict[pair])
        self._verdict[pair] = ''
        excess, se, rc, rs = self.compare(c, s)
        reject = bool(np.isfinite(excess) and np.isfinite(se) and excess > self.z * se)
        self.log.append(dict(complex=c.label(), simpler=s.label(), excess_px2=excess,
                             se_px2=se, rms_complex_px=rc, rms_simpler_px=rs,
                             rejected=reject))
        if not reject:
            return False
        c.holdout_note = (f'rejected by the held-out check: it predicts held-out points worse '
                          f'than {s.label()} ({rc:.3f} against {rs:.3f} px over '
                          f'{self.check_folds} of {self.folds} folds; excess {excess:.4f} +- '
                          f'{se:.4f} px^2, more than {self.z:g} standard error)')
        self._verdict[pair] = c.holdout_note
        return True
