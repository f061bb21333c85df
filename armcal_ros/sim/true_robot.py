"""
The "true" robot of a simulated cell: the nominal URDF chain plus the errors a real arm has.

The calibrator only knows the nominal chain; the simulator moves the marker with this one.  For
joint readings q (what the encoders report and JointState carries) the true marker position is::

    q_true = q + dq_periodic(q) + dq_compliance(q)
    X_true = FK(q_true; point, e_geometric) + b(FK_nominal(q))

Error sources and the magnitudes drawn by default (each a zero-mean Gaussian with this standard
deviation unless said otherwise), chosen to be typical of a mid-size industrial arm before
calibration, whose absolute accuracy is of the order of a millimetre while its repeatability is
a few hundredths (ISO 9283 figures; Mooring, Roth and Driels, "Fundamentals of Manipulator
Calibration", 1991; Corke and Armstrong-Helouvry's PUMA 560 survey):

- geometric (the chain's error vector, see :mod:`armcal_ros.robot.kinematics`): per joint an
  angle offset of 0.05 deg (encoder zeroing / home-position error), origin translations of
  0.3 mm per axis (machining and assembly tolerances of link lengths and offsets), origin
  rotations of 0.03 deg per axis (twist and parallelism errors of the joint axes); and the
  marker mount (the tip block) 0.2 mm per axis, as a turned adapter on the flange would be.
  That is error model ``joint-origin`` (the default, :data:`ERROR_MODELS`).  Model ``dh`` has
  Denavit-Hartenberg errors instead (per joint an angle offset, link-length errors of a and d,
  and a twist error of alpha; ``--error-model dh`` of the accuracy benchmark): for a URDF
  written from standard DH, where joint i+1's origin in link i is Tz(d_i) Tx(a_i) Rx(alpha_i)
  (the bundled PUMA 560), these are the origin's x and z translations and its x rotation; the
  first joint's origin is the base frame itself (DH frame 0) and carries no error.  Its draws
  are those of ``joint-origin`` with the other components set to zero, so a seed gives the
  same cell.
- periodic joint-angle errors: per joint a sum of a one-cycle-per-revolution term (gear or
  encoder eccentricity) and a two-cycles term (encoder ellipticity, harmonic-drive
  kinematic error), dq = A1 sin(q + phi1) + A2 sin(2 q + phi2), amplitudes uniform in
  [0.01, 0.025] deg and phases uniform: the size of the transmission errors measured on
  industrial gear trains.
- gravity compliance: each joint deflects by dq_k = tau_k(q) / K_k under the gravity torque
  tau_k from the URDF's link masses and centres of mass (``KinematicChain.gravity_torques``).
  The stiffnesses K_k are set so that the shoulder (the most loaded joint) deflects by about
  0.02 deg at the largest gravity torque it meets in the workspace (for the PUMA 560's
  44 N m that is K ~ 1.3e5 N m/rad, the range reported for arms of its class), and scale with
  each joint's rated effort (smaller drives are softer); each is then multiplied by a random
  factor in [0.7, 1.3].
- a bias field b: a smooth random vector field
  (:class:`~armcal_ros.sim.bias_field.FourierBiasField`), evaluated at the nominal marker
  position; used by the ``gp-prior`` and ``mixed`` scenarios.
"""

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

DEG = np.pi / 180.0

#: Default error magnitudes (see the module docstring).
ERROR_MAGNITUDES = {
    'offset_deg': 0.05,
    'translation_mm': 0.3,
    'rotation_deg': 0.03,
    'tip_translation_mm': 0.2,
    'periodic_deg': (0.01, 0.025),
    'compliance_deg': 0.02,
}


