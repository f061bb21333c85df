"""Automatic model choice: the Laplace evidence picks the truth where the truth is known."""
from dataclasses import replace

import numpy as np
import pytest

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.kinematic_prior import KinematicData
from armcal_ros.core.holdout import HeldOut, HOLDOUT_FOLDS, HOLDOUT_Z
from armcal_ros.core.image_noise import estimate_pixel_sigma, pooled_pixel_sigma
from armcal_ros.core.model_selection import (_local_lengths, _occam_choice, _search_scale,
                                             Candidate, DEFAULT_GRID, HYBRID_MAX_L_FRACTION,
                                             OCCAM_MARGIN, SCALE_BOUNDS, SCALE_EXTENSIONS,
                                             SCALE_REFINEMENTS, SCALE_TOLERANCE, select_model)
from armcal_ros.core.priors import PriorSettings
from armcal_ros.sim.robot_points import make_robot_problem
from armcal_ros.sim.synthetic import make_problem


def _fixed(prob, s):
    fx = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)
    return fx.adjustment.camera_list(), fx.adjustment.inliers


@pytest.mark.parametrize('true_length', [0.15, 0.3])
def test_evidence_picks_the_true_coherence_length_on_gp_prior_data(true_length):
    prob = make_problem(300, 2, bias_sigma=1e-3, coherence_length=true_length, pixel_sigma=0.3)
    s = SolverSettings(pixel_sigma=0.3)
    cams, inl = _fixed(prob, s)
    sel = select_model(cams, prob.measured, prob.obs, PriorSettings(bias_sigma=1e-3), s,
                       inliers=inl, models=['correlated'], holdout=False,
                       grid={'coherence_length': (0.075, 0.15, 0.3, 0.6),
                             'bias_sigma': (1e-3,)})
    assert sel.settings.model == 'correlated'
    assert sel.settings.coherence_length == true_length, sel.reason
    assert 'Laplace evidence' in sel.reason


@pytest.mark.slow
def test_auto_chooses_a_kinematic_model_for_linkage_errors_and_says_why():
    prob = make_robot_problem('geometric', 300, 1, n_test=20)
    s = SolverSettings(pixel_sigma=0.3)
    res = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('auto'), s,
                    kinematics=prob.kinematics)
    assert res.success, res.message
    sel = res.selection
    assert sel.settings.model in ('kinematic', 'hybrid')
    assert res.stages[-1][0] == f'auto:{sel.settings.model}'
    assert sel.settings.model in res.message and 'held-out' in res.message
    held = {c.settings.model: c.holdout_px for c in sel.candidates
            if np.isfinite(c.holdout_px)}
    # the held-out check agrees: the kinematic family predicts unseen points better than fixed
    assert held[sel.settings.model] < held['fixed']


def test_auto_without_joint_angles_considers_only_point_models():
    prob = make_problem(120, 4, bias_sigma=1e-3, coherence_length=0.3, pixel_sigma=0.3)
    s = SolverSettings(pixel_sigma=0.3)
    cams, inl = _fixed(prob, s)
    sel = select_model(cams, prob.measured, prob.obs, PriorSettings(), s, inliers=inl,
                       holdout=False, grid={'coherence_length': (0.3,),
                                            'bias_sigma': (1e-3,)})
    models = {c.settings.model for c in sel.candidates}
    assert models == {'fixed', 'independent', 'correlated'}
    assert sel.settings.model == 'correlated'


@pytest.mark.parametrize('true_sigma', [0.05, 0.3, 1.0])
def test_free_network_estimate_recovers_the_image_noise_under_a_bias(true_sigma):
    # 1 mm of correlated bias is ~0.5 px here: far above the smaller noise levels, so the
    # estimate must come from the images, not from the fit of the robot's points.
    prob = make_problem(300, 3, bias_sigma=1e-3, coherence_length=0.3, pixel_sigma=true_sigma)
    s = SolverSettings(pixel_sigma=0.5)
    cams, inl = _fixed(prob, s)
    est = estimate_pixel_sigma(cams, prob.measured, prob.obs, s, inliers=inl)
    assert est.success
    assert est.pixel_sigma == pytest.approx(true_sigma, rel=0.15)
    assert 0 < est.redundancy < 2 * est.n_observations


