"""
Typed settings: the parameter table's values, checked once and split by pipeline stage.

:func:`settings_from_values` is the one place where a dictionary of parameter values (from a
ROS 2 parameter file, or the node's declared parameters) becomes a :class:`Settings`: every
value is checked by :mod:`armcal_ros.params` (type, range, the rules between parameters), the
prior and solver settings are built and validated, and any refusal is a ValueError that names
the parameter.  Below the composition root (:mod:`armcal_ros.compose`) nothing sees the raw
dictionary; each stage receives its own part:

=============  ===========================================================================
part           parameters
=============  ===========================================================================
``inputs``     camera_names, image_topics, joint_states_topic, pose_topic, pose_type
``robot``      robot_description(_file), base_frame, marker_link, marker_offset
``target``     marker_type, charuco_*, aruco_size, target_pose_guess, estimate_marker_offset,
               eye_in_hand, estimate_aruco_size
``detector``   sphere_*, aruco_*, max_views_per_dwell
``front_end``  max_marker_speed, dwell_radius, still_guard, image_stamp_latency
``store``      max_samples, min_sample_spacing
``prior``      noise_model, point_sigma, bias_sigma, coherence_length, kernel
``solver``     pixel_sigma, free_distortion, robust_loss(_scale), outlier_gate_sigmas, and the
               intrinsics read from intrinsics_files
``schedule``   min_samples, solve_period, min_new_samples, detect_changes, change_false_alarm,
               recalibration_samples, max_sample_age, solver_process
``outputs``    output_dir, publish_tf, set_camera_info_services, resume, write_camera_info,
               camera_info_dir, camera_info_names, republish_images
``intrinsics`` intrinsics_mode, intrinsics_sigma_px, intrinsics_sigma_dist, the CameraInfo
               topics of the given cameras without a file
=============  ===========================================================================
"""

import math
from dataclasses import dataclass, replace
from typing import Any, Dict, Optional, Tuple

import yaml

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.intrinsics_prior import IntrinsicsPrior
from armcal_ros.core.priors import PriorSettings
from armcal_ros.io.calib_files import read_camera_info
from armcal_ros.io.message_fields import camera_info_topic
from armcal_ros.params import (check_all, check_value, default_camera_info_dir,
                               default_output_dir, load_params_file, NODE_NAME)


@dataclass(frozen=True)
class InputSettings:
    """Where the arm's state and the images come from."""

    camera_names: Tuple[str, ...]
    image_topics: Tuple[str, ...]
    joint_states_topic: str = '/joint_states'
    pose_topic: str = ''
    pose_type: str = 'pose_stamped'

    @property
    def pose_input(self) -> bool:
        """Return True when the marker link's measured pose replaces joint states."""
        return bool(self.pose_topic)

    @property
    def arm_topic(self) -> str:
        """Return the topic that carries the arm's state (poses or joint states)."""
        return self.pose_topic or self.joint_states_topic

    def describe_arm(self) -> str:
        """Return 'pose_topic X' or 'joint_states_topic X' (reports, messages)."""
        return (f'pose_topic {self.pose_topic}' if self.pose_input
                else f'joint_states_topic {self.joint_states_topic}')


@dataclass(frozen=True)
class RobotSettings:
    """The robot model and the frames the calibration is expressed in."""

    robot_description: str = ''
    robot_description_file: str = ''
    base_frame: str = 'base_link'
    marker_link: str = 'tool0'
    marker_offset: Tuple[float, float, float] = (0.0, 0.0, 0.0)

    def urdf_text(self) -> str:
        """Return the URDF text; ValueError naming robot_description_file if unreadable."""
        if self.robot_description:
            return self.robot_description
        path = self.robot_description_file
        try:
            with open(path) as f:
                return f.read()
        except OSError as exc:
            raise ValueError(f'parameter robot_description_file: cannot read {path}: '
                             f'{exc}') from exc


