"""
The calibrator's parameters, one table for the node and the offline CLI.

The ROS node declares them with descriptors; the offline CLI reads them from the same ROS 2
parameter file.

Each parameter has a type, a default, a description and a check.  A bad value is refused with the
parameter's name and the reason - never silently replaced by a default.  The first block of
names is the node's public contract (README, "Parameters"); the rest are documented tuning
knobs.  :mod:`armcal_ros.settings` turns checked values into typed settings.
"""

import math
import os
import re
from dataclasses import dataclass, replace
from typing import Any, Callable, Dict, Optional

import yaml

from armcal_ros.core.camera import DISTORTION_NAMES
from armcal_ros.core.intrinsics_prior import INTRINSICS_MODES
from armcal_ros.core.kernels import KERNELS
from armcal_ros.core.priors import KINEMATIC_MODELS, NOISE_MODELS
from armcal_ros.core.robust import LOSSES

NAME_RE = re.compile(r'^[A-Za-z0-9_]+$')
MARKER_TYPES = ('sphere', 'aruco', 'charuco')
#: SphereDetector.CENTRES (frontend/detectors/sphere.py), and the shaded fit's light shift
#: pooled over each camera's views (core/light_pooling.py)
SPHERE_CENTRES = ('centroid', 'shaded', 'shaded_pooled')
POSE_TYPES = ('pose_stamped', 'transform_stamped')
NODE_NAME = 'armcal'
#: Parameters that name files: a relative path is resolved against the parameter file's folder.
PATH_PARAMETERS = ('robot_description_file', 'intrinsics_files')


@dataclass(frozen=True)
class Param:
    """One parameter: name, type ('string', 'double', 'int', 'bool', 'double[]', 'string[]')."""

    name: str
    type: str
    default: Any
    description: str
    check: Optional[Callable[[Any], Optional[str]]] = None
    read_only: bool = False
    minimum: Optional[float] = None
    maximum: Optional[float] = None


def _positive(v):
    return None if v > 0 and math.isfinite(v) else 'must be a finite number > 0'


def _nonneg(v):
    return None if v >= 0 and math.isfinite(v) else 'must be a finite number >= 0'


def _one_of(options):
    def check(v):
        return None if v in options else f'must be one of {list(options)}'
    return check


def _vec3(v):
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        return 'must be 3 finite numbers [x, y, z] in metres'
    return None


def _camera_names(v):
    if not v:
        return 'must name at least one camera'
    bad = [n for n in v if not NAME_RE.match(n)]
    if bad:
        return f'names must use [A-Za-z0-9_] only (camera_info convention), bad: {bad}'
    if len(set(v)) != len(v):
        return f'has duplicate names: {v}'
    return None


def _camera_info_names(v):
    if not v:
        return None
    bad = [n for n in v if not NAME_RE.match(n)]
    if bad:
        return (f'names must use [A-Za-z0-9_] only (camera_info_manager refuses others), '
                f'bad: {bad}')
    if len(set(v)) != len(v):
        return f'has duplicate names: {v}'
    return None


def _topics(v):
    bad = [t for t in v if not t or ' ' in t]
    return f'has empty or malformed topic names: {bad}' if bad else None


def _distortion(v):
    bad = [d for d in v if d not in DISTORTION_NAMES]
    return f'unknown terms {bad}; allowed {list(DISTORTION_NAMES)}' if bad else None


def _modes(v):
    bad = [m for m in v if m not in INTRINSICS_MODES]
    return f'unknown modes {bad}; allowed {list(INTRINSICS_MODES)}' if bad else None


def _pose7(v):
    if len(v) == 0:
        return None
    if len(v) != 7 or not all(math.isfinite(x) for x in v):
        return 'must be empty or [x, y, z, qx, qy, qz, qw]'
    if abs(math.sqrt(sum(x * x for x in v[3:])) - 1.0) > 1e-3:
        return 'its quaternion must have unit length'
    return None