def test_auto_uses_the_estimated_image_noise_not_the_configured_one():
    prob = make_problem(150, 5, bias_sigma=1e-3, coherence_length=0.3, pixel_sigma=0.1)
    s = SolverSettings(pixel_sigma=2.0)
    cams, inl = _fixed(prob, s)
    sel = select_model(cams, prob.measured, prob.obs, PriorSettings(), s, inliers=inl,
                       holdout=False, grid={'coherence_length': (0.3,), 'bias_sigma': (1e-3,)})
    assert sel.pixel_sigma == pytest.approx(0.1, rel=0.2)
    assert 'image noise' in sel.reason and 'free-network' in sel.reason
    assert sel.settings.model == 'correlated', sel.reason
    kept = select_model(cams, prob.measured, prob.obs, PriorSettings(), s, inliers=inl,
                        holdout=False, estimate_noise=False,
                        grid={'coherence_length': (0.3,), 'bias_sigma': (1e-3,)})
    assert kept.pixel_sigma == 2.0 and kept.noise is None


def test_pooled_scatter_recovers_the_noise_of_pooled_observations():
    rng = np.random.default_rng(3)
    sigma = 0.04
    n = rng.integers(2, 20, 400)
    spread = []
    for k in n:
        uv = rng.normal(0.0, sigma, (k, 2))
        spread.append(np.sqrt(np.mean(np.sum((uv - uv.mean(axis=0)) ** 2, axis=1))))
    expected = np.sqrt(np.mean(sigma ** 2 / n))
    assert pooled_pixel_sigma(spread, n) == pytest.approx(expected, rel=0.05)
    assert np.isnan(pooled_pixel_sigma([0.1, 0.2], [1, 1]))    # single frames: no scatter
    with pytest.raises(ValueError, match='spread_px and n_frames'):
        pooled_pixel_sigma([0.1, 0.2], [3])


def test_one_camera_auto_takes_the_pooled_scatter_where_the_free_network_cannot():
    prob = make_problem(150, 2, n_cameras=1, bias_sigma=1e-3, pixel_sigma=0.1)
    s = SolverSettings(pixel_sigma=2.0)
    cams, inl = _fixed(prob, s)
    grid = {'coherence_length': (0.3,), 'bias_sigma': (1e-3,)}
    alone = select_model(cams, prob.measured, prob.obs, PriorSettings(), s, inliers=inl,
                         holdout=False, grid=grid)
    assert not alone.noise.success and alone.pixel_sigma == 2.0      # no redundancy
    assert alone.settings.model == 'fixed', alone.reason       # images drowned in 2 px
    assert 'as configured' in alone.reason
    sel = select_model(cams, prob.measured, prob.obs, PriorSettings(), s, inliers=inl,
                       holdout=False, grid=grid, pooled_sigma_px=0.1)
    assert sel.pixel_sigma == 0.1 and 'scatter of the pooled detections' in sel.reason
    # with the images weighted by their real noise the field becomes visible to the evidence
    assert sel.settings.model == 'correlated', sel.reason


def _fake(evidence):
    """Return a Candidate factory for the 1-D search: log evidence as a function of scale."""
    calls = []

    def evaluate(k, ps):
        calls.append(k)
        return Candidate(PriorSettings('kinematic', kinematic_scale=k, point_sigma=ps),
                         evidence(k), 0.0, True)
    return evaluate, calls