@dataclass
class TrueRobot:
    """
    The true kinematics of a simulated arm (see the module docstring).

    ``chain`` is the nominal :class:`~armcal_ros.robot.kinematics.KinematicChain` (tip = the
    marker link), ``point`` the marker centre in the tip frame, ``errors`` the geometric error
    vector (``chain.error_names``), ``periodic_amplitude``/``periodic_phase`` (n, 2) in radians
    for 1 and 2 cycles per revolution, ``compliance`` (n,) rad/(N m), ``bias_field`` an optional
    callable (N, 3) -> (N, 3) in metres.
    """

    chain: object
    point: np.ndarray
    errors: np.ndarray
    periodic_amplitude: np.ndarray
    periodic_phase: np.ndarray
    compliance: np.ndarray
    bias_field: Optional[Callable] = None
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))

    def __post_init__(self):
        n = self.chain.n_joints
        self.point = np.asarray(self.point, float).reshape(3)
        self.errors = np.asarray(self.errors, float).reshape(-1)
        if self.errors.shape != (self.chain.n_errors,):
            raise ValueError(f'errors must have shape ({self.chain.n_errors},), '
                             f'got {self.errors.shape}')
        self.periodic_amplitude = np.asarray(self.periodic_amplitude, float).reshape(n, 2)
        self.periodic_phase = np.asarray(self.periodic_phase, float).reshape(n, 2)
        self.compliance = np.asarray(self.compliance, float).reshape(n)

    def periodic_error(self, q):
        """Periodic joint-angle errors (M, n) at joint readings q (M, n), radians."""
        q = np.atleast_2d(np.asarray(q, float))
        a, p = self.periodic_amplitude, self.periodic_phase
        return a[:, 0] * np.sin(q + p[:, 0]) + a[:, 1] * np.sin(2.0 * q + p[:, 1])

    def compliance_error(self, q):
        """Gravity deflection of each joint (M, n) at joint readings q, radians."""
        q = np.atleast_2d(np.asarray(q, float))
        if not np.any(self.compliance):
            return np.zeros_like(q)
        return self.chain.gravity_torques(q, self.gravity, self.errors) * self.compliance

    def true_joint_angles(self, q):
        """Joint angles the arm really has when its encoders read q."""
        q = np.atleast_2d(np.asarray(q, float))
        return q + self.periodic_error(q) + self.compliance_error(q)

    def nominal_marker(self, q):
        """Marker position (M, 3) by the nominal model, as the calibrator computes it."""
        return self.chain.fk(np.atleast_2d(q), self.point)

    def marker(self, q):
        """Return the true marker position (M, 3) for joint readings q (M, n)."""
        q = np.atleast_2d(np.asarray(q, float))
        x = self.chain.fk(self.true_joint_angles(q), self.point, self.errors)
        if self.bias_field is not None:
            x = x + self.bias_field(self.nominal_marker(q))
        return x

    def describe(self):
        """Return the true error parameters (radians, metres) as a dict for robot_errors.yaml."""
        c = self.chain
        return {
            'units': 'radians and metres; compliance in rad/(N m)',
            'marker_point_in_tip': [float(v) for v in self.point],
            'tip_link': c.tip_link,
            'geometric_errors': {n: float(v) for n, v in zip(c.error_names, self.errors)},
            'periodic': {
                j: {'amplitude_1': float(a[0]), 'phase_1': float(p[0]),
                    'amplitude_2': float(a[1]), 'phase_2': float(p[1])}
                for j, a, p in zip(c.joint_names, self.periodic_amplitude, self.periodic_phase)},
            'compliance': {j: float(v) for j, v in zip(c.joint_names, self.compliance)},
            'gravity': [float(v) for v in self.gravity],
            'bias_field': self.bias_field is not None,
        }


#: Geometric error models of the simulator (module docstring).
ERROR_MODELS = ('joint-origin', 'dh')
#: Joint-origin error components the ``dh`` model draws (besides the joint's angle offset).
DH_FIELDS = ('offset', 'tx', 'tz', 'rx')


def geometric_error_sigmas(chain, offset_deg=0.05, translation_mm=0.3, rotation_deg=0.03,
                           tip_translation_mm=0.2, model='joint-origin'):
    """Return the standard deviations of the chain's geometric errors under ``model``."""
    if model not in ERROR_MODELS:
        raise ValueError(f'error model must be one of {ERROR_MODELS}, got {model!r}')
    sigma = chain.error_vector(offset=offset_deg * DEG, translation=translation_mm * 1e-3,
                               rotation=rotation_deg * DEG,
                               tip_translation=tip_translation_mm * 1e-3, tip_rotation=0.0)
    if model == 'dh':
        first = chain.joint_names[0]
        for i, name in enumerate(chain.error_names):
            joint, comp = name.rsplit('/', 1)
            if joint in chain.joint_names and comp not in DH_FIELDS:
                sigma[i] = 0.0
            elif joint == first and comp != 'offset':
                sigma[i] = 0.0
    return sigma


def draw_geometric_errors(chain, rng, offset_deg=0.05, translation_mm=0.3, rotation_deg=0.03,
                          tip_translation_mm=0.2, model='joint-origin'):
    """Draw a geometric error vector (Gaussian, :func:`geometric_error_sigmas`)."""
    sigma = geometric_error_sigmas(chain, offset_deg, translation_mm, rotation_deg,
                                   tip_translation_mm, model)
    return rng.standard_normal(chain.n_errors) * sigma


def draw_periodic(chain, rng, amplitude_deg=(0.01, 0.025)):
    """Draw periodic-error amplitudes and phases, each (n, 2), radians."""
    lo, hi = amplitude_deg
    amp = rng.uniform(lo, hi, (chain.n_joints, 2)) * DEG
    phase = rng.uniform(0.0, 2.0 * np.pi, (chain.n_joints, 2))
    return amp, phase


def joint_efforts(chain):
    """Rated efforts of the chain's movable joints from the URDF (inf where not given)."""
    if hasattr(chain, 'effort_limits'):
        return np.asarray(chain.effort_limits, float)
    joints = [j for j in chain.model.chain(chain.base_frame, chain.tip_link) if j.movable]
    return np.array([j.effort for j in joints], float)


def draw_compliance(chain, rng, q_sample, compliance_deg=0.02, gravity=(0.0, 0.0, -9.81)):
    """
    Draw joint compliances (n,) in rad/(N m).

    The most loaded joint over ``q_sample`` (M, n) deflects by ``compliance_deg`` at its
    largest gravity torque; other joints' stiffnesses scale with their rated efforts (equal if
    the URDF gives none); each is multiplied by a random factor in [0.7, 1.3].
    """
    tau = np.abs(chain.gravity_torques(np.atleast_2d(q_sample), gravity)).max(axis=0)
    k_ref = int(np.argmax(tau))
    if tau[k_ref] <= 0:
        return np.zeros(chain.n_joints)
    effort = joint_efforts(chain)
    if not np.all(np.isfinite(effort)) or np.any(effort <= 0):
        effort = np.ones(chain.n_joints)
    c_ref = compliance_deg * DEG / tau[k_ref]
    return c_ref * effort[k_ref] / effort * rng.uniform(0.7, 1.3, chain.n_joints)