PARAMS = [
    # The public contract (README, "Parameters").
    Param('robot_description', 'string', '', 'URDF text of the robot (ROS convention)'),
    Param('robot_description_file', 'string', '',
          'path to a URDF file (used when robot_description is empty; a relative path is '
          'resolved against the parameter file\'s directory)'),
    Param('base_frame', 'string', 'base_link', 'world frame: the robot base link'),
    Param('marker_link', 'string', 'tool0', 'link the marker is attached to'),
    Param('marker_offset', 'double[]', [0.0, 0.0, 0.0],
          'marker (sphere or tag centre) position in marker_link, metres', _vec3),
    Param('marker_type', 'string', 'sphere', 'marker detector: sphere, aruco or charuco',
          _one_of(MARKER_TYPES)),
    Param('joint_states_topic', 'string', '/joint_states', 'sensor_msgs/JointState topic'),
    Param('camera_names', 'string[]', ['cam1', 'cam2', 'cam3'],
          'camera names ([A-Za-z0-9_]); optical frames are <name>_optical_frame', _camera_names),
    Param('image_topics', 'string[]', ['/cam1/image_raw', '/cam2/image_raw', '/cam3/image_raw'],
          'one image topic per camera, same order; topics ending in /compressed carry '
          'CompressedImage', _topics),
    Param('noise_model', 'string', 'auto',
          'prior on the robot\'s points: ' + ', '.join(NOISE_MODELS), _one_of(NOISE_MODELS)),
    Param('pixel_sigma', 'double', 0.0,
          'image noise, pixels per axis; 0: estimated from the data (the residuals\' variance '
          'factor for a given model, the free network for auto, the pooled detections\' '
          'scatter with one camera); > 0: used as given', _nonneg, minimum=0.0),
    Param('point_sigma', 'double', 0.0002, 'independent point noise s_n, metres', _positive,
          minimum=0.0),
    Param('bias_sigma', 'double', 0.001, 'correlated bias scale s_b, metres', _nonneg,
          minimum=0.0),
    Param('coherence_length', 'double', 0.3, 'coherence length L of the bias, metres', _positive,
          minimum=0.0),
    Param('solve_period', 'double', 10.0, 'seconds between background solves', _nonneg,
          minimum=0.0),
    Param('min_samples', 'int', 20, 'samples (3-D points) before the first solve',
          lambda v: None if v >= 1 else 'must be >= 1', minimum=1),
    Param('output_dir', 'string', '',
          'where calibration files and saved samples go (empty: $ROS_HOME/armcal, ROS_HOME '
          'defaulting to ~/.ros)'),
    # Tuning knobs.
    Param('kernel', 'string', 'squared_exponential', 'correlation kernel: ' + ', '.join(KERNELS),
          _one_of(KERNELS)),
    Param('free_distortion', 'string[]', ['k1', 'k2', 'p1', 'p2'],
          'plumb_bob terms to estimate (others fixed at 0)', _distortion),
    Param('robust_loss', 'string', 'huber', 'robust loss: ' + ', '.join(LOSSES), _one_of(LOSSES)),
    Param('robust_loss_scale', 'double', 2.0, 'robust loss scale, pixels', _positive,
          minimum=0.0),
    Param('outlier_gate_sigmas', 'double', 5.0,
          'after convergence, observations beyond this many robust sigmas are gated', _positive,
          minimum=0.0),
    Param('max_marker_speed', 'double', 0.0375,
          'stillness: marker speed (m/s) above which a frame is not used; the default moves the '
          'image 0.1 px over 5 ms of stamp error at f = 800 px and 1.5 m', _positive,
          minimum=0.0),
    Param('still_guard', 'double', 0.0,
          'stillness must also have held this long (s) before a frame\'s stamp: set it to the '
          'cameras\' stamp latency when their drivers stamp images on arrival (USB, GigE: '
          '0.03-0.1 s); 0 judges stillness at the stamp only', _nonneg, minimum=0.0),
    Param('image_stamp_latency', 'double[]', [],
          'per camera (same order as camera_names; one entry: every camera), how late (s) its '
          'driver stamps images: subtracted from each image\'s stamp before it is paired with '
          'the joint angles (USB, GigE drivers that stamp on arrival: 0.01-0.1 s; armcal '
          'calibrate measures it, report.json stamp_latency, and so does the node, '
          '/diagnostics stamp_latency_ms); empty: stamps are exposure times'),
    Param('dwell_radius', 'double', 0.001,
          'still frames within this distance (m) of a dwell\'s first are pooled into one sample',
          _positive, minimum=0.0),
    Param('min_sample_spacing', 'double', 0.005,
          'a new sample closer than this (m) to a stored one is merged or dropped', _nonneg,
          minimum=0.0),
    Param('max_samples', 'int', 2000, 'most samples kept (spatially diverse ones are kept)',
          lambda v: None if v >= 10 else 'must be >= 10', minimum=10),
    Param('min_new_samples', 'int', 5, 'new samples needed before a re-solve',
          lambda v: None if v >= 0 else 'must be >= 0', minimum=0),
    Param('detect_changes', 'bool', True,
          'test every new sample against the calibration; a camera that moved or changed its '
          'lens starts a new epoch (its older views retired) and is recalibrated; an arm or '
          'marker change is reported (README, "When a camera moves")'),
    Param('change_false_alarm', 'double', 1e-6,
          'false alarms per view of a camera the change test allows (default: one per million '
          'views; at most 1e-5, above which two disagreeing views could raise an alarm)',
          lambda v: None if 0 < v <= 1e-5 else 'must be in (0, 1e-5]', minimum=0.0),
    Param('recalibration_samples', 'int', 20,
          'new views a changed camera needs before it is solved and published again',
          lambda v: None if v >= 6 else 'must be >= 6 (a camera has 6 pose parameters)',
          minimum=6),
    Param('max_sample_age', 'double', 0.0,
          'forgetting for slow drift: views older than this (s, before the newest) are '
          'retired before each solve; 0 keeps every view', _nonneg, minimum=0.0),
    Param('solver_process', 'bool', True,
          'node: run each solve in a child process (on another core), so that a solve never '
          'holds the interpreter the front end needs; false solves on a thread of the node '
          '(armcal calibrate always solves in its own process)'),
    Param('sphere_min_radius_px', 'double', 1.5, 'smallest sphere image radius, pixels',
          _positive, minimum=0.0),
    Param('sphere_max_radius_px', 'double', 40.0, 'largest sphere image radius, pixels',
          _positive, minimum=0.0),
    Param('sphere_static_scene', 'bool', True,
          'learn each camera\'s static scene (median of five images kept as the marker moves) '
          'and subtract it before the sphere search: clutter and static look-alikes (lamps, '
          'bolt heads) vanish; a marker parked for about 120 images becomes scenery until it '
          'moves; a knocked camera\'s scene, shifted, moves with it and is learnt again'),
    Param('sphere_centre', 'string', 'shaded_pooled',
          'how the sphere\'s centre is measured: shaded_pooled (default: a fit of a shaded '
          'ball - outline, one lamp from any side, ambient, blur - at every still frame, and '
          'each view solved at its intensity centroid plus the light\'s shift of the '
          'centroid pooled over the camera\'s views at nearby places: the centroid\'s noise '
          'without its bias under the cell\'s lights; where the shift is no function of the '
          'place - an LED whose bright side turns with the tool - the fitted centres are '
          'kept; 2-3 ms per still frame) or shaded (the per-view fit alone: about twice the '
          'centroid\'s noise) or centroid (intensity-weighted, 0.2 ms: right only for a ball '
          'that glows alike from every side; half a pixel off towards the lamp for a matte '
          'ball under one)',
          _one_of(SPHERE_CENTRES)),
    Param('aruco_dictionary', 'string', 'DICT_4X4_50', 'ArUco dictionary (cv2.aruco name)'),
    Param('aruco_id', 'int', -1, 'ArUco id of the marker (-1: any)'),
    Param('aruco_size', 'double', 0.0,
          'side of the ArUco tag (its black square), metres: > 0 makes the tag a rigid target '
          'of four corners on marker_link (its pose there given by target_pose_guess or '
          'estimated with estimate_marker_offset); 0: the tag\'s centre as a point marker',
          _nonneg, minimum=0.0),
    Param('publish_tf', 'bool', True,
          'publish static TF base_frame -> each camera\'s optical frame (the frame_id its '
          'images carry; <camera>_optical_frame until one has arrived)'),
    Param('write_camera_info', 'bool', True,
          'the node also writes each calibrated camera\'s YAML where camera_info_manager looks '
          'by default (camera_info_dir/<camera_info_name>.yaml), so a driver started later '
          'loads it; a file found there that armcal did not write is kept once as '
          '<name>.before_armcal.yaml'),
    Param('camera_info_dir', 'string', '',
          'directory of those files (empty: $ROS_HOME/camera_info, camera_info_manager\'s '
          'default; ROS_HOME defaulting to ~/.ros)'),
    Param('camera_info_names', 'string[]', [],
          'one per camera: the camera_name its driver gives camera_info_manager (file '
          'name and camera_name in the YAML); empty: the camera names', _camera_info_names),
    Param('republish_images', 'bool', False,
          'republish each image under the node\'s namespace (~/<camera>/image_raw, or '
          '~/<camera>/image_raw/compressed) beside its CameraInfo, for consumers that want '
          'both from one place (an image_transport camera subscriber, image_proc)'),
    Param('set_camera_info_services', 'string[]', [],
          'if not empty, one sensor_msgs/srv/SetCameraInfo service per camera to commit each '
          'accepted calibration to its driver (e.g. /cam1/set_camera_info)'),
    Param('resume', 'bool', True, 'reload saved samples and calibration from output_dir'),
    # Board targets and pose input.
    Param('charuco_rows', 'int', 0, 'ChArUco board squares per column (0: unset; a '
          'robot_cal_tools folder takes it from target.yaml)',
          lambda v: None if v == 0 or v >= 2 else 'must be 0 (unset) or >= 2', minimum=0),
    Param('charuco_cols', 'int', 0, 'ChArUco board squares per row (0: unset)',
          lambda v: None if v == 0 or v >= 2 else 'must be 0 (unset) or >= 2', minimum=0),
    Param('charuco_square_size', 'double', 0.0, 'ChArUco square side, metres (0: unset)',
          _nonneg, minimum=0.0),
    Param('charuco_marker_size', 'double', 0.0, 'ChArUco marker side, metres (0: unset)',
          _nonneg, minimum=0.0),
    Param('charuco_dictionary', 'string', 'DICT_6X6_250', 'ChArUco ArUco dictionary'),
    Param('charuco_legacy_pattern', 'bool', False,
          'board made for OpenCV < 4.6 (robot_cal_tools): its corner numbering, frame (y up '
          'from the bottom row) and square pattern'),
    Param('max_views_per_dwell', 'int', 3,
          'charuco: once this many still frames of a camera in one dwell show the board, its '
          'later still frames there are skipped undecoded (a board search costs tens of ms, one '
          'view suffices, three let the median drop one bad view); 0: no cap; sphere and aruco '
          'targets are never capped (their detection is cheap, their pooling wants many frames)',
          lambda v: None if v >= 0 else 'must be >= 0 (0: no cap)', minimum=0),
    Param('estimate_marker_offset', 'bool', False,
          'estimate the target\'s place on marker_link from the data: a board\'s pose '
          '(T_link_target), or a sphere\'s or tag centre\'s position, seeded at marker_offset '
          '(a guess centimetres off will do; the views must turn the wrist)'),
    Param('estimate_aruco_size', 'bool', False,
          'estimate the tag\'s side from the data (the arm\'s poses set the scale), aruco_size '
          'being a guess within about half its value; needs estimate_marker_offset'),
    Param('eye_in_hand', 'bool', False,
          'the cameras ride on marker_link and look at a static target: marker_offset (a point) '
          'or target_pose_guess (a tag or board) are then its place in base_frame, and the '
          'cameras\' poses are given in marker_link (T_<marker_link>_camera)'),
    Param('marker_lamp', 'double[]', [],
          'a matte ball lit by one lamp: the lamp\'s [x, y, z] in base_frame (m); each view\'s '
          'centroid, pulled towards the lit side, is corrected (needs marker_radius); empty: '
          'the marker glows alike from every side (an LED in a diffuser)',
          lambda v: None if len(v) in (0, 3) and all(math.isfinite(x) for x in v)
          else 'must be empty or 3 finite numbers'),
    Param('marker_ambient', 'double', 0.25,
          'with marker_lamp: the brightness of the ball\'s unlit side as a fraction of full light',
          lambda v: None if 0.0 <= v <= 1.0 else 'must be in [0, 1]', minimum=0.0, maximum=1.0),
    Param('marker_radius', 'double', 0.0,
          'the ball\'s radius (m), for marker_lamp; 0: not given', _nonneg, minimum=0.0),
    Param('target_pose_guess', 'double[]', [],
          'T_link_target of a board as [x, y, z, qx, qy, qz, qw] (seed when estimated; empty: '
          'found by hand-eye, or the data set\'s own guess)', _pose7),
    Param('pose_topic', 'string', '',
          'geometry_msgs PoseStamped or TransformStamped topic with marker_link\'s pose in '
          'base_frame; when set it replaces joint states and the robot model (pose input)'),
    # Given intrinsics.
    Param('intrinsics_mode', 'string[]', [],
          'per camera (same order as camera_names; one entry: every camera): estimate (from '
          'the data), fixed (given in intrinsics_files; only the pose is estimated) or prior '
          '(a Gaussian prior around the given values); empty: estimate every camera', _modes),
    Param('intrinsics_files', 'string[]', [],
          'per camera, a camera_info YAML (camera_calibration_parsers format, e.g. what the '
          'driver or camera_calibration wrote) with the given K and D for intrinsics_mode fixed '
          'or prior; "" (or an empty list): the first message on the CameraInfo topic beside '
          'the camera\'s images (/ns/image_raw -> /ns/camera_info), live or in the bag; '
          'relative paths are resolved against the parameter file\'s directory'),
    Param('intrinsics_sigma_px', 'double', 0.0,
          'prior standard deviation of fx, fy, cx and cy, pixels, for intrinsics_mode prior '
          '(no default: how good a factory calibration is depends on the camera)', _nonneg,
          minimum=0.0),
    Param('intrinsics_sigma_dist', 'double', 0.0,
          'prior standard deviation of each free distortion coefficient for intrinsics_mode '
          'prior; 0 holds the given distortion fixed', _nonneg, minimum=0.0),
    Param('pose_type', 'string', 'pose_stamped',
          'message type on pose_topic for the node: pose_stamped (geometry_msgs/PoseStamped) '
          'or transform_stamped (geometry_msgs/TransformStamped); a bag says its own type',
          _one_of(POSE_TYPES)),
]
#: Largest valid values (the smallest are in the table).  Not tuning: bounds past which a value
#: is a typo or a unit slip, sized from physics with a wide margin - an image noise of tens of
#: pixels leaves no calibration in the data, an arm error of a metre is no arm, a marker or
#: board is not metres across.  Without them a finite but absurd value (pixel_sigma 1e300)
#: overflowed deep in the solver instead of being refused here.
_MAXIMA = {
    'pixel_sigma': 50.0, 'point_sigma': 1.0, 'bias_sigma': 1.0, 'coherence_length': 100.0,
    'solve_period': 86400.0, 'robust_loss_scale': 1000.0, 'outlier_gate_sigmas': 1000.0,
    'max_marker_speed': 100.0, 'still_guard': 10.0, 'dwell_radius': 1.0, 'min_sample_spacing': 1.0,
    'max_sample_age': 10.0 * 365 * 86400, 'sphere_min_radius_px': 10000.0,
    'sphere_max_radius_px': 10000.0, 'aruco_size': 10.0, 'charuco_square_size': 10.0,
    'charuco_marker_size': 10.0, 'marker_radius': 1.0, 'intrinsics_sigma_px': 100000.0,
    'intrinsics_sigma_dist': 100.0, 'min_samples': 1000000, 'max_samples': 10000000,
    'min_new_samples': 1000000, 'recalibration_samples': 1000000, 'charuco_rows': 1000,
    'charuco_cols': 1000, 'max_views_per_dwell': 1000,
}
PARAMS = [replace(p, maximum=_MAXIMA[p.name]) if p.name in _MAXIMA and p.maximum is None else p
          for p in PARAMS]