@pytest.mark.parametrize('true_scale', [0.7, 1.3, 5.0, 0.2])
def test_scale_search_brackets_and_refines_the_evidence_maximum(true_scale):
    evaluate, calls = _fake(lambda k: -40.0 * (np.log(k) - np.log(true_scale)) ** 2)
    best = _search_scale(evaluate, (0.5, 1.0, 2.0), 1e-5)
    assert best.settings.point_sigma == 1e-5
    # a parabola in log scale: found to within the search tolerance
    assert abs(np.log(best.settings.kinematic_scale / true_scale)) < np.log1p(SCALE_TOLERANCE)
    assert len(calls) <= 3 + SCALE_EXTENSIONS + SCALE_REFINEMENTS


def test_scale_search_stays_within_its_bounds():
    evaluate, calls = _fake(lambda k: -40.0 * (np.log(k) - np.log(50.0)) ** 2)
    best = _search_scale(evaluate, (0.5, 1.0, 2.0), 1e-5)
    assert best.settings.kinematic_scale == SCALE_BOUNDS[1]
    assert max(calls) <= SCALE_BOUNDS[1]


def test_scale_search_survives_failed_candidates():
    evaluate, calls = _fake(lambda k: -np.inf if k > 1.5 else -(k - 1.0) ** 2)
    best = _search_scale(evaluate, (0.5, 1.0, 2.0), 1e-5)
    assert 0.5 <= best.settings.kinematic_scale <= 1.5


@pytest.mark.slow
def test_hybrid_search_contains_both_limits_and_kinematic_point_sigma_is_searched():
    prob = make_robot_problem('geometric', 300, 2, n_test=20)
    s = SolverSettings(pixel_sigma=0.3)
    cams, inl = _fixed(prob, s)
    sel = select_model(cams, prob.measured, prob.obs, PriorSettings(), s, prob.kinematics, inl,
                       holdout=False, grid={'coherence_length': (0.3,), 'bias_sigma': (1e-3,),
                                            'hybrid_bias_sigma': (0.3e-3,)})
    kin, corr, hyb = (sel.best_of(m) for m in ('kinematic', 'correlated', 'hybrid'))
    # the limits are candidates, so hybrid's evidence is never below either simpler model
    assert hyb.log_evidence >= max(kin.log_evidence, corr.log_evidence)
    limits = [c for c in sel.candidates if c.settings.model == 'hybrid' and
              c.settings.bias_sigma == 0]
    assert limits and limits[0].log_evidence == kin.log_evidence
    # s_n is searched over its grid at the best scale; with pure linkage errors (nothing
    # left for s_n) a small one is never clearly worse than the 0.2 mm default
    at_best = {c.settings.point_sigma: c.log_evidence for c in sel.candidates
               if c.settings.model == 'kinematic' and
               c.settings.kinematic_scale == kin.settings.kinematic_scale}
    assert set(DEFAULT_GRID['kinematic_point_sigma']) <= set(at_best)
    assert at_best[min(at_best)] > at_best[0.2e-3] - 1.0
    scales = {c.settings.kinematic_scale for c in sel.candidates
              if c.settings.model == 'kinematic'}
    assert len(scales) > 3                  # refined beyond the grid
    choice = sel.choice_of('hybrid')
    assert choice.settings.bias_sigma == 0 or choice.settings.kinematic_scale == 0 or \
        choice.log_evidence > max(kin.log_evidence, corr.log_evidence) + OCCAM_MARGIN
    assert sel.settings.model in ('kinematic', 'hybrid')


@pytest.mark.parametrize('radius', [0.1, 0.3, 0.5])
def test_hybrid_field_lengths_are_local_to_the_sampled_workspace(radius):
    # The six points +-radius along each axis: RMS radius about their centroid exactly radius.
    P = np.array([0.4, -0.2, 0.9]) + radius * np.vstack([np.eye(3), -np.eye(3)])
    lengths = (0.05, 0.15, 0.3, 0.6, 1.2)
    cap = HYBRID_MAX_L_FRACTION * radius
    assert _local_lengths(lengths, P) == [L for L in lengths if L <= cap]
    # a workspace smaller than every length still gets the shortest one
    assert _local_lengths((10.0, 20.0), P) == [10.0]


