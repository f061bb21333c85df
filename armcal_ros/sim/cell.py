"""
A simulated calibration cell with its ground truth.

A PUMA-class arm carries a sphere marker, three cameras watch it, an operator jogs it about.

:func:`simulate_cell` is ROS-free: it returns a :class:`SimResult` with the joint-state stream,
the camera frame schedule with the true marker projection of every frame, the dwell poses with
true and nominal marker positions, and a renderer for the images.
:mod:`armcal_ros.sim.output` writes it to a rosbag2 bag with ground truth.

Scenarios (:data:`SCENARIOS`; magnitudes in :mod:`armcal_ros.sim.true_robot`):

- ``geometric``: joint offsets, joint-origin translations and rotations, marker mount error.
- ``nongeometric``: geometric plus periodic joint-angle errors and gravity compliance.
- ``gp-prior``: the nominal robot is exact; the true marker is the nominal one plus a bias
  field drawn from the paper's correlated prior (s_b = 1 mm, L = 0.3 m, squared exponential).
- ``mixed``: geometric plus a local field from that prior (s_b = 0.3 mm, L = 0.15 m).

Timing: JointState at 200 Hz on a regular control clock, names in a shuffled order plus an extra
gripper joint (the calibrator must map by name).  Each camera has its own 15 Hz clock (a
random phase and a clock-rate error of up to 100 ppm) and stamps each frame at the middle of
its exposure plus Gaussian jitter (2 ms); the bag receive time adds a transfer latency of
8-20 ms, so bag order differs from stamp order as in a real recording.

Occlusion, two kinds: geometric, by the arm's own links, modelled as capsules of radius
``link_radius`` between consecutive link-frame origins (the line of sight from the camera
centre to within ``occlusion_clearance`` of the marker must clear them); and random spans
(an operator's hand, a cable) per camera, a Poisson process of ``occlusion_rate`` per second
lasting 0.3-1.5 s.  Targets are chosen so that the marker is inside every image (with a
margin) and unoccluded by the links in every camera, except for a fraction
``partial_view_probability`` of them where two cameras suffice.  During moves the marker
may leave an image or pass behind the arm.

Camera changes (:class:`CameraChange`, ``SimSettings.camera_changes``): at a given time a camera
can be knocked (its body turns about its optical centre and the centre moves) or refocused (fx
and fy scale).  Frames from then on are projected and rendered with the changed camera, and the
static scene behind it moves with it; :attr:`SimResult.camera_epochs` holds each camera's
states.  The random axes and directions come from their own random stream, so a run's other
draws are the same with and without changes.
"""

import bisect
import math
import os
import sys
from dataclasses import asdict, dataclass, field
from typing import List, Optional

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from armcal_ros.robot.kinematics import KinematicChain
from armcal_ros.sim.arm_effects import arm_effects
from armcal_ros.sim.bias_field import FourierBiasField
from armcal_ros.sim.cameras import ring_of_cameras
from armcal_ros.sim.render import (clutter_scene, expose, glint_patches, marker_signal,
                                   SensorModel)
from armcal_ros.sim.trajectory import teleop_trajectory, Trajectory
from armcal_ros.sim.true_robot import (
    draw_compliance, draw_geometric_errors, draw_periodic, ERROR_MODELS, TrueRobot,
)

#: name -> (geometric, non-geometric, bias field (sigma m, coherence m) or None)
SCENARIOS = {
    'geometric': (True, False, None),
    'nongeometric': (True, True, None),
    'gp-prior': (False, False, (1e-3, 0.3)),
    'mixed': (True, False, (0.3e-3, 0.15)),
}

START_TIME_NS = 1_700_000_000 * 1_000_000_000
OCCLUSION_NONE, OCCLUSION_LINK, OCCLUSION_RANDOM, OUTSIDE_IMAGE = 0, 1, 2, 3


def bundled_urdf(filename):
    """Path of a URDF bundled with the package (source tree or installed share directory)."""
    here = os.path.dirname(os.path.abspath(__file__))
    candidates = [os.path.join(here, '..', '..', 'urdf', filename),
                  os.path.join(sys.prefix, 'share', 'armcal_ros', 'urdf', filename)]
    for c in candidates:
        if os.path.exists(c):
            return os.path.normpath(c)
    raise FileNotFoundError(f'{filename} not found in {candidates}')


def default_urdf_path():
    """Path of the bundled PUMA 560 URDF, the simulator's default arm."""
    return bundled_urdf('puma560.urdf')