@dataclass(frozen=True)
class BoardSettings:
    """A ChArUco board's geometry (0 = unset) and its dictionary."""

    rows: int = 0
    cols: int = 0
    square_size: float = 0.0
    marker_size: float = 0.0
    dictionary: Any = 'DICT_6X6_250'
    legacy: bool = False

    def completed(self, data_set_target=None) -> 'BoardSettings':
        """
        Return the board with unset sizes filled from a data set's own target description.

        ``data_set_target`` (rows, cols, square_size, marker_size, dictionary), e.g. from a
        robot_cal_tools ``target.yaml``, fills unset values; a set value that disagrees with it
        is an error naming the parameter; every size must be set in the end.
        """
        out = self
        if data_set_target is not None:
            fields = {}
            for k, v in zip(('rows', 'cols', 'square_size', 'marker_size'), data_set_target[:4]):
                mine = getattr(self, k)
                if mine == 0:
                    fields[k] = v
                elif not math.isclose(mine, v, rel_tol=1e-6):
                    raise ValueError(f'parameter charuco_{k}: {mine} disagrees with the data '
                                     f'set\'s target ({v})')
            out = replace(self, dictionary=data_set_target[4], **fields)
        unset = [f'charuco_{k}' for k in ('rows', 'cols', 'square_size', 'marker_size')
                 if getattr(out, k) == 0]
        if unset:
            raise ValueError(f'parameters {", ".join(unset)} must be set for a charuco target')
        return out


@dataclass(frozen=True)
class TargetSettings:
    """What the cameras look for: a point marker (sphere, tag) or a board, and its mount."""

    marker_type: str = 'sphere'
    board: BoardSettings = BoardSettings()
    #: Side of an ArUco tag used by its four corners (m); 0: the tag's centre as a point.
    aruco_size: float = 0.0
    #: The cameras ride on the marker link and the target is static in the base frame.
    eye_in_hand: bool = False
    #: Estimate the tag's side (``aruco_size`` is then a guess).
    estimate_size: bool = False
    #: A matte ball lit by one lamp: its position (base frame, m; empty: none), the unlit
    #: side's fraction and the ball's radius (m).
    lamp: Tuple[float, ...] = ()
    ambient: float = 0.25
    radius: float = 0.0
    #: T_link_target of a board as (x, y, z, qx, qy, qz, qw); empty: unknown.
    pose_guess: Tuple[float, ...] = ()
    estimate_mount: bool = False

    @property
    def is_board(self) -> bool:
        """Return True for a multi-point rigid target (a ChArUco board, a tag's corners)."""
        return self.marker_type == 'charuco' or self.tag_corners

    @property
    def tag_corners(self) -> bool:
        """Return True for an ArUco tag used by its four corners."""
        return self.marker_type == 'aruco' and self.aruco_size > 0


@dataclass(frozen=True)
class DetectorSettings:
    """Per-detector knobs (the marker type is in :class:`TargetSettings`)."""

    sphere_min_radius_px: float = 1.5
    sphere_max_radius_px: float = 40.0
    sphere_static_scene: bool = True
    aruco_dictionary: str = 'DICT_4X4_50'
    aruco_id: Optional[int] = None
    max_views_per_dwell: int = 3
    sphere_centre: str = 'shaded_pooled'


@dataclass(frozen=True)
class FrontEndSettings:
    """Stillness and dwell pooling."""

    max_marker_speed: float = 0.0375
    dwell_radius: float = 0.001
    still_guard: float = 0.0
    #: Camera name -> how late its images are stamped (s); subtracted before pairing.
    image_stamp_latency: Tuple[Tuple[str, float], ...] = ()


@dataclass(frozen=True)
class StoreSettings:
    """Bounds of the sample store."""

    max_samples: int = 2000
    min_sample_spacing: float = 0.005


@dataclass(frozen=True)
class ScheduleSettings:
    """When the engine solves."""

    min_samples: int = 20
    solve_period_s: float = 10.0
    min_new_samples: int = 5
    detect_changes: bool = True
    change_false_alarm: float = 1e-6
    recalibration_samples: int = 20
    max_sample_age_s: float = 0.0
    #: The node's solves in a child process (armcal_ros/solver_process.py).
    solver_process: bool = True


@dataclass(frozen=True)
class IntrinsicsSettings:
    """Given intrinsics: which cameras, how held, and those still to come from CameraInfo."""

    modes: Tuple[Tuple[str, str], ...] = ()
    sigma_px: float = 0.0
    sigma_dist: float = 0.0
    #: camera -> CameraInfo topic, for given cameras without a file.
    topics: Tuple[Tuple[str, str], ...] = ()

    def prior_from(self, camera: str, info) -> IntrinsicsPrior:
        """Return the IntrinsicsPrior of ``camera`` from its given values (a Camera)."""
        mode = dict(self.modes)[camera]
        sigma = sigma_dist = None
        if mode == 'prior':
            sigma = (self.sigma_px,) * 4
            if self.sigma_dist > 0:
                sigma_dist = (self.sigma_dist,) * 5
        return IntrinsicsPrior.from_camera(info, sigma, sigma_dist)


