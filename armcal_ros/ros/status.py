"""
What the node reports, computed without ROS: diagnostics content and the geometry of markers.

:func:`diagnostic_statuses` turns the engine's state and the front end's counters into plain
:class:`Status` records (level, name, message, key/values); ``conversions`` turns them into a
``diagnostic_msgs/DiagnosticArray``.  :func:`frustum_segments` and :func:`bias_vectors` give the
line segments drawn in RViz.
"""

import datetime
from dataclasses import dataclass, field
from typing import Dict, List, Optional

import numpy as np

from armcal_ros.change_tracking import of_earlier_self
from armcal_ros.core.camera import Camera
from armcal_ros.frontend.collector import why_few_samples

OK, WARN, ERROR = 0, 1, 2


@dataclass
class Status:
    """One diagnostic status: ``level`` is OK, WARN or ERROR (diagnostic_msgs values)."""

    level: int
    name: str
    message: str
    hardware_id: str = ''
    values: Dict[str, str] = field(default_factory=dict)


def _fmt(v):
    if isinstance(v, float):
        return f'{v:.6g}'
    return str(v)


def _iso(t):
    if t is None or not np.isfinite(t):
        return ''
    return datetime.datetime.fromtimestamp(t, datetime.timezone.utc).isoformat(
        timespec='seconds')


@dataclass
class NodeState:
    """A snapshot of what the diagnostics report (filled by the node, read by this module)."""

    camera_names: List[str]
    n_samples: int
    min_samples: int
    samples_per_camera: Dict[str, int]
    image_sizes: Dict[str, tuple]
    solving: bool
    n_solves: int
    n_rejected: int
    calibration: Optional[object] = None          # engine.Calibration
    last_outcome: Optional[object] = None         # engine.SolveOutcome
    last_outcome_wall: Optional[float] = None     # wall-clock time the last solve ended
    input_counts: Dict[str, int] = field(default_factory=dict)
    queue_dropped: Dict[str, int] = field(default_factory=dict)
    queue_depth: Dict[str, int] = field(default_factory=dict)
    restored: str = ''
    #: Change detection: the engine's records (change_tracking.ChangeRecord), the cameras
    #: withheld until recalibrated, the first stamp (ns) the times are counted from, and the
    #: views a changed camera needs.
    changes: List[object] = field(default_factory=list)
    withheld: List[str] = field(default_factory=list)
    start_ns: int = 0
    recalibration_samples: int = 20
    #: Calibrations published so far (a consumer waiting for a new one compares it), and the
    #: optical frame each camera's outputs name.
    n_published: int = 0
    frame_ids: Dict[str, str] = field(default_factory=dict)
    #: Robot-model joints the joint states lacked, and the names such a message carried.
    missing_joints: tuple = ()
    seen_joint_names: tuple = ()
    #: Camera -> how the light's shift was pooled at the last solve (``shaded_pooled``).
    light_pooling: Dict[str, str] = field(default_factory=dict)
    #: Where solves run ('in the node', or the child's pid), and how many children were
    #: started (more than one: a child died and was replaced).
    solver: str = ''
    solver_starts: int = 0
    #: Camera -> its stamp latency timed from the frames in motion
    #: (stamp_latency.latency_report: latency_ms, std_ms, frames, status, message, applied_ms).
    stamp_latency: Dict[str, dict] = field(default_factory=dict)


