"""
Held-out reprojection: how well a fitted model predicts where the arm really is.

The points are split once into ``HOLDOUT_FOLDS`` folds (the same split for every candidate, so
the comparisons are paired); for a fold, the model is fitted on the other points, the fold's
points are predicted from the robot's measurement (X^ plus the model's predicted correction:
J_p dp, the field's posterior mean) and projected with the fitted cameras.

Two candidates c (the more complex) and s are compared on the same folds.  With e_k the squared
pixel error of held-out observation k, d_i = sum over the observations of point i of
(e_k(c) - e_k(s)), and M observations in all, c's excess is D = sum_i d_i / M with standard
error sqrt(n) std(d_i) / M (the observations of one point share its prediction error, so the
point is the sampling unit).  c is rejected when D > ``HOLDOUT_Z`` standard errors: one
standard error, as in the one-standard-error rule of cross-validation.
"""

import numpy as np

from armcal_ros.core.adjustment import adjust, Observations
from armcal_ros.core.priors import canonical_settings, KINEMATIC_MODELS, prior_key

#: Folds of the held-out check (each point is held out once; the report uses the first fold).
HOLDOUT_FOLDS = 5
#: Folds the Occam check compares on (the first ones; the report always uses the first).
HOLDOUT_CHECK_FOLDS = 5
#: A more complex candidate is rejected when its held-out squared error exceeds the simpler
#: one's by more than this many standard errors of the paired difference (module doc).
HOLDOUT_Z = 1.0


class HeldOut:
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
        ps = canonical_settings(cand.settings)
        key = (prior_key(ps), f)
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
                     points_init=p0, globals_init=g0, redundancy=False)
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
        pair = (prior_key(canonical_settings(c.settings)),
                prior_key(canonical_settings(s.settings)))
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