@dataclass(frozen=True)
class OutputSettings:
    """Where results go."""

    output_dir: str
    publish_tf: bool = True
    set_camera_info_services: Tuple[str, ...] = ()
    resume: bool = True
    #: Where the node writes each camera's YAML for the drivers (None: not written), and the
    #: driver's name of each camera (camera name -> camera_info_manager's camera_name).
    camera_info_dir: Optional[str] = None
    camera_info_names: Tuple[Tuple[str, str], ...] = ()
    republish_images: bool = False


@dataclass(frozen=True)
class Settings:
    """Every stage's settings, built by :func:`settings_from_values`."""

    inputs: InputSettings
    robot: RobotSettings
    target: TargetSettings
    detector: DetectorSettings
    front_end: FrontEndSettings
    store: StoreSettings
    prior: PriorSettings
    solver: SolverSettings
    schedule: ScheduleSettings
    outputs: OutputSettings
    intrinsics: IntrinsicsSettings = IntrinsicsSettings()


def prior_settings(values) -> PriorSettings:
    """Build and validate the prior settings; ValueError names the parameter."""
    return _named(lambda: PriorSettings(
        values['noise_model'], values['point_sigma'], values['bias_sigma'],
        values['coherence_length'], values['kernel']).validate())


#: Where the image-noise estimate starts (px): a detector's typical sub-pixel noise; the
#: estimate replaces it after the first adjustment.
START_PIXEL_SIGMA = 0.5


def solver_settings(values) -> SolverSettings:
    """Build and validate the solver settings; ValueError names the parameter."""
    given = given_intrinsics(values)
    given_sigma = values['pixel_sigma'] > 0
    return _named(lambda: SolverSettings(
        pixel_sigma=values['pixel_sigma'] if given_sigma else START_PIXEL_SIGMA,
        estimate_noise=not given_sigma, free_distortion=tuple(values['free_distortion']),
        loss=values['robust_loss'], loss_scale=values['robust_loss_scale'],
        gate_sigmas=values['outlier_gate_sigmas'], intrinsics=given).validate())


def intrinsics_settings(values) -> IntrinsicsSettings:
    """Return the given-intrinsics part: modes, sigmas, the CameraInfo topics still needed."""
    cams, modes = values['camera_names'], values['intrinsics_mode']
    modes = modes * len(cams) if len(modes) == 1 else modes
    files = values['intrinsics_files'] or [''] * len(cams)
    given = [(c, m) for c, m in zip(cams, modes) if m != 'estimate']
    topics = tuple((c, camera_info_topic(t)) for c, m, t, f in
                   zip(cams, modes, values['image_topics'], files) if m != 'estimate' and not f)
    return IntrinsicsSettings(tuple(given), values['intrinsics_sigma_px'],
                              values['intrinsics_sigma_dist'], topics)


def given_intrinsics(values) -> Dict[str, IntrinsicsPrior]:
    """
    Read the given intrinsics of files: camera name -> IntrinsicsPrior (modes fixed, prior).

    The files are camera_info YAMLs; only K, D and the image size are taken from them (the
    camera name in a file is the driver's business).  ValueError names the parameter and file.
    Cameras whose intrinsics come from a CameraInfo topic are not here (the node and the bag
    reader fill them in: :attr:`IntrinsicsSettings.topics`).
    """
    part = intrinsics_settings(values)
    cams = values['camera_names']
    files = values['intrinsics_files'] or [''] * len(cams)
    out = {}
    for cam, mode in part.modes:
        path = files[cams.index(cam)]
        if not path:
            continue
        try:
            info = read_camera_info(path, cam)
        except (OSError, yaml.YAMLError, ValueError) as exc:
            raise ValueError(f'parameter intrinsics_files: camera {cam}: {exc}') from exc
        out[cam] = part.prior_from(cam, info)
    return out


def with_solver_intrinsics(solver: SolverSettings,
                           given: Dict[str, IntrinsicsPrior]) -> SolverSettings:
    """Return ``solver`` with more cameras' intrinsics given (e.g. from CameraInfo)."""
    return replace(solver, intrinsics={**solver.intrinsics, **given})