def _heldout_case(kinematics_of):
    """Geometric data, and the held-out check with the kinematic data ``kinematics_of`` gives."""
    prob = make_robot_problem('geometric', 300, 0, n_test=20)
    s = SolverSettings(pixel_sigma=0.3)
    cams, inl = _fixed(prob, s)
    quick = replace(s, max_gate_rounds=0, max_iterations=30, ftol=1e-6)
    check = HeldOut(cams, prob.measured, prob.obs, quick, kinematics_of(prob.kinematics), inl,
                    np.random.default_rng(0))
    simple = Candidate(PriorSettings('independent'), 0.0, 0.0, True)
    # the evidence is set to win by far more than the margin: only the held-out check decides
    complex_ = Candidate(PriorSettings('kinematic'), 10.0 * OCCAM_MARGIN, 0.0, True)
    assert _occam_choice([simple, complex_], OCCAM_MARGIN) is complex_
    return check, simple, complex_


def test_heldout_check_keeps_the_simpler_model_when_the_complex_one_predicts_worse():
    # Joint angles that do not belong to the points (each sample paired with its neighbour's
    # joint state): the kinematic model fits the training points through a wrong Jacobian
    # and predicts unseen points worse than no correction at all.
    def misaligned(k):
        return KinematicData(np.roll(k.jacobian, 1, axis=0), k.names, k.sigma)
    check, simple, complex_ = _heldout_case(misaligned)
    excess, se, rms_c, rms_s = check.compare(complex_, simple)
    assert excess > HOLDOUT_Z * se and rms_c > rms_s
    assert _occam_choice([simple, complex_], OCCAM_MARGIN, check) is simple
    assert 'held-out' in complex_.holdout_note and check.log[-1]['rejected']
    # every observation was predicted once, from the fit of the folds that do not hold it
    assert np.all(np.isfinite(check.all_folds(simple)[check.active]))
    assert check.folds == HOLDOUT_FOLDS


def test_heldout_check_lets_the_right_complex_model_win():
    check, simple, complex_ = _heldout_case(lambda k: k)
    excess, se, rms_c, rms_s = check.compare(complex_, simple)
    assert excess < -HOLDOUT_Z * se and rms_c < rms_s     # clearly better, not just tolerated
    assert _occam_choice([simple, complex_], OCCAM_MARGIN, check) is complex_
    assert complex_.holdout_note == '' and not check.log[-1]['rejected']


class _Rejecting:
    """Stub check: rejects the named models, records what it was asked."""

    def __init__(self, *models):
        self.models, self.asked = models, []

    def rejects(self, c, s):
        self.asked.append((c.settings.model, s.settings.model))
        return c.settings.model in self.models


def test_occam_rule_walks_down_the_complexity_ladder_when_the_check_rejects():
    fixed = Candidate(PriorSettings('fixed'), -100.0, 0.0, True)
    kin = Candidate(PriorSettings('kinematic'), 0.0, 0.0, True)
    hyb = Candidate(PriorSettings('hybrid', bias_sigma=0.3e-3), 10.0, 0.0, True)
    cands = [fixed, kin, hyb]
    assert _occam_choice(cands, OCCAM_MARGIN, _Rejecting()) is hyb
    stub = _Rejecting('hybrid')
    # hybrid is compared with the evidence choice among the simpler ones, then kinematic, the
    # fallback, with the candidates simpler than itself
    assert _occam_choice(cands, OCCAM_MARGIN, stub) is kin
    assert stub.asked == [('hybrid', 'kinematic'), ('kinematic', 'fixed')]
    assert _occam_choice(cands, OCCAM_MARGIN, _Rejecting('hybrid', 'kinematic')) is fixed
