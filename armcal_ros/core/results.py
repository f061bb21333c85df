"""
The calibration handed to users: each camera with its uncertainty and fit figures.

:func:`calibration_from_result` turns the solver's
:class:`~armcal_ros.core.calibration.CalibrationResult` into a :class:`Calibration`; the engine
decides whether it replaces the current one, the node publishes it and
:mod:`armcal_ros.io.results_files` writes and reads it.
"""

import time
from dataclasses import dataclass, field
from typing import Dict

import numpy as np

from armcal_ros.core.calibration import CalibrationResult
from armcal_ros.core.camera import Camera
from armcal_ros.core.uncertainty import pose_covariance, rms_error_mm, triangulation_covariance

POSE_PARAMETERS = ('wx', 'wy', 'wz', 'tx', 'ty', 'tz')


@dataclass
class CameraCalibration:
    """One camera's accepted calibration and its quality figures."""

    camera: Camera
    std: Dict[str, float]
    pose_covariance: np.ndarray          # 6x6 over (x, y, z, rx, ry, rz) of T_base_camera
    rms_px: float
    n_observations: int
    n_inliers: int
    #: Degrees of freedom left in the camera's residuals and the image noise they give (px per
    #: axis; NaN without redundancy) - :class:`~armcal_ros.core.adjustment.CameraEstimate`.
    redundancy: float = float('nan')
    sigma_px: float = float('nan')
    #: RMS 3-D error (mm, one sigma) that this camera's own parameter uncertainty puts into
    #: points triangulated over the workspace the samples covered
    #: (:func:`~armcal_ros.core.uncertainty.triangulation_covariance`); NaN where no other
    #: camera shares its view.
    workspace_error_mm: float = float('nan')


@dataclass
class Calibration:
    """A calibration the engine accepted: cameras, quality, and how it was obtained."""

    cameras: Dict[str, CameraCalibration]
    model: str
    cost: float
    n_samples: int
    solve_time_s: float
    solved_at: float                     # wall-clock seconds since the epoch
    status: str
    message: str
    hyperparameters: Dict[str, float] = field(default_factory=dict)
    #: Cameras the solve had but whose fit is no calibration, and why (a degenerate
    #: :class:`~armcal_ros.core.adjustment.CameraEstimate`): in :attr:`cameras` only with an
    #: earlier solve's calibration, kept.
    not_calibrated: Dict[str, str] = field(default_factory=dict)

    def summary(self):
        """Return a JSON-friendly dict (no numpy types)."""
        cams = {}
        for name, c in self.cameras.items():
            t, q = c.camera.pose_in_world()
            cams[name] = dict(
                width=c.camera.width, height=c.camera.height, fx=c.camera.fx, fy=c.camera.fy,
                cx=c.camera.cx, cy=c.camera.cy, dist=[float(v) for v in c.camera.dist],
                translation=[float(v) for v in t], rotation=[float(v) for v in q],
                std={k: float(v) for k, v in c.std.items()},
                pose_covariance=[float(v) for v in np.asarray(c.pose_covariance).ravel()],
                rms_px=float(c.rms_px), n_observations=int(c.n_observations),
                n_inliers=int(c.n_inliers), redundancy=_json_float(c.redundancy),
                sigma_px=_json_float(c.sigma_px),
                workspace_error_mm=_json_float(c.workspace_error_mm))
            if name in self.not_calibrated:
                # Kept from an earlier solve: this solve's fit of it was no calibration.
                cams[name]['last_fit_unusable'] = self.not_calibrated[name]
        return dict(model=self.model, cost=float(self.cost), n_samples=int(self.n_samples),
                    solve_time_s=float(self.solve_time_s), solved_at=float(self.solved_at),
                    status=self.status, message=self.message,
                    hyperparameters=dict(self.hyperparameters), cameras=cams,
                    not_calibrated=dict(self.not_calibrated))


def _json_float(x):
    """Return ``x`` as a float, None for NaN (JSON has no NaN)."""
    x = float(x)
    return None if not np.isfinite(x) else x


def calibration_from_result(result: CalibrationResult, n_samples, hyper=None,
                            hidden=()) -> Calibration:
    """
    Turn a solver result into a :class:`Calibration` (pose covariances included).

    A camera whose estimate is not 'ok' (a degenerate fit), or that the solve left out for
    keeping too few views, is left out, named with its reason in
    :attr:`Calibration.not_calibrated`, and out of the 3-D error figures.  The cameras
    named in ``hidden`` are left out silently: solved beside the others but not cameras of
    the cell now (a moved camera's earlier self).
    """
    adj = result.adjustment
    cams = {}
    names = adj.parameter_names
    hyper = dict(hyper or {})
    hidden = set(hidden)
    shown = {name: est for name, est in adj.cameras.items() if name not in hidden}
    good = {name: est for name, est in shown.items() if est.status == 'ok'}
    skipped = {name: est.message or est.status for name, est in shown.items()
               if name not in good}
    # A camera whose fixed fit kept too few views was left out of the solve (core.calibration).
    skipped.update({name: r.message for name, r in result.init.items()
                    if r.status == 'too_few_inliers' and name not in hidden})
    own, total = {}, float('nan')
    if adj.points is not None and len(adj.points) and good:
        cov, own, _ = triangulation_covariance([e.camera for e in good.values()], adj.covariance,
                                               names, adj.points)
        total = rms_error_mm(cov)
    hyper['triangulation_error_mm'] = _json_float(total)
    for name, est in good.items():
        idx = [names.index(f'{name}/{p}') for p in POSE_PARAMETERS]
        cov = adj.covariance[np.ix_(idx, idx)]
        cams[name] = CameraCalibration(est.camera.copy(), dict(est.std),
                                       pose_covariance(est.camera, cov), est.rms_px,
                                       est.n_observations, est.n_inliers, est.redundancy,
                                       est.sigma_px,
                                       rms_error_mm(own[name]) if name in own else float('nan'))
    return Calibration(cams, adj.model, adj.cost, n_samples, result.time_s, time.time(),
                       result.status, result.message, hyper, skipped)