BY_NAME = {p.name: p for p in PARAMS}


def _coerce(p: Param, value):
    """Return ``value`` as the parameter's type or raise ValueError naming it."""
    t = p.type
    try:
        if t == 'string':
            if not isinstance(value, str):
                raise TypeError
            return value
        if t == 'bool':
            if not isinstance(value, bool):
                raise TypeError
            return value
        if t == 'int':
            if isinstance(value, bool) or not isinstance(value, int):
                raise TypeError
            return int(value)
        if t == 'double':
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError
            return float(value)
        if t == 'double[]':
            if isinstance(value, (str, bytes)) or any(isinstance(x, bool) for x in value):
                raise TypeError
            return [float(x) for x in value]
        if t == 'string[]':
            if isinstance(value, (str, bytes)) or not all(isinstance(x, str) for x in value):
                raise TypeError
            return list(value)
    except (TypeError, ValueError):
        pass
    raise ValueError(f'parameter {p.name}: expected {t}, got {value!r}')


def check_value(name, value):
    """Coerce and check one parameter; return the value or raise ValueError(name: reason)."""
    if name not in BY_NAME:
        raise ValueError(f'unknown parameter {name!r}')
    p = BY_NAME[name]
    v = _coerce(p, value)
    if p.type in ('double', 'int'):
        # NaN compares False both ways: refused here, whatever the table's own check says.
        if not math.isfinite(v):
            raise ValueError(f'parameter {name}: must be a finite number (got {value!r})')
        if p.maximum is not None and v > p.maximum:
            raise ValueError(f'parameter {name}: must be <= {p.maximum:g} (got {value!r})')
        if p.minimum is not None and v < p.minimum:
            raise ValueError(f'parameter {name}: must be >= {p.minimum:g} (got {value!r})')
    elif p.type == 'double[]' and not all(math.isfinite(x) for x in v):
        raise ValueError(f'parameter {name}: every value must be a finite number (got {value!r})')
    if p.check is not None:
        why = p.check(v)
        if why:
            raise ValueError(f'parameter {name}: {why} (got {value!r})')
    return v