@dataclass(frozen=True)
class CameraChange:
    """
    A change of one camera ``time_s`` seconds after the session start.

    A knock turns the camera body by ``rotation_deg`` about a random axis through its optical
    centre and moves the centre by ``translation_mm`` in a random direction; a focus change
    multiplies fx and fy by (1 + ``focal_percent`` / 100), leaving the principal point and
    the distortion as they were.  One change may do both.
    """

    camera: str
    time_s: float
    rotation_deg: float = 0.0
    translation_mm: float = 0.0
    focal_percent: float = 0.0

    def __post_init__(self):
        if not isinstance(self.camera, str) or not self.camera:
            raise ValueError(f'camera must be a camera name, got {self.camera!r}')
        for name in ('time_s', 'rotation_deg', 'translation_mm', 'focal_percent'):
            value = getattr(self, name)
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ValueError(f'{name} must be a number, got {value!r}') from None
            if not math.isfinite(value):
                raise ValueError(f'{name} must be finite, got {value}')
            object.__setattr__(self, name, value)
        if self.time_s <= 0:
            raise ValueError(f'time_s must be > 0, got {self.time_s}')
        if self.rotation_deg < 0:
            raise ValueError(f'rotation_deg must be >= 0, got {self.rotation_deg}')
        if self.translation_mm < 0:
            raise ValueError(f'translation_mm must be >= 0, got {self.translation_mm}')
        if self.focal_percent <= -100:
            raise ValueError(f'focal_percent must be > -100, got {self.focal_percent}')

    def apply(self, camera, axis, direction):
        """
        Return a changed copy of ``camera``; ``axis`` and ``direction`` are unit 3-vectors.

        Both are in the base frame.  The camera-to-base rotation R^T becomes R_a R^T with R_a
        the turn of ``rotation_deg`` about ``axis`` (right hand), so the world-to-camera
        rotation becomes R R_a^T; the centre C becomes C + ``translation_mm`` * ``direction``
        and t = -R C.
        """
        cam = camera.copy()
        if self.rotation_deg or self.translation_mm:
            turn = Rotation.from_rotvec(np.radians(self.rotation_deg) * np.asarray(axis, float))
            centre = camera.center + 1e-3 * self.translation_mm * np.asarray(direction, float)
            cam.rotation = camera.rotation @ turn.as_matrix().T
            cam.translation = -cam.rotation @ centre
        scale = 1.0 + self.focal_percent / 100.0
        cam.fx, cam.fy = camera.fx * scale, camera.fy * scale
        return cam


@dataclass
class SimSettings:
    """Everything a cell simulation depends on besides the scenario and seed."""

    duration: float = 60.0
    urdf_path: str = ''                      # '' = the bundled PUMA 560
    base_frame: str = 'base_link'
    marker_link: str = 'marker'
    marker_offset: tuple = (0.0, 0.0, 0.0)  # marker centre in marker_link, m
    marker_radius: float = 0.005
    # workspace the operator works in (base frame, m) and the joint ranges used to get there
    workspace_min: tuple = (0.3, -0.35, -0.35)
    workspace_max: tuple = (0.8, 0.35, 0.3)
    joint_range_deg: Optional[tuple] = ((-60, 60), (0, 110), (-230, -120), (-90, 90),
                                        (-100, 100), (-90, 90))
    hop_sigma_deg: tuple = (8, 6, 8, 20, 20, 25)
    far_jump_probability: float = 0.15
    partial_view_probability: float = 0.2  # targets the arm hides from one camera
    speed_fraction: float = 0.5             # of the URDF velocity limits
    dwell: tuple = (0.4, 1.2)               # s
    min_move_time: float = 0.4              # s
    # cameras
    camera_names: tuple = ('cam1', 'cam2', 'cam3')
    image_width: int = 640
    image_height: int = 480
    focal: float = 800.0
    camera_distance: tuple = (1.5, 2.0)
    camera_height: tuple = (0.4, 1.0)
    camera_rate: float = 15.0
    camera_clock_ppm: float = 100.0
    stamp_jitter: float = 0.002             # s
    image_latency: tuple = (0.008, 0.020)   # s
    image_margin: float = 25.0              # px, targets project at least this far inside
    camera_min_x: float = -0.2              # m, cameras stay in front of this plane
    # joint states
    joint_rate: float = 200.0
    extra_joints: tuple = ('gripper_finger_joint',)
    # occlusion
    link_radius: float = 0.035
    occlusion_clearance: float = 0.02
    occlusion_rate: float = 1.0 / 40.0      # random spans per second per camera
    occlusion_duration: tuple = (0.3, 1.5)
    # robot errors (see true_robot; error_model 'joint-origin' or 'dh')
    error_model: str = 'joint-origin'
    offset_deg: float = 0.05
    translation_mm: float = 0.3
    rotation_deg: float = 0.03
    tip_translation_mm: float = 0.2
    periodic_deg: tuple = (0.01, 0.025)
    compliance_deg: float = 0.02
    sensor: SensorModel = field(default_factory=SensorModel)
    camera_changes: tuple = ()              # CameraChange (or its dictionaries)
    # What real arms and clocks add, all off by default (module docstring, sim/arm_effects.py)
    stamp_latency: tuple = ()               # s per camera (camera_names order): late stamps
    joint_jitter: float = 0.0               # s, std of the joint states' stamps
    joint_drop: float = 0.0                 # fraction of joint states lost
    backlash_deg: float = 0.0               # per joint, total play
    repeatability_mm: float = 0.0           # per axis, where each stop really ends
    settle_mm: float = 0.0                  # ring-down amplitude after each stop
    settle_hz: float = 10.0
    settle_tau: float = 0.1                 # s
    #: A rolling shutter's readout (s, first row to last); 0: global shutter.
    rolling_shutter: float = 0.0
    #: Lenses (each camera's own stream, others' draws unchanged): k3 of every camera
    #: (x U(0.8, 1.2)), and the std of p1, p2 (0: the default 5e-4).
    lens_k3: float = 0.0
    lens_tangential: float = 0.0

    def __post_init__(self):
        if isinstance(self.sensor, dict):
            self.sensor = SensorModel(**self.sensor)
        if not isinstance(self.camera_changes, (tuple, list)):
            raise ValueError('camera_changes must be a sequence of CameraChange, got '
                             f'{self.camera_changes!r}')
        changes = []
        for c in self.camera_changes:
            if isinstance(c, dict):
                c = CameraChange(**c)
            if not isinstance(c, CameraChange):
                raise ValueError(f'camera_changes must hold CameraChange or dicts, got {c!r}')
            changes.append(c)
        self.camera_changes = tuple(changes)
        if self.duration <= 2.0:
            raise ValueError(f'duration must be > 2 s, got {self.duration}')
        if self.camera_rate <= 0 or self.joint_rate <= 0:
            raise ValueError('camera_rate and joint_rate must be > 0')
        if self.error_model not in ERROR_MODELS:
            raise ValueError(f'error_model must be one of {ERROR_MODELS}, '
                             f'got {self.error_model!r}')
        if len(self.camera_names) < 1:
            raise ValueError('camera_names must name at least one camera')
        lat = np.asarray(self.stamp_latency, float).reshape(-1)
        if lat.size > len(self.camera_names) or not np.all(np.isfinite(lat)) or \
                np.any(np.abs(lat) > 1.0):
            raise ValueError(f'stamp_latency must give at most one latency per camera, each '
                             f'within 1 s, got {self.stamp_latency}')
        self.stamp_latency = tuple(float(v) for v in lat)
        if not (np.isfinite(self.joint_jitter) and self.joint_jitter >= 0.0):
            raise ValueError(f'joint_jitter must be >= 0 (s), got {self.joint_jitter}')
        if not 0.0 <= self.joint_drop < 1.0:
            raise ValueError(f'joint_drop must be in [0, 1), got {self.joint_drop}')
        if not (np.isfinite(self.rolling_shutter) and 0.0 <= self.rolling_shutter < 0.2):
            raise ValueError(f'rolling_shutter must be in [0, 0.2) s, got {self.rolling_shutter}')
        if not (np.isfinite(self.lens_k3) and abs(self.lens_k3) < 1.0):
            raise ValueError(f'lens_k3 must be within (-1, 1), got {self.lens_k3}')
        if not (np.isfinite(self.lens_tangential) and 0.0 <= self.lens_tangential < 0.02):
            raise ValueError(f'lens_tangential must be in [0, 0.02), got {self.lens_tangential}')
        if not (len(self.dwell) == 2 and 0.0 < self.dwell[0] <= self.dwell[1]):
            raise ValueError(f'dwell must be (shortest, longest) s with 0 < shortest <= longest, '
                             f'got {self.dwell}')

    def to_dict(self):
        """Plain dictionary (YAML-safe); ``camera_changes`` only when there are some."""
        def plain(v):
            if isinstance(v, (tuple, list)):
                return [plain(x) for x in v]
            if isinstance(v, dict):
                return {k: plain(x) for k, x in v.items()}
            if isinstance(v, (np.floating, np.integer)):
                return v.item()
            return v
        out = plain(asdict(self))
        if not out['camera_changes']:
            del out['camera_changes']
        return out


