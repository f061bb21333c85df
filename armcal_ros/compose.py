"""
The composition root: from typed :class:`~armcal_ros.settings.Settings` to a working pipeline.

The node and the offline CLI both call :func:`build_pipeline`; nothing else wires the parts.
It reads the robot model, makes the target (a point marker or a ChArUco board), one detector
per camera, the :class:`~armcal_ros.frontend.collector.SampleCollector` (front end) and the
:class:`~armcal_ros.engine.CalibrationEngine` with its sample store.  A configuration that
cannot be built raises ValueError naming the parameters.
"""

from dataclasses import dataclass, replace
from typing import Callable, Optional, Tuple

import numpy as np

from armcal_ros.core.change import ChangeSettings
from armcal_ros.core.kinematic_prior import KinematicData, kinematic_sigmas
from armcal_ros.core.priors import KINEMATIC_MODELS
from armcal_ros.core.target import optional_pose
from armcal_ros.engine import CalibrationEngine, EngineSettings
from armcal_ros.frontend.collector import SampleCollector
from armcal_ros.frontend.detectors import (CharucoBoard, CharucoDetector, make_detector,
                                           tag_corner_points)
from armcal_ros.frontend.samples import BoardTarget
from armcal_ros.frontend.store import SampleStore
from armcal_ros.robot.kinematics import KinematicChain
from armcal_ros.settings import Settings
from armcal_ros.stamp_latency import LatencyTimer

#: Two samples closer than this (m) are the same place (merged), whatever min_sample_spacing.
SAME_POINT_TOLERANCE = 0.0005
#: Prior standard deviation (m, per axis) of a point marker's place about its guess when a
#: kinematic model estimates it: a guess read off a drawing or a ruler is good to centimetres,
#: so a decimetre leaves the place to the data (the tip translation enters the marker's
#: position linearly, so a wide prior costs no linearisation error).
PLACE_GUESS_SIGMA = 0.1


@dataclass
class Pipeline:
    """What :func:`build_pipeline` wires: the robot chain, the front end and the engine."""

    chain: Optional[KinematicChain]        # None with pose input
    board: Optional[CharucoBoard]          # None for a point marker
    collector: SampleCollector
    engine: CalibrationEngine
    #: Times each camera's stamps from the frames in motion (None where it does not apply:
    #: :func:`latency_detectors`).
    latency: Optional[LatencyTimer] = None


def build_chain(settings: Settings, pose_input=None) -> Optional[KinematicChain]:
    """
    Return the robot's kinematic chain, or None with pose input (no robot model needed).

    ``pose_input`` None follows the settings (``pose_topic`` set); True when the source itself
    gives the link's poses (a robot_cal_tools folder).
    """
    if settings.inputs.pose_input if pose_input is None else pose_input:
        return None
    robot = settings.robot
    try:
        return KinematicChain.from_urdf(robot.urdf_text(), robot.base_frame, robot.marker_link)
    except ValueError as exc:
        raise ValueError(f'robot model (parameters robot_description/robot_description_file, '
                         f'base_frame, marker_link): {exc}') from exc


def build_board(settings: Settings, data_set_target=None,
                data_set_guess=None) -> Tuple[Optional[CharucoBoard], Optional[BoardTarget]]:
    """
    Return (CharucoBoard, BoardTarget) for a charuco target, else (None, None).

    A tag of given ``aruco_size`` is a four-corner target (None, BoardTarget) on the link at
    ``target_pose_guess`` (found by hand-eye when empty and estimated).  A point marker
    (sphere, tag centre) with ``estimate_marker_offset`` is a one-point target (None,
    BoardTarget) seeded at ``marker_offset``: the board path estimates its place - except
    under a kinematic model, whose marker-mount errors estimate the place on the point path
    (:func:`build_engine`), so it stays a point marker (None, None).

    ``data_set_target`` (rows, cols, square_size, marker_size, dictionary) completes the
    ``charuco_*`` parameters from a data set's own description; ``data_set_guess`` (4, 4) seeds
    the mount when ``target_pose_guess`` is empty.
    """
    target = settings.target
    if target.tag_corners:
        guess = optional_pose(target.pose_guess or None)
        return None, BoardTarget(tag_corner_points(target.aruco_size), guess,
                                 target.estimate_mount, target.estimate_size)
    if not target.is_board:
        if not target.estimate_mount or settings.prior.model in KINEMATIC_MODELS:
            return None, None
        # A point marker whose place on the link is estimated: a one-point rigid target,
        # seeded at marker_offset (its orientation is not observable and stays as given).
        seed = np.eye(4)
        seed[:3, 3] = settings.robot.marker_offset
        return None, BoardTarget(np.zeros((1, 3)), seed, True)
    b = target.board.completed(data_set_target)
    board = CharucoBoard(b.rows, b.cols, b.square_size, b.marker_size, b.dictionary, b.legacy)
    guess = optional_pose(target.pose_guess or None)
    if guess is None:
        guess = data_set_guess
    return board, BoardTarget(board.points(), guess, target.estimate_mount)