def check_all(values: Dict[str, Any], require_robot_model=True):
    """
    Check the cross-parameter rules; raise ValueError naming the parameters.

    A robot model is not needed with pose input (``pose_topic``) or when the caller reads
    poses from elsewhere (``require_robot_model`` False, e.g. a robot_cal_tools folder).
    """
    cams, topics = values['camera_names'], values['image_topics']
    if len(cams) != len(topics):
        raise ValueError(f'parameters camera_names and image_topics must have the same length, '
                         f'got {len(cams)} and {len(topics)}')
    svc = values['set_camera_info_services']
    if svc and len(svc) != len(cams):
        raise ValueError(f'parameter set_camera_info_services must be empty or have one entry '
                         f'per camera ({len(cams)}), got {len(svc)}')
    lat = values['image_stamp_latency']
    if lat and len(lat) not in (1, len(cams)):
        raise ValueError(f'parameter image_stamp_latency must be empty, one value or one per '
                         f'camera ({len(cams)}), got {len(lat)}')
    if any(abs(v) > 1.0 for v in lat):
        raise ValueError(f'parameter image_stamp_latency must be within 1 s of the stamp, got '
                         f'{list(lat)}')
    names = values['camera_info_names']
    if names and len(names) != len(cams):
        raise ValueError(f'parameter camera_info_names must be empty or have one entry per '
                         f'camera ({len(cams)}), got {len(names)}')
    if values['sphere_min_radius_px'] >= values['sphere_max_radius_px']:
        raise ValueError('parameters sphere_min_radius_px must be < sphere_max_radius_px')
    model = values['noise_model']
    if model in KINEMATIC_MODELS and values['pose_topic']:
        raise ValueError(f'parameters noise_model and pose_topic: noise_model {model} needs '
                         'joint angles (the robot model\'s error Jacobian at each sample), '
                         'which pose input does not have; use fixed, independent, correlated '
                         'or auto')
    tag_corners = values['marker_type'] == 'aruco' and values['aruco_size'] > 0
    if model in KINEMATIC_MODELS and (values['marker_type'] == 'charuco' or tag_corners):
        raise ValueError(f'parameters noise_model and marker_type: noise_model {model} is not '
                         'available with a charuco board or a tag of given aruco_size (the '
                         'board solver\'s global parameters are the target\'s mount on the '
                         'link, not the arm\'s kinematic errors); use fixed, independent, '
                         'correlated or auto')
    if values['eye_in_hand'] and model in KINEMATIC_MODELS:
        raise ValueError(f'parameters noise_model and eye_in_hand: noise_model {model} is not '
                         'available with cameras on the arm (the target is static; the '
                         'solver\'s global parameters are its place); use fixed, independent, '
                         'correlated or auto')
    if values['eye_in_hand'] and not (values['marker_type'] == 'charuco' or tag_corners or
                                      values['estimate_marker_offset']):
        raise ValueError('parameters eye_in_hand and estimate_marker_offset: with the cameras '
                         'on the arm a point target\'s place in base_frame is estimated; set '
                         'estimate_marker_offset (marker_offset is the guess)')
    if values['estimate_aruco_size'] and not (tag_corners and values['estimate_marker_offset']):
        raise ValueError('parameter estimate_aruco_size: needs marker_type aruco with '
                         'aruco_size > 0 (the guess) and estimate_marker_offset (the tag\'s '
                         'pose is estimated with its size)')
    if tag_corners and values['aruco_id'] < 0:
        raise ValueError('parameters aruco_size and aruco_id: a tag used by its corners '
                         '(aruco_size > 0) needs its aruco_id')
    modes, files = values['intrinsics_mode'], values['intrinsics_files']
    if len(modes) not in (0, 1, len(cams)):
        raise ValueError(f'parameter intrinsics_mode must be empty, one mode, or one per camera '
                         f'({len(cams)}), got {len(modes)}')
    given = [c for c, m in zip(cams, modes * len(cams) if len(modes) == 1 else modes)
             if m != 'estimate']
    if given and files and len(files) != len(cams):
        raise ValueError(f'parameters intrinsics_mode and intrinsics_files: intrinsics_files '
                         f'must be empty (every camera\'s CameraInfo topic) or have one entry '
                         f'per camera ({len(cams)}), got {len(files)}')
    if 'prior' in modes and not values['intrinsics_sigma_px'] > 0:
        raise ValueError('parameters intrinsics_mode and intrinsics_sigma_px: the prior mode '
                         'needs intrinsics_sigma_px > 0 (the given values\' standard deviation)')
    if require_robot_model and not values['pose_topic'] and \
            not values['robot_description'] and not values['robot_description_file']:
        raise ValueError('parameters robot_description or robot_description_file: one must be '
                         'set (URDF text, or a path to a URDF file)')