@dataclass
class DwellTruth:
    """Per dwell: times (ns, bag clock), held joint readings (D, n), true/nominal marker (D, 3)."""

    start_ns: np.ndarray
    end_ns: np.ndarray
    q: np.ndarray
    true_marker: np.ndarray
    nominal_marker: np.ndarray

    @property
    def stamp_ns(self):
        """Middle of each dwell."""
        return (self.start_ns + self.end_ns) // 2

    def __len__(self):
        """Return the number of dwells."""
        return len(self.start_ns)


@dataclass
class FrameTruth:
    """
    Per camera frame, in bag (receive) order.

    ``camera`` index into the cameras, ``stamp_ns`` the header stamp, ``exposure_ns`` the true
    middle of the exposure, ``log_ns`` the bag time, ``marker`` (F, 3) the true marker at
    mid-exposure, ``uv`` (F, 2) its projection (the truth a detector should find),
    ``occlusion`` one of OCCLUSION_NONE/LINK/RANDOM/OUTSIDE_IMAGE, ``visible`` = none.
    ``exposure_markers`` (F, K, 3) the marker over the exposure (for motion blur).
    """

    camera: np.ndarray
    stamp_ns: np.ndarray
    exposure_ns: np.ndarray
    log_ns: np.ndarray
    marker: np.ndarray
    uv: np.ndarray
    occlusion: np.ndarray
    exposure_markers: np.ndarray

    @property
    def visible(self):
        """Frames whose marker is in the image and unoccluded."""
        return self.occlusion == OCCLUSION_NONE

    def __len__(self):
        """Return the number of frames."""
        return len(self.stamp_ns)