def diagnostic_statuses(s: NodeState, node_name='armcal') -> List[Status]:
    """
    One status for the calibrator and one per camera.

    The calibrator's level is OK once a calibration is published and the last solve was
    accepted, WARN while collecting, after a rejected solve or when inputs were dropped, and
    ERROR when a solve failed with no calibration to fall back on.
    """
    cal = s.calibration
    out = s.last_outcome
    if cal is None and s.solving:
        state = 'solving'
    elif cal is None and s.n_samples < s.min_samples:
        state = f'collecting samples ({s.n_samples} of {s.min_samples})'
        why = why_few_samples(s.input_counts, s.missing_joints, s.seen_joint_names)
        if why:
            state += f': {why}'
    elif cal is None:
        state = 'waiting for the first solve'
    else:
        state = 'calibrated'
    level = OK if cal is not None else WARN
    message = state
    if out is not None and not out.accepted:
        level = max(level, WARN if cal is not None else ERROR)
        message = f'{state}; last solve not accepted: {out.reason}'
    elif cal is not None:
        message = (f'{state}: {cal.model} model, {cal.n_samples} samples, solved '
                   f'{_iso(cal.solved_at)}' + ('; solving again' if s.solving else ''))
    dropped = sum(s.queue_dropped.values())
    if dropped:
        level = max(level, WARN)
        message += f'; {dropped} inputs dropped (front end too slow)'
    values = dict(state=state, samples=s.n_samples, min_samples=s.min_samples,
                  solving=s.solving, solves=s.n_solves, solves_rejected=s.n_rejected,
                  published=s.n_published)
    if s.solver:
        values.update(solver=s.solver, solver_process_starts=s.solver_starts)
    for name in s.camera_names:
        values[f'samples_{name}'] = s.samples_per_camera.get(name, 0)
    if out is not None:
        values.update(last_solve_time=_iso(s.last_outcome_wall),
                      last_solve_duration_s=float(out.time_s),
                      last_solve_accepted=bool(out.accepted), last_solve_result=out.reason,
                      last_solve_samples=int(out.n_samples))
        adj = out.result.adjustment if out.result is not None else None
        if adj is not None:
            values['last_solve_cost'] = float(adj.cost)
            values['last_solve_iterations'] = int(adj.iterations)
    if cal is not None:
        values.update(calibration_model=cal.model, calibration_cost=float(cal.cost),
                      calibration_time=_iso(cal.solved_at))
    for kind in sorted(set(s.queue_dropped) | set(s.queue_depth)):
        values[f'queue_dropped_{kind}'] = s.queue_dropped.get(kind, 0)
        values[f'queue_depth_{kind}'] = s.queue_depth.get(kind, 0)
    for key in sorted(s.input_counts):
        values[f'input_{key}'] = s.input_counts[key]
    if s.restored:
        values['restored'] = s.restored
    real = [r for r in s.changes if r.kind != 'disagreement']
    values['changes'] = len(real)
    values['disagreements'] = len(s.changes) - len(real)
    if s.changes:
        last = s.changes[-1]
        values['last_change'] = last.summary(s.start_ns)
        if last.kind in ('arm', 'unexplained', 'disagreement') and last.status == 'reported':
            level = max(level, WARN)
            message += f'; {last.summary(s.start_ns)}'
    if s.withheld:
        level = max(level, WARN)
        message += f'; withheld until recalibrated: {", ".join(s.withheld)}'
    statuses = [Status(level, f'{node_name}: calibration', message, node_name,
                       {k: _fmt(v) for k, v in values.items()})]
    for name in s.camera_names:
        statuses.append(camera_status(name, s, node_name))
    return statuses


