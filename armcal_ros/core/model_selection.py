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
A more complex model must beat a simpler one by ``OCCAM_MARGIN`` (3 in natural log) to be
chosen.

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

Held-out reprojection is part of the Occam rule (:mod:`armcal_ros.core.holdout`: the folds
and the paired comparison).  The report gives, for the best candidate of each model, the RMS
pixel error on the first fold (a fifth of the points): how well the model predicts where the
arm really is.  The choice runs down the complexity ladder: the evidence choice c (above) is
compared with the evidence choice s among the strictly simpler candidates (all of which are
nested in c: a sigma switched off), on all folds, i.e. every point held out once.  c is kept
unless it predicts the held-out observations worse than s by more than ``HOLDOUT_Z`` standard
errors of the paired difference; otherwise s replaces it and is checked the same way against
the candidates simpler than itself.  So a more complex model must win the evidence by the
margin and must not predict unseen points measurably worse than the simpler model it replaces.

Image noise.  The evidence weighs the image term against the prior through the pixel sigma
s_px, so it is only as good as s_px: with s_px several times the real noise the images barely
tell the models apart and the Occam penalty hands the choice to the simplest.  So ``auto``
first estimates s_px itself from a free-network adjustment
(:func:`~armcal_ros.core.image_noise.estimate_pixel_sigma`), or, where that has no redundancy
(one camera), takes the scatter of the pooled detections the caller passes
(:func:`~armcal_ros.core.image_noise.pooled_pixel_sigma`), and the held-out check still guards
the choice.  The search then runs with it (and starts from the free network's cameras and
points, which sit next to every candidate's optimum).

How these rules were arrived at (the measurements behind the margin, the search, the held-out
check and the limits below): docs/NOISE_MODELS.md.
"""

import time
from dataclasses import dataclass, field, replace
from typing import Dict, List, Optional

import numpy as np

from armcal_ros.core.adjustment import AdjustmentResult, Observations, SolverSettings, adjust
from armcal_ros.core.holdout import HeldOut
from armcal_ros.core.image_noise import estimate_pixel_sigma, FREE_POINT_SIGMA, NoiseEstimate
from armcal_ros.core.priors import KINEMATIC_MODELS, prior_key, PriorSettings

#: Complexity order for the Occam rule: among candidates within ``occam_margin`` of the best
#: evidence the simplest model is chosen.
COMPLEXITY = {'fixed': 0, 'independent': 1, 'kinematic': 2, 'correlated': 2, 'hybrid': 3}
#: Evidence margin (natural log units) below which a more complex model is not preferred:
#: ln B < 3 is "not worth more than a bare mention" to "positive" (Kass and Raftery, 1995).
OCCAM_MARGIN = 3.0

#: Iteration cap and relative cost tolerance of a candidate's adjustment (the chosen one is
#: re-run with the caller's settings).  1e-6 of a cost of a few thousand is ~1e-2 in the log
#: evidence, far below the Occam margin.
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
#: the cameras instead of describing the arm.  ``correlated`` alone keeps the whole grid: there
#: the field is the only model of the bias.
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
#: the data hold (such as a position field it cannot represent); an arm that really is that far
#: off needs its own scales.
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


@dataclass
class ModelSelection:
    """The choice: ``settings`` and its ``result``, every candidate, and why."""

    settings: PriorSettings
    result: AdjustmentResult
    candidates: List[Candidate] = field(default_factory=list)
    reason: str = ''
    time_s: float = 0.0
    pixel_sigma: float = float('nan')       # the image noise the evidence was computed with
    noise: Optional[NoiseEstimate] = None
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
    held-out points worse than the simpler model it replaces (:class:`HeldOut`: by more than
    ``HOLDOUT_Z`` standard errors over ``HOLDOUT_FOLDS`` folds), and the best candidate of
    each model gets its held-out RMS (``Candidate.holdout_px``, the first fold); ``rng`` draws
    the folds.  With ``estimate_noise`` the image noise is first estimated
    (:func:`~armcal_ros.core.image_noise.estimate_pixel_sigma`) and replaces
    ``settings.pixel_sigma`` in every candidate and in the returned result
    (``ModelSelection.pixel_sigma``); where the free network has no redundancy (one camera),
    ``pooled_sigma_px`` (:func:`~armcal_ros.core.image_noise.pooled_pixel_sigma`), if given
    and positive, is used instead.
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
        key = prior_key(ps)
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
                     kinematics=kinematics if ps.model in KINEMATIC_MODELS else None,
                     redundancy=False)
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
    check = HeldOut(cameras, measured, obs, quiet, kinematics, inliers, rng, points0) \
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


def _occam_choice(cands, margin, check=None):
    """
    Return the Occam choice among ``cands``: evidence margin, then the held-out check.

    The evidence choice c (:func:`_evidence_choice`) is compared with the evidence choice s
    among the strictly simpler candidates by ``check`` (a :class:`HeldOut`, module doc); if c
    predicts the held-out points worse, the choice is made again among the simpler ones.
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
