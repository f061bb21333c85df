"""
Parse a URDF (the ``robot_description`` convention) into plain dataclasses.

Only what forward kinematics and a gravity model need is kept: links with their mass and
centre of mass, joints with type, parent, child, origin, axis and limits.  Visual and
collision geometry, transmissions and Gazebo tags are ignored.

URDF conventions used here (http://wiki.ros.org/urdf/XML):

- A joint's ``<origin xyz rpy>`` is the pose of the joint frame in the parent link frame,
  T = [R | xyz] with R = Rz(yaw) Ry(pitch) Rx(roll) (fixed-axis roll, pitch, yaw).
  The child link frame is the joint frame moved by the joint motion: a rotation by q about
  ``axis`` (revolute, continuous) or a translation by q along ``axis`` (prismatic).
- ``<axis xyz>`` defaults to (1, 0, 0) and is normalised here; a zero axis is an error.
- ``<limit lower upper velocity effort>`` is required for revolute and prismatic joints
  (lower and upper default to 0 as the URDF specification says).  Continuous joints have no
  position limits: lower = -inf, upper = +inf.
- ``<inertial><origin xyz rpy/><mass value/><inertia .../></inertial>``: the inertial origin
  xyz is the centre of mass in the link frame; the inertia tensor is returned about the centre
  of mass in link-frame axes, R I R^T.  A link without ``<inertial>`` has zero mass.

Joint types ``floating`` and ``planar`` are parsed and recorded but are not supported by the
kinematic chain: ``UrdfModel.chain`` raises a ValueError naming the joint if a chain crosses
one, so URDFs with, for example, a planar mobile base elsewhere still load.  Any other type
is a parse error.
"""

from dataclasses import dataclass, field
from typing import Dict, List, Optional
import xml.etree.ElementTree as ET

import numpy as np
from scipy.spatial.transform import Rotation

JOINT_TYPES = ('revolute', 'continuous', 'prismatic', 'fixed', 'floating', 'planar')
SUPPORTED_JOINT_TYPES = ('revolute', 'continuous', 'prismatic', 'fixed')
MOVABLE_JOINT_TYPES = ('revolute', 'continuous', 'prismatic')


def rpy_to_matrix(rpy):
    """Rotation matrix of URDF roll-pitch-yaw angles: Rz(yaw) Ry(pitch) Rx(roll)."""
    return Rotation.from_euler('xyz', np.asarray(rpy, float)).as_matrix()


def origin_matrix(xyz=(0.0, 0.0, 0.0), rpy=(0.0, 0.0, 0.0)):
    """Return the 4x4 homogeneous transform [Rz(y) Ry(p) Rx(r) | xyz] of a URDF origin."""
    T = np.eye(4)
    T[:3, :3] = rpy_to_matrix(rpy)
    T[:3, 3] = np.asarray(xyz, float)
    return T


@dataclass(frozen=True)
class UrdfLink:
    """
    A link: its name and inertial data.

    ``com`` is the centre of mass in the link frame (metres); ``inertia`` the 3x3 inertia
    tensor about the centre of mass in link-frame axes (kg m^2); both zero without
    ``<inertial>``.
    """

    name: str
    mass: float = 0.0
    com: np.ndarray = field(default_factory=lambda: np.zeros(3))
    inertia: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


@dataclass(frozen=True)
class UrdfJoint:
    """
    A joint: type, the links it connects, its origin transform, axis and limits.

    ``origin`` is the 4x4 pose of the joint frame in the parent link frame; ``axis`` a unit
    3-vector in the joint frame.  ``lower``/``upper`` are radians (revolute) or metres
    (prismatic), -inf/+inf for continuous joints and 0/0 for fixed ones.  ``velocity`` and
    ``effort`` are inf when not given.  ``mimic`` names the joint this one mimics, if any.
    """

    name: str
    type: str
    parent: str
    child: str
    origin: np.ndarray
    axis: np.ndarray
    lower: float = 0.0
    upper: float = 0.0
    velocity: float = float('inf')
    effort: float = float('inf')
    mimic: Optional[str] = None

    @property
    def movable(self) -> bool:
        """Tell whether the joint moves (revolute, continuous or prismatic)."""
        return self.type in MOVABLE_JOINT_TYPES


