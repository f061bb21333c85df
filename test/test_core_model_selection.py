"""
Automatic model choice: the Laplace evidence picks the truth where the truth is known.

Its parts have their own tests: the image noise estimates in test_core_image_noise.py, the
held-out check in test_core_holdout.py.
"""
import numpy as np
import pytest

from armcal_ros.core.adjustment import Observations, SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.model_selection import (_local_lengths, _occam_choice, _search_scale,
                                             Candidate, DEFAULT_GRID, HYBRID_MAX_L_FRACTION,
                                             OCCAM_MARGIN, SCALE_BOUNDS, SCALE_EXTENSIONS,
                                             SCALE_REFINEMENTS, SCALE_TOLERANCE, select_model)
from armcal_ros.core.priors import PriorSettings
from armcal_ros.core.results import calibration_from_result
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


def test_a_camera_whose_fixed_fit_keeps_too_few_views_is_left_out_and_auto_solves_the_rest():
    """
    A camera that fits too few of its views after the ``fixed`` stage does not sink the rest.

    Here the third camera's 40 views are all of something else (uniform over the image) and
    its start is given (a warm start, as in a running engine), so it is not refused at
    initialisation; the fixed fit keeps 1-2 of them.  Its parameters are then unobservable:
    measured before the rule, the image noise came out at 0.54-0.64 px (0.3 true) and 3 of 4
    seeds ended unconverged, the good cameras with them.  Left out, the others calibrate at
    the true noise, and the result says which camera was left out and why.
    """
    prob = make_problem(40, 1, pixel_sigma=0.3)
    names = [c.name for c in prob.cameras]
    rng = np.random.default_rng(1)
    uv = prob.obs.uv.copy()
    bad = prob.obs.camera == 2
    uv[bad] = rng.uniform([0, 0], [640, 480], (int(bad.sum()), 2))
    obs = Observations(prob.obs.camera, prob.obs.point, uv)
    res = calibrate(prob.specs, prob.measured, obs, PriorSettings('auto'),
                    SolverSettings(pixel_sigma=0.3), initial={names[2]: prob.cameras[2]})
    assert res.success and res.status == 'partial', res.message
    assert sorted(res.cameras) == names[:2]
    assert f'camera {names[2]}: only' in res.message and 'left out' in res.message
    assert not res.init[names[2]].success
    # The engine's calibration names it as not calibrated, with the reason.
    cal = calibration_from_result(res, 40)
    assert sorted(cal.cameras) == names[:2] and 'left out' in cal.not_calibrated[names[2]]
    assert 0.2 < res.pixel_sigma < 0.4, res.pixel_sigma
    for cam in prob.cameras[:2]:
        est = res.cameras[cam.name]
        assert abs(est.fx / cam.fx - 1) < 0.03, (cam.name, est.fx, cam.fx)


def test_auto_with_no_candidate_adjusted_is_a_failed_result_not_an_exception(monkeypatch):
    """When every candidate fails (the evidence undefined), calibrate says so and returns."""
    import armcal_ros.core.calibration as calibration

    def nothing(*args, **kwargs):
        raise ValueError('no candidate model could be adjusted: singular')
    monkeypatch.setattr(calibration, 'select_model', nothing)
    prob = make_problem(30, 0, pixel_sigma=0.3)
    res = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('auto'),
                    SolverSettings(pixel_sigma=0.3))
    assert not res.success and res.status == 'failed' and res.adjustment is None
    assert 'no candidate model could be adjusted' in res.message