def defaults():
    """Return every parameter's default value."""
    return {p.name: (list(p.default) if isinstance(p.default, list) else p.default)
            for p in PARAMS}


def load_params_file(path, node_name=NODE_NAME, require_robot_model=True, overrides=None):
    """
    Read a ROS 2 parameter file and return the checked values (defaults filled in).

    Accepts ``<node_name>: ros__parameters:`` and ``/**: ros__parameters:`` (both merged, the
    node's own taking precedence) and ``/<node_name>``.  Unknown parameter names are an error
    naming them.  ``overrides`` (name -> value, e.g. from a command line) replace the file's
    values.  ``require_robot_model`` is passed to :func:`check_all`.  A relative
    ``robot_description_file`` is resolved against the file's directory.
    """
    try:
        with open(path) as f:
            doc = yaml.safe_load(f)
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f'{path}: cannot read the parameter file: {exc}') from exc
    if not isinstance(doc, dict):
        raise ValueError(f'{path}: expected a mapping of node names to ros__parameters')
    merged = {}
    for key in ('/**', node_name, '/' + node_name):
        section = doc.get(key)
        if section is None:
            continue
        if not isinstance(section, dict) or 'ros__parameters' not in section:
            raise ValueError(f'{path}: section {key!r} has no ros__parameters')
        merged.update(section['ros__parameters'] or {})
    if not merged:
        raise ValueError(f'{path}: no ros__parameters for {node_name!r} or /** '
                         f'(sections found: {list(doc)})')
    merged.update(overrides or {})
    unknown = sorted(k for k in merged if k not in BY_NAME)
    if unknown:
        raise ValueError(f'{path}: unknown parameter(s) {unknown}')
    values = defaults()
    for k, v in merged.items():
        values[k] = check_value(k, v)
    resolve_paths(values, [os.path.dirname(os.path.abspath(path))])
    check_all(values, require_robot_model)
    return values