@dataclass
class UrdfModel:
    """A parsed robot: links and joints by name, in document order."""

    name: str
    links: Dict[str, UrdfLink]
    joints: Dict[str, UrdfJoint]

    def __post_init__(self):
        self._parent_joint = {j.child: j for j in self.joints.values()}

    @property
    def root_link(self) -> str:
        """Name of the link that is no joint's child."""
        roots = [name for name in self.links if name not in self._parent_joint]
        return roots[0]

    def parent_joint(self, link: str) -> Optional[UrdfJoint]:
        """Return the joint whose child is ``link``, or None for the root."""
        if link not in self.links:
            raise ValueError(f'link {link!r} is not in robot {self.name!r}')
        return self._parent_joint.get(link)

    def child_joints(self, link: str) -> List[UrdfJoint]:
        """Return the joints whose parent is ``link``, in document order."""
        return [j for j in self.joints.values() if j.parent == link]

    def chain(self, base: str, tip: str) -> List[UrdfJoint]:
        """
        Return the joints from link ``base`` down to link ``tip``, base first.

        Raises ValueError if either link is missing, if ``tip`` is not a descendant of
        ``base``, or if the chain crosses a floating or planar joint.
        """
        for role, link in (('base frame', base), ('tip link', tip)):
            if link not in self.links:
                raise ValueError(f'{role} {link!r} is not a link of robot {self.name!r} '
                                 f'(links: {", ".join(self.links)})')
        joints = []
        link = tip
        while link != base:
            joint = self._parent_joint.get(link)
            if joint is None:
                raise ValueError(f'no kinematic chain from {base!r} to {tip!r} in robot '
                                 f'{self.name!r}: {tip!r} is not a descendant of {base!r}')
            joints.append(joint)
            link = joint.parent
        joints.reverse()
        for joint in joints:
            if joint.type not in SUPPORTED_JOINT_TYPES:
                raise ValueError(f'joint {joint.name!r} between {base!r} and {tip!r} has '
                                 f'type {joint.type!r}; only {SUPPORTED_JOINT_TYPES} are '
                                 'supported in a kinematic chain')
            if joint.mimic is not None:
                raise ValueError(f'joint {joint.name!r} between {base!r} and {tip!r} mimics '
                                 f'{joint.mimic!r}; mimic joints are not supported in a chain')
        return joints


def _floats(text, n, what):
    try:
        values = [float(v) for v in text.split()]
    except ValueError:
        raise ValueError(f'{what} must be {n} numbers, got {text!r}') from None
    if len(values) != n or not np.all(np.isfinite(values)):
        raise ValueError(f'{what} must be {n} finite numbers, got {text!r}')
    return np.array(values)


def _float_attr(elem, key, default, what):
    text = elem.get(key)
    if text is None:
        return default
    try:
        return float(text)
    except ValueError:
        raise ValueError(f'{what} {key} must be a number, got {text!r}') from None


def _origin(elem, what):
    """Return (xyz, rpy) of an optional ``<origin>`` child (identity if absent)."""
    origin = elem.find('origin')
    if origin is None:
        return np.zeros(3), np.zeros(3)
    xyz = _floats(origin.get('xyz', '0 0 0'), 3, f'{what} origin xyz')
    rpy = _floats(origin.get('rpy', '0 0 0'), 3, f'{what} origin rpy')
    return xyz, rpy


def _parse_link(elem) -> UrdfLink:
    name = elem.get('name')
    if not name:
        raise ValueError('a <link> has no name attribute')
    inertial = elem.find('inertial')
    if inertial is None:
        return UrdfLink(name)
    what = f'link {name!r} inertial'
    xyz, rpy = _origin(inertial, what)
    mass_elem = inertial.find('mass')
    mass = 0.0 if mass_elem is None else _float_attr(mass_elem, 'value', 0.0, f'{what} mass')
    if not np.isfinite(mass) or mass < 0:
        raise ValueError(f'{what} mass must be finite and >= 0, got {mass}')
    inertia = np.zeros((3, 3))
    ie = inertial.find('inertia')
    if ie is not None:
        keys = ('ixx', 'ixy', 'ixz', 'iyy', 'iyz', 'izz')
        ixx, ixy, ixz, iyy, iyz, izz = (_float_attr(ie, k, 0.0, f'{what} inertia') for k in keys)
        local = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
        R = rpy_to_matrix(rpy)
        inertia = R @ local @ R.T
    return UrdfLink(name, mass, xyz, inertia)