@dataclass
class SimResult:
    """
    Everything :func:`simulate_cell` produced (see the module docstring).

    ``cameras`` are the cameras at the session start.  ``camera_epochs`` maps a camera index to
    its states [(start ns, Camera)], sorted, the first starting at ``start_ns``; each later
    one is the previous one changed (:class:`CameraChange`).  ``change_log`` lists the changes
    as applied, in time order (:func:`camera_epochs`).
    """

    scenario: str
    seed: int
    settings: SimSettings
    robot: TrueRobot
    cameras: list
    trajectory: Trajectory
    joint_names: List[str]            # published order, including extra joints
    joint_stamps_ns: np.ndarray       # (N,)
    joint_positions: np.ndarray       # (N, len(joint_names))
    joint_velocities: np.ndarray      # (N, len(joint_names))
    frames: FrameTruth
    dwells: DwellTruth
    start_ns: int = START_TIME_NS
    camera_epochs: dict = field(default_factory=dict)
    change_log: list = field(default_factory=list)
    #: Each camera's static scene behind the marker, drawn on first use (:meth:`render`).
    _clutter_cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __post_init__(self):
        if not self.camera_epochs:
            self.camera_epochs = {j: [(int(self.start_ns), c)] for j, c in enumerate(self.cameras)}

    def epoch_index(self, j, t_ns):
        """Return the index of camera ``j``'s epoch at bag time ``t_ns`` (0 before the first)."""
        starts = [start for start, _ in self.camera_epochs[j]]
        return max(0, bisect.bisect_right(starts, int(t_ns)) - 1)

    def camera_at(self, j, t_ns):
        """Return camera ``j`` as it is at bag time ``t_ns``."""
        return self.camera_epochs[j][self.epoch_index(j, t_ns)][1]

    @property
    def final_cameras(self):
        """Return the cameras at the end of the session."""
        return [self.camera_epochs[j][-1][1] for j in range(len(self.cameras))]

    @property
    def camera_set_epochs(self):
        """Return the distinct states of the whole camera set: [(start ns, [Camera])]."""
        starts = sorted({start for ep in self.camera_epochs.values() for start, _ in ep})
        return [(t, [self.camera_at(j, t) for j in range(len(self.cameras))]) for t in starts]

    @property
    def chain(self):
        """Return the nominal kinematic chain."""
        return self.robot.chain

    def render(self, i, encoding='mono8', sensor: Optional[SensorModel] = None, clean=False):
        """
        Render frame ``i`` as a uint8 image (mono8 (H, W) or rgb8/bgr8 (H, W, 3)).

        Deterministic per (seed, i).  ``clean`` renders the marker alone without noise,
        glints or occlusion (for tests of the geometry).
        """
        sensor = sensor or self.settings.sensor
        f = self.frames
        j = int(f.camera[i])
        epoch = self.epoch_index(j, f.exposure_ns[i])
        cam = self.camera_epochs[j][epoch][1]
        rng = np.random.default_rng([self.seed, 1009, int(i)])
        patches, occluders = [], []
        if clean or f.occlusion[i] in (OCCLUSION_NONE, OUTSIDE_IMAGE):
            centres = f.exposure_markers[i]
            if np.ptp(centres, axis=0).max() < 1e-7:
                centres = centres[:1]
            depth = cam.to_camera(centres[:1])[0, 2]
            blur = np.hypot(sensor.defocus_sigma,
                            sensor.defocus_slope * (depth - self._focus(cam)))
            hides = not clean and (sensor.clutter_level > 0 or sensor.clutter_spots > 0)
            got = marker_signal(cam, centres, self.settings.marker_radius, sensor,
                                0.0 if clean else blur, led_axis=self.led_axis(i, sensor),
                                with_alpha=hides)
            if got is not None:
                patches.append(got[:3])
                if hides:
                    occluders.append((got[0], got[1], got[3]))
        if not clean:
            patches += glint_patches(cam, rng, sensor, near_uv=f.uv[i])
        if clean:
            sensor = SensorModel(**{**asdict(sensor), 'read_noise': 0.0, 'gain': 1e9,
                                    'glint_rate': 0.0})
        background = None
        if not clean and (sensor.clutter_level > 0 or sensor.clutter_spots > 0):
            background = self._clutter(j, sensor, epoch)
        gain = 1.0 if clean else self.exposure_factor(i, sensor)
        if gain != 1.0:
            patches = [(u0, v0, gain * p) for u0, v0, p in patches]
            background = None if background is None else gain * background
        return expose(cam, patches, rng, sensor, encoding, background, occluders)

    def exposure_factor(self, i, sensor: Optional[SensorModel] = None):
        """
        Return frame ``i``'s auto-exposure factor (1 without ``sensor.exposure_steps``).

        Step k = floor(t / period) of camera j draws log-uniform in [1/F, F] from its own
        stream ``default_rng([seed, 3001, j, k])``.
        """
        sensor = sensor or self.settings.sensor
        if not sensor.exposure_steps:
            return 1.0
        period, largest = sensor.exposure_steps
        t = (int(self.frames.exposure_ns[i]) - START_TIME_NS) * 1e-9
        step = np.random.default_rng([self.seed, 3001, int(self.frames.camera[i]),
                                      int(t // period)])
        return float(np.exp(step.uniform(-1.0, 1.0) * np.log(largest)))

    def led_axis(self, i, sensor: Optional[SensorModel] = None):
        """
        Return the world direction an LED marker points at frame ``i`` (None without one).

        ``sensor.led_axis`` turned by the marker link's true orientation at mid-exposure
        (the arm's readings through its true joint angles and geometry).
        """
        sensor = sensor or self.settings.sensor
        if sensor.led_axis is None:
            return None
        t = (int(self.frames.exposure_ns[i]) - START_TIME_NS) * 1e-9
        q = self.robot.true_joint_angles(self.trajectory.positions(np.array([t])))
        R = self.robot.chain.fk_pose(q, self.robot.errors)[0, :3, :3]
        return R @ np.asarray(sensor.led_axis, float)

    def _clutter(self, j, sensor, epoch=0):
        """
        Return the static scene behind camera ``j`` in its epoch ``epoch`` (cached).

        Epoch 0's is drawn once per camera and sensor.  The scene is far compared with a
        knock's translation, so a later epoch sees it through the pure-rotation homography
        H = K_e R_e R_0^T K_0^-1 from epoch 0's image (R world-to-camera rotations, K camera
        matrices): a turn R_delta = R_e R_0^T gives K R_delta K^-1, a focus change K_e K_0^-1.
        """
        key = (j, epoch, sensor.clutter_level, sensor.clutter_spots, sensor.peak)
        if key not in self._clutter_cache:
            cam0 = self.camera_epochs[j][0][1]
            if epoch == 0:
                scene = clutter_scene(cam0.width, cam0.height, sensor,
                                      np.random.default_rng([self.seed, 2027, j]))
            else:
                cam = self.camera_epochs[j][epoch][1]
                H = cam.K @ cam.rotation @ cam0.rotation.T @ np.linalg.inv(cam0.K)
                scene = cv2.warpPerspective(self._clutter(j, sensor, 0), H,
                                            (cam0.width, cam0.height), flags=cv2.INTER_LINEAR,
                                            borderMode=cv2.BORDER_REPLICATE)
            self._clutter_cache[key] = scene
        return self._clutter_cache[key]

    def _focus(self, cam):
        """Return the depth in ``cam`` of the workspace centre, where the lens is focused."""
        centre = 0.5 * (np.asarray(self.settings.workspace_min) +
                        np.asarray(self.settings.workspace_max))
        return float(cam.to_camera(centre[None])[0, 2])

    def iter_images(self, encoding='mono8'):
        """Yield (frame index, camera name, image) in bag order."""
        for i in range(len(self.frames)):
            yield i, self.cameras[int(self.frames.camera[i])].name, self.render(i, encoding)


# ---- geometry helpers --------------------------------------------------------------------

def _segment_distance(p0, p1, q0, q1):
    """Smallest distance between segments [p0, p1] and [q0, q1], arrays (..., 3)."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.einsum('...i,...i', d1, d1)
    e = np.einsum('...i,...i', d2, d2)
    f = np.einsum('...i,...i', d2, r)
    c = np.einsum('...i,...i', d1, r)
    b = np.einsum('...i,...i', d1, d2)
    denom = a * e - b * b
    eps = 1e-12
    s = np.where(denom > eps, np.clip((b * f - c * e) / np.maximum(denom, eps), 0, 1), 0.0)
    t = np.where(e > eps, (b * s + f) / np.maximum(e, eps), 0.0)
    s = np.where(t < 0, np.where(a > eps, np.clip(-c / np.maximum(a, eps), 0, 1), 0.0), s)
    s = np.where(t > 1, np.where(a > eps, np.clip((b - c) / np.maximum(a, eps), 0, 1), 0.0), s)
    t = np.clip(t, 0, 1)
    diff = (p0 + d1 * s[..., None]) - (q0 + d2 * t[..., None])
    return np.linalg.norm(diff, axis=-1)


def link_occluded(chain, q, marker, camera_centre, link_radius, clearance):
    """
    Whether the arm's links hide ``marker`` (M, 3) from a camera centre (3,), for q (M, n).

    Links are capsules of ``link_radius`` between consecutive link-frame origins, starting at
    the base origin; the line of sight stops ``clearance`` short of the marker so the marker's
    own mount does not count.
    """
    q = np.atleast_2d(q)
    origins = chain.link_frames(q)[:, :, :3, 3]
    pts = np.concatenate([np.zeros((len(q), 1, 3)), origins], axis=1)
    sight = marker - camera_centre
    length = np.linalg.norm(sight, axis=1, keepdims=True)
    end = camera_centre + sight * (1.0 - clearance / length)
    start = np.broadcast_to(camera_centre, end.shape)
    hidden = np.zeros(len(q), bool)
    for k in range(pts.shape[1] - 1):
        hidden |= _segment_distance(start, end, pts[:, k], pts[:, k + 1]) < link_radius
    return hidden


def build_true_robot(chain, scenario, rng, s: SimSettings, q_sample, field_spec=None):
    """
    Return the true robot of ``scenario`` (:data:`SCENARIOS`, magnitudes from ``s``).

    Every error source is drawn, in the same order, whatever the scenario, so scenarios with
    the same seed share their draws; the scenario says which are used.  ``field_spec``
    overrides the scenario's bias field as (sigma m, coherence length m).
    """
    if scenario not in SCENARIOS:
        raise ValueError(f'scenario must be one of {sorted(SCENARIOS)}, got {scenario!r}')
    geometric, nongeometric, scenario_field = SCENARIOS[scenario]
    if field_spec is None:
        field_spec = scenario_field
    n = chain.n_joints
    errors = np.zeros(chain.n_errors)
    amp, phase, compliance = np.zeros((n, 2)), np.zeros((n, 2)), np.zeros(n)
    e = draw_geometric_errors(chain, rng, s.offset_deg, s.translation_mm, s.rotation_deg,
                              s.tip_translation_mm, s.error_model)
    a, p = draw_periodic(chain, rng, s.periodic_deg)
    c = draw_compliance(chain, rng, q_sample, s.compliance_deg)
    field_rng = np.random.default_rng(rng.integers(2 ** 63))
    if geometric:
        errors = e
    if nongeometric:
        amp, phase, compliance = a, p, c
    bias = None
    if field_spec is not None:
        bias = FourierBiasField(field_spec[0], field_spec[1], field_rng)
    return TrueRobot(chain, np.asarray(s.marker_offset, float), errors, amp, phase,
                     compliance, bias)


def load_chain(s: SimSettings):
    """Return the :class:`KinematicChain` of ``s``'s URDF (the bundled PUMA 560 by default)."""
    path = s.urdf_path or default_urdf_path()
    with open(path, encoding='utf-8') as f:
        return KinematicChain.from_urdf(f.read(), base_frame=s.base_frame,
                                        tip_link=s.marker_link)


def joint_ranges(chain, s: SimSettings):
    """Joint ranges (lower, upper) the trajectory samples from, radians."""
    n = chain.n_joints
    if s.joint_range_deg is not None and len(s.joint_range_deg) == n:
        lo, hi = np.radians(np.asarray(s.joint_range_deg, float)).T
        return lo, hi
    return np.maximum(chain.lower, -np.pi), np.minimum(chain.upper, np.pi)


def place_cameras(s: SimSettings, rng):
    """
    Draw the cell's cameras around the workspace.

    A camera behind the robot would look at the marker through the arm most of the time, so the
    ring is redrawn until every camera is on the workspace side of the base.
    """
    wmin, wmax = np.asarray(s.workspace_min, float), np.asarray(s.workspace_max, float)
    for _ in range(1000):
        cams = ring_of_cameras(len(s.camera_names), 0.5 * (wmin + wmax), rng,
                               distance=s.camera_distance, height=s.camera_height,
                               width=s.image_width, height_px=s.image_height, focal=s.focal,
                               names=list(s.camera_names))
        if all(c.center[0] > s.camera_min_x for c in cams):
            break
    return cams


def check_camera_changes(s: SimSettings):
    """Raise ValueError if a change of ``s`` names an unknown camera or is not in the session."""
    names = list(s.camera_names)
    for c in s.camera_changes:
        if c.camera not in names:
            raise ValueError(f'camera_changes: unknown camera {c.camera!r}; the cameras are '
                             f'{names}')
        if c.time_s >= s.duration:
            raise ValueError(f'camera_changes: time_s of the change of {c.camera!r} must be '
                             f'before the end of the session ({s.duration} s), got {c.time_s}')


def _unit(v):
    return v / np.linalg.norm(v)


def camera_epochs(cameras, changes, seed, start_ns=START_TIME_NS):
    """
    Return ({camera index: [(start ns, Camera)]}, change log) for ``changes`` of ``cameras``.

    Changes apply in time order, each on top of the camera's previous state; change k (its
    index in ``changes``) draws its rotation axis and translation direction, uniform on the
    sphere, from its own stream ``default_rng([seed, 4099, k])``.  Changes of one camera at
    the same nanosecond make one epoch.  The log has per change: camera, time_ns (bag time),
    time_s, rotation_deg, translation_mm, focal_percent, epoch (the index of the camera-set
    state it starts, :attr:`SimResult.camera_set_epochs`), rotation_axis and
    translation_direction (base frame).
    """
    names = [c.name for c in cameras]
    epochs = {j: [(int(start_ns), c)] for j, c in enumerate(cameras)}
    times = sorted({int(start_ns) + round(c.time_s * 1e9) for c in changes})
    log = []
    for k in sorted(range(len(changes)), key=lambda k: changes[k].time_s):
        change = changes[k]
        if change.camera not in names:
            raise ValueError(f'camera_changes: unknown camera {change.camera!r}; the cameras '
                             f'are {names}')
        j = names.index(change.camera)
        rng = np.random.default_rng([int(seed), 4099, k])
        axis, direction = _unit(rng.standard_normal(3)), _unit(rng.standard_normal(3))
        t_ns = int(start_ns) + round(change.time_s * 1e9)
        cam = change.apply(epochs[j][-1][1], axis, direction)
        if epochs[j][-1][0] == t_ns:
            epochs[j][-1] = (t_ns, cam)
        else:
            epochs[j].append((t_ns, cam))
        log.append({'camera': change.camera, 'time_ns': t_ns, 'time_s': change.time_s,
                    'rotation_deg': change.rotation_deg,
                    'translation_mm': change.translation_mm,
                    'focal_percent': change.focal_percent,
                    'epoch': 1 + times.index(t_ns),
                    'rotation_axis': [float(x) for x in axis],
                    'translation_direction': [float(x) for x in direction]})
    return epochs, log


def simulate_cell(scenario='geometric', seed=0, duration=None, settings=None, chain=None):
    """
    Simulate a cell; returns a :class:`SimResult` (no images are rendered until asked).

    ``scenario`` is one of :data:`SCENARIOS`; ``duration`` (s) overrides
    ``settings.duration``; ``chain`` overrides the URDF in the settings.
    """
    if scenario not in SCENARIOS:
        raise ValueError(f'scenario must be one of {sorted(SCENARIOS)}, got {scenario!r}')
    s = settings or SimSettings()
    if duration is not None:
        s = SimSettings(**{**s.__dict__, 'duration': float(duration)})
    check_camera_changes(s)
    seed = int(seed)
    rng = np.random.default_rng(seed)
    chain = chain or load_chain(s)
    n = chain.n_joints
    lo, hi = joint_ranges(chain, s)
    hop = np.radians(np.resize(np.asarray(s.hop_sigma_deg, float), n))
    wmin, wmax = np.asarray(s.workspace_min, float), np.asarray(s.workspace_max, float)
    point = np.asarray(s.marker_offset, float)
    cams = place_cameras(s, rng)
    if s.lens_k3 or s.lens_tangential:
        for j, cam in enumerate(cams):
            lens = np.random.default_rng([seed, 6007, j])
            cam.dist = np.array(cam.dist, float)
            if s.lens_k3:
                cam.dist[4] = s.lens_k3 * lens.uniform(0.8, 1.2)
            if s.lens_tangential:
                cam.dist[2:4] = lens.normal(0.0, s.lens_tangential, 2)

    def valid(q, need=len(cams)):
        q = np.atleast_2d(q)
        x = chain.fk(q, point)
        ok = np.all((x >= wmin) & (x <= wmax), axis=1)
        n_clear = np.zeros(len(q), int)
        for cam in cams:
            uv = cam.project(x)
            inside = cam.in_front(x) & (uv[:, 0] >= s.image_margin) \
                & (uv[:, 0] <= cam.width - 1 - s.image_margin) \
                & (uv[:, 1] >= s.image_margin) & (uv[:, 1] <= cam.height - 1 - s.image_margin)
            ok &= inside
            n_clear += ~link_occluded(chain, q, x, cam.center, s.link_radius,
                                      s.occlusion_clearance)
        return ok & (n_clear >= need)

    def uniform_valid(rng, tries=20000):
        for _ in range(tries // 200):
            cand = rng.uniform(lo, hi, (200, n))
            good = np.flatnonzero(valid(cand))
            if len(good):
                return cand[good[0]]
        raise RuntimeError('no joint configuration puts the marker in the workspace and in '
                           'view of the cameras; check workspace and joint ranges')

    def sample_target(rng, q):
        need = len(cams)
        if rng.random() < s.partial_view_probability:
            need = min(2, len(cams))
        if rng.random() >= s.far_jump_probability:
            cand = np.clip(q + rng.standard_normal((50, n)) * hop, lo, hi)
            good = np.flatnonzero(valid(cand, need))
            if len(good):
                return cand[good[0]]
        return uniform_valid(rng)

    q_sample = rng.uniform(lo, hi, (500, n))
    robot = build_true_robot(chain, scenario, rng, s, q_sample)
    speed = np.where(np.isfinite(chain.velocity_limits), chain.velocity_limits, 2.0)
    traj = teleop_trajectory(sample_target, uniform_valid(rng), s.duration, rng,
                             speed * s.speed_fraction, dwell=s.dwell,
                             min_move_time=s.min_move_time)
    T = min(traj.duration, s.duration)

    # joint states on the control clock
    t_js = np.arange(0.0, T, 1.0 / s.joint_rate)
    q_js = traj.positions(t_js)
    qd_js = traj.velocities(t_js)
    extra = list(s.extra_joints)
    order = rng.permutation(n + len(extra))
    names_all = list(chain.joint_names) + extra
    pub_names = [names_all[i] for i in order]
    grip = 0.02 + 0.01 * np.sin(2 * np.pi * t_js / 17.0)
    pos_all = np.column_stack([q_js] + [grip] * len(extra))
    vel_all = np.column_stack([qd_js] + [np.zeros_like(grip)] * len(extra))
    js_stamps = START_TIME_NS + np.round(t_js * 1e9).astype(np.int64)
    if s.joint_jitter > 0.0 or s.joint_drop > 0.0:
        # Their own random stream: every other draw stays as without them.
        rng_js = np.random.default_rng([seed, 5527])
        js_stamps = js_stamps + np.round(rng_js.normal(0.0, s.joint_jitter, len(js_stamps))
                                         * 1e9).astype(np.int64)
        keep = np.flatnonzero(rng_js.random(len(js_stamps)) >= s.joint_drop)
        keep = keep[np.argsort(js_stamps[keep], kind='stable')]   # published in stamp order
        js_stamps, pos_all, vel_all = js_stamps[keep], pos_all[keep], vel_all[keep]

    # camera clocks
    sens = s.sensor
    K = max(1, int(sens.motion_samples))
    offsets = (np.linspace(-0.5, 0.5, K) if K > 1 else np.zeros(1)) * sens.exposure
    rows = []
    for j, cam in enumerate(cams):
        period = (1.0 / s.camera_rate) * (1.0 + rng.uniform(-1, 1) * s.camera_clock_ppm * 1e-6)
        t_exp = rng.uniform(0.0, period) + np.arange(0.0, T, period)
        t_exp = t_exp[(t_exp > 0.1) & (t_exp < T - 0.1)]
        stamp = t_exp + rng.normal(0.0, s.stamp_jitter, len(t_exp))
        if j < len(s.stamp_latency):
            stamp = stamp + s.stamp_latency[j]
        log = t_exp + 0.5 * sens.exposure + rng.uniform(*s.image_latency, len(t_exp))
        # random occlusion spans
        hidden = np.zeros(len(t_exp), bool)
        t = rng.exponential(1.0 / s.occlusion_rate) if s.occlusion_rate > 0 else np.inf
        while t < T:
            d = rng.uniform(*s.occlusion_duration)
            hidden |= (t_exp >= t) & (t_exp <= t + d)
            t += d + rng.exponential(1.0 / s.occlusion_rate)
        rows.append((np.full(len(t_exp), j), t_exp, stamp, log, hidden))
    cam_idx = np.concatenate([r[0] for r in rows]).astype(np.int64)
    t_exp = np.concatenate([r[1] for r in rows])
    stamp = np.concatenate([r[2] for r in rows])
    log = np.concatenate([r[3] for r in rows])
    hidden = np.concatenate([r[4] for r in rows])
    sort = np.argsort(log, kind='stable')
    cam_idx, t_exp, stamp, log, hidden = (a[sort] for a in (cam_idx, t_exp, stamp, log, hidden))

    to_ns = (lambda t: START_TIME_NS + np.round(t * 1e9).astype(np.int64))
    exposure_ns = to_ns(t_exp)
    epochs, change_log = camera_epochs(cams, s.camera_changes, seed)

    effects = arm_effects(traj, s.backlash_deg, s.repeatability_mm, s.settle_mm, s.settle_hz,
                          s.settle_tau, seed)

    def markers(t_mid):
        """Return (x_all (F, K, 3), x_mid (F, 3), q_mid) of exposures centred at t_mid."""
        t_all = (t_mid[:, None] + offsets[None, :]).reshape(-1)
        q_all, q_mid = traj.positions(t_all), traj.positions(t_mid)
        if effects is None:
            return robot.marker(q_all).reshape(len(t_mid), K, 3), robot.marker(q_mid), q_mid
        x_all = (robot.marker(effects.link_joints(q_all, t_all)) +
                 effects.displacement(t_all)).reshape(len(t_mid), K, 3)
        x_mid = robot.marker(effects.link_joints(q_mid, t_mid)) + effects.displacement(t_mid)
        return x_all, x_mid, q_mid

    def project(x_mid, q_mid):
        """Return (uv, occlusion codes) of every frame's marker in its camera's epoch."""
        uv = np.zeros((len(x_mid), 2))
        occ = np.zeros(len(x_mid), np.int8)
        for j in range(len(cams)):
            starts = np.array([start for start, _ in epochs[j]], np.int64)
            which = np.maximum(np.searchsorted(starts, exposure_ns, side='right') - 1, 0)
            for e, (_, cam) in enumerate(epochs[j]):
                m = (cam_idx == j) & (which == e)
                if not np.any(m):
                    continue
                uv[m] = cam.project(x_mid[m])
                out = ~cam.in_front(x_mid[m]) | (uv[m, 0] < -0.5) | (uv[m, 1] < -0.5) \
                    | (uv[m, 0] > cam.width - 0.5) | (uv[m, 1] > cam.height - 0.5)
                by_link = link_occluded(chain, q_mid[m], robot.nominal_marker(q_mid[m]),
                                        cam.center, s.link_radius, s.occlusion_clearance)
                code = np.where(hidden[m], OCCLUSION_RANDOM, OCCLUSION_NONE)
                code = np.where(by_link, OCCLUSION_LINK, code)
                occ[m] = np.where(out, OUTSIDE_IMAGE, code)
        return uv, occ

    x_all, x_mid, q_mid = markers(t_exp)
    uv, occ = project(x_mid, q_mid)
    if s.rolling_shutter > 0.0:
        # Row v is exposed (v / (H - 1) - 1/2) x readout after the frame's middle row: the
        # marker is where the arm was when its own row was read (two passes: the row depends
        # on where the marker is, by a fraction of a pixel at the second).
        height = np.array([c.height for c in cams], float)[cam_idx]
        for _ in range(2):
            row = np.clip(uv[:, 1], 0.0, height - 1.0) / (height - 1.0) - 0.5
            x_all, x_mid, q_mid = markers(t_exp + row * s.rolling_shutter)
            uv, occ = project(x_mid, q_mid)
    frames = FrameTruth(cam_idx, to_ns(stamp), exposure_ns, to_ns(log), x_mid, uv, occ, x_all)

    spans = traj.dwells()
    spans = spans[spans[:, 0] < T]
    spans[:, 1] = np.minimum(spans[:, 1], T)
    q_d = traj.dwell_knots()[:len(spans)]
    true_d = robot.marker(q_d)
    if effects is not None:
        # Where each stop really rests: the links behind the play, off by the stop's
        # repeatability (the ring-down has decayed).
        mid = 0.5 * (spans[:, 0] + spans[:, 1])
        true_d = robot.marker(effects.link_joints(q_d, mid)) + effects.resting_offset(mid)
    dwells = DwellTruth(to_ns(spans[:, 0]), to_ns(spans[:, 1]), q_d, true_d,
                        robot.nominal_marker(q_d))
    return SimResult(scenario, seed, s, robot, cams, traj, pub_names, js_stamps,
                     np.ascontiguousarray(pos_all[:, order]),
                     np.ascontiguousarray(vel_all[:, order]), frames, dwells,
                     camera_epochs=epochs, change_log=change_log)


__all__ = ['SCENARIOS', 'CameraChange', 'SimSettings', 'SimResult', 'DwellTruth', 'FrameTruth',
           'simulate_cell', 'link_occluded', 'default_urdf_path', 'OCCLUSION_NONE',
           'OCCLUSION_LINK', 'OCCLUSION_RANDOM', 'OUTSIDE_IMAGE', 'camera_epochs',
           'check_camera_changes']