def with_given_intrinsics(settings: Settings, given: Dict[str, IntrinsicsPrior]) -> Settings:
    """Return ``settings`` with more cameras' intrinsics given (e.g. from CameraInfo)."""
    return replace(settings, solver=with_solver_intrinsics(settings.solver, given))


def _per_camera(values, cameras):
    """Return ((camera, value), ...) from a per-camera list: empty, one for all, or one each."""
    if not values:
        return ()
    values = list(values) * len(cameras) if len(values) == 1 else list(values)
    return tuple((c, float(v)) for c, v in zip(cameras, values))


def _named(build):
    try:
        return build()
    except ValueError as exc:
        text = str(exc)
        raise ValueError(text if text.startswith('parameter') else f'parameter {text}') from exc


def settings_from_values(values: Dict[str, Any], require_robot_model=True,
                         node_name=NODE_NAME) -> Settings:
    """
    Check a full dictionary of parameter values and return the typed :class:`Settings`.

    Every value is checked again (:func:`~armcal_ros.params.check_value`), then the rules
    between parameters (:func:`~armcal_ros.params.check_all`; ``require_robot_model`` False
    when the arm's poses are measured elsewhere, e.g. a robot_cal_tools folder; ``node_name``
    names the default output directory).  Raises ValueError naming the parameter.
    """
    v = {k: check_value(k, x) for k, x in values.items()}
    check_all(v, require_robot_model)
    aruco_id = v['aruco_id']
    return Settings(
        inputs=InputSettings(tuple(v['camera_names']), tuple(v['image_topics']),
                             v['joint_states_topic'], v['pose_topic'], v['pose_type']),
        robot=RobotSettings(v['robot_description'], v['robot_description_file'],
                            v['base_frame'], v['marker_link'], tuple(v['marker_offset'])),
        target=TargetSettings(
            marker_type=v['marker_type'],
            board=BoardSettings(v['charuco_rows'], v['charuco_cols'], v['charuco_square_size'],
                                v['charuco_marker_size'], v['charuco_dictionary'],
                                v['charuco_legacy_pattern']),
            aruco_size=v['aruco_size'], pose_guess=tuple(v['target_pose_guess']),
            estimate_mount=v['estimate_marker_offset'], eye_in_hand=v['eye_in_hand'],
            estimate_size=v['estimate_aruco_size'], lamp=tuple(v['marker_lamp']),
            ambient=v['marker_ambient'], radius=v['marker_radius']),
        detector=DetectorSettings(v['sphere_min_radius_px'], v['sphere_max_radius_px'],
                                  v['sphere_static_scene'], v['aruco_dictionary'],
                                  None if aruco_id < 0 else aruco_id,
                                  v['max_views_per_dwell'], v['sphere_centre']),
        front_end=FrontEndSettings(v['max_marker_speed'], v['dwell_radius'], v['still_guard'],
                                   _per_camera(v['image_stamp_latency'], v['camera_names'])),
        store=StoreSettings(v['max_samples'], v['min_sample_spacing']),
        prior=prior_settings(v),
        solver=solver_settings(v),
        schedule=ScheduleSettings(v['min_samples'], v['solve_period'], v['min_new_samples'],
                                  v['detect_changes'], v['change_false_alarm'],
                                  v['recalibration_samples'], v['max_sample_age'],
                                  v['solver_process']),
        outputs=OutputSettings(
            v['output_dir'] or default_output_dir(node_name), v['publish_tf'],
            tuple(v['set_camera_info_services']), v['resume'],
            (v['camera_info_dir'] or default_camera_info_dir()) if v['write_camera_info']
            else None,
            tuple(zip(v['camera_names'], v['camera_info_names'] or v['camera_names'])),
            v['republish_images']),
        intrinsics=intrinsics_settings(v))


def load_settings(path, overrides: Optional[Dict[str, Any]] = None,
                  require_robot_model=True) -> Settings:
    """
    Read a ROS 2 parameter file (see :func:`~armcal_ros.params.load_params_file`).

    ``overrides`` (parameter name -> value, e.g. from the command line) replace the file's
    values before the checks.
    """
    values = load_params_file(path, require_robot_model=require_robot_model,
                              overrides=overrides)
    return settings_from_values(values, require_robot_model)


def with_noise_model(settings: Settings, model: str) -> Settings:
    """Return ``settings`` with another noise model (checked like the parameter)."""
    model = check_value('noise_model', model)
    return replace(settings, prior=_named(lambda: replace(settings.prior, model=model).validate()))
