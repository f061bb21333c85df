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

Check: held-out reprojection.  For the best candidate of each model, a fifth of the points is
held out, the model is fitted on the rest, the held-out points are predicted from the robot's
measurement (X^ plus the model's predicted correction: J_p dp, the field's posterior mean) and
projected with the fitted cameras; the RMS pixel error against their observations says how
well the model predicts where the arm really is.  The evidence decides; the report gives both,
and says so when they disagree.

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

    def best_of(self, model):
        """Return the best (highest-evidence) candidate of ``model``, or None."""
        c = [x for x in self.candidates if x.settings.model == model and x.success]
        return max(c, key=lambda x: x.log_evidence) if c else None

    def choice_of(self, model, occam_margin: float = OCCAM_MARGIN):
        """
        Return the candidate of ``model`` that ``auto`` would choose were it the only model.

        The Occam rule of :func:`select_model` applied within the model: among its candidates
        within ``occam_margin`` of its best evidence, the simplest (a hybrid with its field or
        its kinematic part switched off counts as that simpler model) with the best evidence.
        None when ``model`` has no successful candidate.
        """
        c = [x for x in self.candidates if x.settings.model == model and x.success]
        return _occam_choice(c, occam_margin) if c else None


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
                 estimate_noise: bool = True) -> ModelSelection:
    """
    Choose the noise model and hyperparameters by the Laplace evidence (module docstring).

    ``cameras`` are warm-start estimates (normally the ``fixed`` solution), ``inliers`` its
    inlier mask (kept for every candidate so that their evidences compare the same data).
    ``base`` supplies the settings not searched (point sigma, kernel, lattice options).
    ``models`` restricts the candidates; kinematic ones are dropped without ``kinematics``.
    Among candidates within ``occam_margin`` (natural log) of the best evidence, the simplest
    model (:data:`COMPLEXITY`) wins: a difference that small is noise in the Laplace estimate,
    and the simpler model is the safer bet.  With ``estimate_noise`` the image noise is first
    estimated (:func:`estimate_pixel_sigma`) and replaces ``settings.pixel_sigma`` in every
    candidate and in the returned result (``ModelSelection.pixel_sigma``).
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
    cands: List[Candidate] = []
    seen = {}
    last_kin = {}

    def key_of(ps):
        # The prior a candidate solves: hybrid with one part switched off is that model.
        model = ps.model
        if model == 'hybrid' and ps.kinematic_scale == 0:
            model = 'correlated'
        elif model == 'hybrid' and ps.bias_sigma == 0:
            model = 'kinematic'
        field_part = (ps.bias_sigma, ps.coherence_length) if model in (
            'correlated', 'hybrid') else None
        kin = ps.kinematic_scale if model in KINEMATIC_MODELS else None
        return (model, field_part, kin, ps.point_sigma if model != 'fixed' else None)

    def run(**kw):
        ps = replace(base, **kw)
        key = key_of(ps)
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
                      point_sigma=ps) for L in grid['coherence_length']])
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
    chosen = _occam_choice(ok, occam_margin)
    if holdout:
        for m in dict.fromkeys(c.settings.model for c in ok):
            b = best([c for c in ok if c.settings.model == m])
            b.holdout_px = holdout_reprojection(cameras, measured, obs, b.settings, quiet,
                                                kinematics, inliers, rng)
    reason = _reason(chosen, ok)
    if noise is not None and noise.success:
        reason += (f'; image noise {noise.pixel_sigma:.3g} px estimated from the free-network '
                   f'residuals ({noise.n_observations} observations, redundancy '
                   f'{noise.redundancy:.0f}) and used for every candidate')
    else:
        reason += f'; image noise {settings.pixel_sigma:.3g} px (as configured)'
    if chosen is not top:
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
                          settings.pixel_sigma, noise)


def _complexity(c):
    """Complexity of a candidate's prior: a hybrid with one part off is the simpler model."""
    s = c.settings
    if s.model == 'hybrid' and (s.kinematic_scale == 0 or s.bias_sigma == 0):
        return COMPLEXITY['kinematic']
    return COMPLEXITY.get(s.model, 9)


def _occam_choice(cands, margin):
    """Among ``cands`` within ``margin`` of the best evidence, the best of the simplest."""
    top = max(c.log_evidence for c in cands)
    near = [c for c in cands if c.log_evidence >= top - margin]
    simplest = min(_complexity(c) for c in near)
    # ties (a hybrid limit and the model it equals) go to the plain model: lower table rank
    return max((c for c in near if _complexity(c) == simplest),
               key=lambda c: (c.log_evidence, -COMPLEXITY.get(c.settings.model, 9)))


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