def camera_status(name, s: NodeState, node_name='armcal') -> Status:
    """One camera's status: its calibration, quality and standard deviations."""
    values = dict(samples=s.samples_per_camera.get(name, 0))
    size = s.image_sizes.get(name)
    values['image_size'] = f'{size[0]}x{size[1]}' if size else 'no image yet'
    values['frame_id'] = s.frame_ids.get(name) or f'{name}_optical_frame'
    if name in s.light_pooling:
        values['light_pooling'] = s.light_pooling[name]
    lat = s.stamp_latency.get(name)
    if lat:
        values['stamp_latency'] = lat['message'] if lat['status'] != 'ok' else (
            f'{lat["latency_ms"]:.1f} +- {lat["std_ms"]:.2f} ms from {lat["frames"]} frames in '
            f'motion (image_stamp_latency {lat.get("applied_ms") or 0.0:.1f} ms)')
        if lat['status'] == 'ok':
            values['stamp_latency_ms'] = lat['latency_ms']
    c = s.calibration.cameras.get(name) if s.calibration is not None else None
    mine = [r for r in s.changes if r.camera == name and r.kind == 'camera']
    if mine:
        values['last_change'] = mine[-1].summary(s.start_ns)
        values['changes'] = len(mine)
    earlier = s.calibration.hyperparameters.get('earlier_epochs') if s.calibration else None
    for who, said in sorted((earlier or {}).items()):
        camera, epoch = of_earlier_self(who) or ('', 0)
        if camera == name:
            values[f'views_before_change_{epoch}'] = f'{who}: {said}'
    if name in s.withheld:
        said = (mine[-1].summary(s.start_ns, s.recalibration_samples) if mine
                else f'{name} changed')
        return Status(WARN, f'{node_name}: {name}', said + '; its calibration is withheld',
                      name, {k: _fmt(v) for k, v in values.items()})
    why = s.calibration.not_calibrated.get(name) if s.calibration is not None else None
    if why:
        values['last_fit_unusable'] = why
    if c is None:
        return Status(WARN, f'{node_name}: {name}', 'not calibrated yet' +
                      (f': its fit is not a calibration ({why})' if why else ''), name,
                      {k: _fmt(v) for k, v in values.items()})
    cam = c.camera
    values.update(fx=cam.fx, fy=cam.fy, cx=cam.cx, cy=cam.cy,
                  rms_px=float(c.rms_px), observations=int(c.n_observations),
                  inliers=int(c.n_inliers), image_noise_px=float(c.sigma_px),
                  workspace_error_mm=float(c.workspace_error_mm))
    for i, k in enumerate(('k1', 'k2', 'p1', 'p2', 'k3')):
        values[k] = float(cam.dist[i])
    for k, v in sorted(c.std.items()):
        values[f'std_{k}'] = float(v)
    return Status(WARN if why else OK, f'{node_name}: {name}',
                  f'reprojection RMS {c.rms_px:.3f} px over {c.n_inliers} of '
                  f'{c.n_observations} observations'
                  + (f'; expected 3-D error it adds over the workspace '
                     f'{c.workspace_error_mm:.2f} mm' if np.isfinite(c.workspace_error_mm)
                     else '')
                  + (f'; the previous calibration kept: the last solve\'s fit is not one '
                     f'({why})' if why else ''), name,
                  {k: _fmt(v) for k, v in values.items()})


def frustum_segments(cam: Camera, depth=0.15):
    """
    Line segments (M, 2, 3) in the base frame drawing ``cam``'s field of view to ``depth`` m.

    The apex is the optical centre; the far rectangle is the image border back-projected
    (without distortion) to z = depth in the optical frame.
    """
    if not depth > 0:
        raise ValueError(f'depth must be > 0 (m), got {depth}')
    w, h = float(cam.width), float(cam.height)
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], float)
    rays = np.column_stack([(corners[:, 0] - cam.cx) / cam.fx,
                            (corners[:, 1] - cam.cy) / cam.fy, np.ones(4)]) * depth
    to_base = cam.rotation.T
    far = (rays - cam.translation) @ to_base.T
    apex = cam.center
    segs = [(apex, p) for p in far] + [(far[i], far[(i + 1) % 4]) for i in range(4)]
    return np.array(segs, float)


def bias_vectors(nominal, estimated, max_match=0.0025):
    """
    Pair each estimated point with the nominal point it came from: (K, 2, 3) segments.

    The solver returns estimated points X_i for a snapshot of the store; the store may have
    changed since, so they are matched to the current nominal points by nearest neighbour.  That
    is unambiguous because samples are at least ``min_sample_spacing`` (5 mm by default) apart
    while the bias is about a millimetre; a pair further apart than ``max_match`` is left out.
    """
    nominal = np.asarray(nominal, float).reshape(-1, 3)
    estimated = np.asarray(estimated, float).reshape(-1, 3)
    if len(nominal) == 0 or len(estimated) == 0:
        return np.zeros((0, 2, 3))
    from scipy.spatial import cKDTree
    d, i = cKDTree(nominal).query(estimated)
    keep = d <= max_match
    return np.stack([nominal[i[keep]], estimated[keep]], axis=1)