def build_detectors(settings: Settings, camera_names, board: Optional[CharucoBoard] = None):
    """One detector per camera (each tracks its own marker position)."""
    det, kind = settings.detector, settings.target.marker_type
    out = {}
    for name in camera_names:
        if kind == 'charuco':
            out[name] = CharucoDetector(board)
        elif kind == 'sphere':
            out[name] = make_detector('sphere', min_radius_px=det.sphere_min_radius_px,
                                      max_radius_px=det.sphere_max_radius_px,
                                      static_scene=det.sphere_static_scene,
                                      centre=('centroid' if det.sphere_centre == 'centroid'
                                              else 'shaded'))
        else:
            out[name] = make_detector('aruco', dictionary=det.aruco_dictionary,
                                      marker_id=det.aruco_id, corners=settings.target.tag_corners)
    return out


def latency_detectors(settings: Settings, camera_names, chain):
    """
    Return {camera: Detector} of the marker's point for timing the stamps, or None.

    None where stamp latency is not measured: no robot model (pose input), cameras on the arm,
    a board.  A ball blurred by motion is not the shaded-ball model, but its intensity centroid
    is where it was at mid-exposure; a tag is timed by its centre.
    """
    t = settings.target
    if chain is None or t.eye_in_hand or t.marker_type not in ('sphere', 'aruco'):
        return None
    point_only = replace(settings, detector=replace(settings.detector, sphere_centre='centroid'),
                         target=replace(t, aruco_size=0.0))
    return build_detectors(point_only, list(camera_names))


#: Shaded-ball fits per camera and dwell when the light shift is pooled (``shaded_pooled``).
#: The solve takes each view's centroid (all its frames) plus the camera's light shift pooled
#: over all its views, so a view's own shift only enters that pool, where its noise is
#: averaged with hundreds of others; three fits give the scatter and a median to drop a bad
#: one (two are the least the pooling takes).  Fitting every frame cost the live node three
#: times its CPU (docs/BENCHMARKS.md *node*).
FITS_PER_VIEW_POOLED = 3


def fits_per_view(settings: Settings) -> int:
    """Return the front end's cap on centre fits per camera and dwell (0: fit every frame)."""
    if settings.target.marker_type == 'sphere' and \
            settings.detector.sphere_centre == 'shaded_pooled':
        return FITS_PER_VIEW_POOLED
    return 0


def min_frames_per_dwell(settings: Settings) -> int:
    """
    Return the frames a camera needs in a dwell for an observation of the marker.

    Decoded targets (ChArUco corners, an ArUco tag's id) are trustworthy in one frame; a
    sphere is a bright blob that a glint can imitate in one frame, so it needs two.
    """
    return 2 if settings.target.marker_type == 'sphere' else 1


def engine_settings(settings: Settings, board: Optional[BoardTarget] = None) -> EngineSettings:
    """Return the engine's settings (also used when the node's parameters change at runtime)."""
    s = settings.schedule
    robot, eih = settings.robot, settings.target.eye_in_hand
    guess = (tuple(robot.marker_offset) if _place_by_kinematics(settings) else None)
    # With the cameras on the arm their poses are in the link's frame, the target's in the base.
    return EngineSettings(list(settings.inputs.camera_names), settings.prior, settings.solver,
                          min_samples=s.min_samples, solve_period_s=s.solve_period_s,
                          min_new_samples=s.min_new_samples,
                          base_frame=robot.marker_link if eih else robot.base_frame,
                          board=board,
                          marker_link=robot.base_frame if eih else robot.marker_link,
                          eye_in_hand=eih, point_place_guess=guess,
                          detect_changes=s.detect_changes,
                          change=ChangeSettings(false_alarm=s.change_false_alarm),
                          recalibration_samples=s.recalibration_samples,
                          max_sample_age_s=s.max_sample_age_s,
                          marker_light=_marker_light(settings),
                          pool_light_shift=(settings.target.marker_type == 'sphere' and
                                            settings.detector.sphere_centre == 'shaded_pooled')
                          ).validate()