def _parse_joint(elem) -> UrdfJoint:
    name = elem.get('name')
    if not name:
        raise ValueError('a <joint> has no name attribute')
    jtype = elem.get('type')
    if jtype not in JOINT_TYPES:
        raise ValueError(f'joint {name!r} has type {jtype!r}; expected one of {JOINT_TYPES}')
    ends = {}
    for tag in ('parent', 'child'):
        sub = elem.find(tag)
        if sub is None or not sub.get('link'):
            raise ValueError(f'joint {name!r} has no <{tag} link="..."/>')
        ends[tag] = sub.get('link')
    xyz, rpy = _origin(elem, f'joint {name!r}')
    axis = np.array([1.0, 0.0, 0.0])
    axis_elem = elem.find('axis')
    if axis_elem is not None and jtype != 'fixed':
        axis = _floats(axis_elem.get('xyz', '1 0 0'), 3, f'joint {name!r} axis xyz')
        norm = np.linalg.norm(axis)
        if norm < 1e-12:
            raise ValueError(f'joint {name!r} axis must be non-zero, got {axis.tolist()}')
        axis = axis / norm
    lower, upper = 0.0, 0.0
    velocity = effort = float('inf')
    limit = elem.find('limit')
    what = f'joint {name!r} limit'
    if limit is not None:
        velocity = _float_attr(limit, 'velocity', velocity, what)
        effort = _float_attr(limit, 'effort', effort, what)
    if jtype in ('revolute', 'prismatic'):
        if limit is None:
            raise ValueError(f'{jtype} joint {name!r} has no <limit> (required by URDF)')
        lower = _float_attr(limit, 'lower', 0.0, what)
        upper = _float_attr(limit, 'upper', 0.0, what)
        if not lower <= upper:
            raise ValueError(f'{what}: lower ({lower}) must be <= upper ({upper})')
    elif jtype == 'continuous':
        lower, upper = -np.inf, np.inf
    mimic_elem = elem.find('mimic')
    mimic = None if mimic_elem is None else mimic_elem.get('joint')
    return UrdfJoint(name, jtype, ends['parent'], ends['child'], origin_matrix(xyz, rpy), axis,
                     lower, upper, velocity, effort, mimic)


def parse_urdf(text: str) -> UrdfModel:
    """
    Parse URDF XML text into a UrdfModel.

    Raises ValueError for text that is not well-formed XML, a root element other than
    ``<robot>``, missing or duplicate names, unknown joint types, malformed numbers, joints
    that reference missing links, a link with two parent joints, or a tree without a single
    root.
    """
    if not isinstance(text, (str, bytes)):
        raise ValueError(f'URDF text must be str or bytes, got {type(text).__name__}')
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise ValueError(f'URDF is not well-formed XML: {exc}') from None
    if root.tag != 'robot':
        raise ValueError(f'URDF root element must be <robot>, got <{root.tag}>')
    robot_name = root.get('name', '')
    links: Dict[str, UrdfLink] = {}
    for elem in root.findall('link'):
        link = _parse_link(elem)
        if link.name in links:
            raise ValueError(f'link {link.name!r} is defined twice')
        links[link.name] = link
    if not links:
        raise ValueError(f'robot {robot_name!r} has no <link>')
    joints: Dict[str, UrdfJoint] = {}
    children: Dict[str, str] = {}
    for elem in root.findall('joint'):
        joint = _parse_joint(elem)
        if joint.name in joints:
            raise ValueError(f'joint {joint.name!r} is defined twice')
        for role, link in (('parent', joint.parent), ('child', joint.child)):
            if link not in links:
                raise ValueError(f'joint {joint.name!r} {role} link {link!r} is not defined')
        if joint.child in children:
            raise ValueError(f'link {joint.child!r} is the child of two joints: '
                             f'{children[joint.child]!r} and {joint.name!r}')
        children[joint.child] = joint.name
        joints[joint.name] = joint
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise ValueError(f'robot {robot_name!r} must have exactly one root link (a link that '
                         f'is no joint\'s child), found {len(roots)}: {roots}')
    reached, frontier = {roots[0]}, [roots[0]]
    while frontier:
        link = frontier.pop()
        for joint in joints.values():
            if joint.parent == link and joint.child not in reached:
                reached.add(joint.child)
                frontier.append(joint.child)
    if len(reached) != len(links):
        raise ValueError(f'robot {robot_name!r}: links {sorted(set(links) - reached)} are not '
                         f'connected to the root link {roots[0]!r} (a cycle?)')
    for joint in joints.values():
        if joint.mimic is not None and joint.mimic not in joints:
            raise ValueError(f'joint {joint.name!r} mimics unknown joint {joint.mimic!r}')
    return UrdfModel(robot_name, links, joints)


def load_urdf(path) -> UrdfModel:
    """Read and parse a URDF file (see ``parse_urdf``)."""
    with open(path, 'r', encoding='utf-8') as f:
        return parse_urdf(f.read())
