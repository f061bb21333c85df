"""
The held-out check of auto: a complex model must not predict unseen observations worse.

Geometric linkage errors of :mod:`armcal_ros.sim.robot_points`; the check (:class:`HeldOut`) is
asked through the Occam rule of :mod:`armcal_ros.core.model_selection`.
"""
from dataclasses import replace

import numpy as np

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.calibration import calibrate
from armcal_ros.core.holdout import HeldOut, HOLDOUT_FOLDS, HOLDOUT_Z
from armcal_ros.core.kinematic_prior import KinematicData
from armcal_ros.core.model_selection import _occam_choice, Candidate, OCCAM_MARGIN
from armcal_ros.core.priors import PriorSettings
from armcal_ros.sim.robot_points import make_robot_problem


def _fixed(prob, s):
    fx = calibrate(prob.specs, prob.measured, prob.obs, PriorSettings('fixed'), s)
    return fx.adjustment.camera_list(), fx.adjustment.inliers


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