def resolve_paths(values, directories):
    """
    Resolve the relative paths of :data:`PATH_PARAMETERS` in place.

    A relative path becomes the first ``directories`` entry where it exists (the last one when
    it exists nowhere, so the error names a full path).
    """
    def resolve(rel):
        if not rel or os.path.isabs(rel) or not directories:
            return rel
        for d in directories:
            if os.path.exists(os.path.join(d, rel)):
                return os.path.normpath(os.path.join(d, rel))
        return os.path.normpath(os.path.join(directories[-1], rel))
    for name in PATH_PARAMETERS:
        v = values[name]
        values[name] = [resolve(x) for x in v] if isinstance(v, list) else resolve(v)


def default_output_dir(node_name=NODE_NAME):
    """
    Return $ROS_HOME/<node_name> (ROS_HOME defaulting to ~/.ros).

    Per node name, so that two calibrators of one cell (static cameras and cameras on the arm)
    never share a samples file.
    """
    return os.path.join(ros_home(), node_name)


def ros_home():
    """Return $ROS_HOME, defaulting to ~/.ros as rcutils and camera_info_manager do."""
    return os.environ.get('ROS_HOME') or os.path.join(os.path.expanduser('~'), '.ros')


def default_camera_info_dir():
    """Return $ROS_HOME/camera_info: where camera_info_manager's default URL points."""
    return os.path.join(ros_home(), 'camera_info')


def number_arg(kind=float, minimum=None, maximum=None, above=None):
    """
    Return an argparse ``type`` that reads a finite number within bounds, else refuses it.

    ``minimum`` and ``maximum`` are inclusive, ``above`` an exclusive lower bound.  argparse
    turns the refusal into one usage line naming the option (``--duration nan`` made the
    simulator loop for ever; a finite absurd value is refused as well).
    """
    import argparse

    def parse(text):
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'expected {kind.__name__}, got {text!r}') from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f'must be a finite number, got {text!r}')
        if above is not None and not v > above:
            raise argparse.ArgumentTypeError(f'must be > {above:g}, got {text!r}')
        if minimum is not None and v < minimum:
            raise argparse.ArgumentTypeError(f'must be >= {minimum:g}, got {text!r}')
        if maximum is not None and v > maximum:
            raise argparse.ArgumentTypeError(f'must be <= {maximum:g}, got {text!r}')
        return v
    parse.__name__ = kind.__name__     # argparse names the type in its messages
    return parse