def _marker_light(settings: Settings):
    """Return the engine's marker_light of a lit ball (None when no lamp is given)."""
    t = settings.target
    if not t.lamp:
        return None
    if t.marker_type != 'sphere':
        raise ValueError('marker_lamp is for marker_type sphere, got ' + repr(t.marker_type))
    if not t.radius > 0:
        raise ValueError('marker_lamp needs marker_radius > 0 (the ball\'s radius, m)')
    if settings.detector.sphere_centre != 'centroid':
        raise ValueError('marker_lamp corrects intensity centroids: it needs sphere_centre '
                         f'centroid, got {settings.detector.sphere_centre!r} (a fitted centre '
                         'has no light offset to remove)')
    return tuple(t.lamp), t.ambient, t.radius


def _place_by_kinematics(settings: Settings) -> bool:
    """Whether a point marker's place is estimated by a kinematic model's tip errors."""
    t = settings.target
    return t.estimate_mount and not t.is_board and settings.prior.model in KINEMATIC_MODELS


def build_store(settings: Settings, chain: Optional[KinematicChain]) -> SampleStore:
    """Return an empty sample store bounded by the store settings."""
    st = settings.store
    return SampleStore(max_samples=st.max_samples, min_sample_spacing=st.min_sample_spacing,
                       same_point_tolerance=min(SAME_POINT_TOLERANCE, st.min_sample_spacing),
                       joint_names=None if chain is None else chain.joint_names)


def build_engine(settings: Settings, chain: Optional[KinematicChain],
                 board: Optional[BoardTarget] = None) -> CalibrationEngine:
    """
    Engine and its sample store.

    ``chain`` (None with pose input) gives the kinematic models their Jacobian; a board target
    has no use for it (those models are refused with a board).
    """
    engine_s = engine_settings(settings, board)
    store = build_store(settings, chain)
    if chain is None or board is not None:
        return CalibrationEngine(engine_s, store)
    offset = np.asarray(settings.robot.marker_offset, float)
    sigma = (kinematic_sigmas(chain.error_names, {'tip_translation': PLACE_GUESS_SIGMA})
             if _place_by_kinematics(settings) else None)

    def kinematics(Q, place=offset):
        return KinematicData(chain.jacobian_errors(Q, place), chain.error_names, sigma)
    return CalibrationEngine(engine_s, store, kinematics_fn=kinematics)


def build_pipeline(settings: Settings, log: Optional[Callable[[str], None]] = None,
                   data_set_target=None, data_set_guess=None, pose_input=None) -> Pipeline:
    """
    Wire the whole pipeline from ``settings``.

    ``data_set_target`` and ``data_set_guess`` complete a board from a data set's own files
    (:func:`build_board`); ``pose_input`` as for :func:`build_chain`.  ``log(message)`` receives
    the front end's rate-limited reports.
    """
    chain = build_chain(settings, pose_input)
    board, target = build_board(settings, data_set_target, data_set_guess)
    names = list(settings.inputs.camera_names)
    detectors = build_detectors(settings, names, board)
    fe, det = settings.front_end, settings.detector
    collector = SampleCollector(chain, settings.robot.marker_offset, names, detectors,
                                fe.max_marker_speed, fe.dwell_radius, log=log, board=target,
                                max_views_per_dwell=det.max_views_per_dwell,
                                min_frames=min_frames_per_dwell(settings),
                                cameras_on_link=settings.target.eye_in_hand,
                                still_guard_s=fe.still_guard,
                                stamp_latency_s=dict(fe.image_stamp_latency),
                                max_fits_per_view=fits_per_view(settings))
    timing = latency_detectors(settings, names, chain)
    latency = None if timing is None else LatencyTimer(
        timing, chain, settings.robot.marker_offset, min_marker_speed=fe.max_marker_speed)
    return Pipeline(chain, board, collector, build_engine(settings, chain, target), latency)
