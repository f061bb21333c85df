"""Tests of the serial-chain forward kinematics, Jacobians and error parameters."""

from pathlib import Path

import numpy as np
import pytest

from armcal_ros.robot import KinematicChain, load_urdf

URDF_DIR = Path(__file__).resolve().parents[1] / 'urdf'
PUMA = URDF_DIR / 'puma560.urdf'
UR5 = URDF_DIR / 'ur5.urdf'
DESK = URDF_DIR / 'desk_arm6.urdf'

PUMA_A = [0.0, 0.4318, 0.0203, 0.0, 0.0, 0.0]
PUMA_D = [0.0, 0.0, 0.15005, 0.4318, 0.0, 0.0]
PUMA_ALPHA = [np.pi / 2, 0.0, -np.pi / 2, np.pi / 2, -np.pi / 2, 0.0]
UR5_A = [0.0, -0.425, -0.39225, 0.0, 0.0, 0.0]
UR5_D = [0.089159, 0.0, 0.0, 0.10915, 0.09465, 0.0823]
UR5_ALPHA = [np.pi / 2, 0.0, 0.0, np.pi / 2, -np.pi / 2, 0.0]

# A small hand-checkable chain: continuous joint about z, fixed link, prismatic joint along a
# skewed axis, revolute joint about -x, then a tool offset.
TOY_URDF = """<robot name="toy">
  <link name="base_link"/>
  <link name="a"/><link name="b"/><link name="c"/><link name="d"/><link name="tool0"/>
  <link name="side"><inertial><origin xyz="0 0.1 0"/><mass value="2"/></inertial></link>
  <joint name="spin" type="continuous">
    <parent link="base_link"/><child link="a"/>
    <origin xyz="0 0 0.3"/><axis xyz="0 0 1"/>
  </joint>
  <joint name="bracket" type="fixed">
    <parent link="a"/><child link="b"/>
    <origin xyz="0.2 0 0" rpy="0 0 0.5"/>
  </joint>
  <joint name="slide" type="prismatic">
    <parent link="b"/><child link="c"/>
    <origin xyz="0 0.1 0"/><axis xyz="1 1 0"/>
    <limit lower="-0.1" upper="0.4" effort="10" velocity="0.5"/>
  </joint>
  <joint name="tilt" type="revolute">
    <parent link="c"/><child link="d"/>
    <origin xyz="0 0 0.05" rpy="0.3 0 0"/><axis xyz="-1 0 0"/>
    <limit lower="-1" upper="1" effort="10" velocity="1"/>
  </joint>
  <joint name="side_joint" type="fixed">
    <parent link="c"/><child link="side"/>
    <origin xyz="0 0 0" rpy="0 0 1.5707963267948966"/>
  </joint>
  <joint name="tool_joint" type="fixed">
    <parent link="d"/><child link="tool0"/>
    <origin xyz="0 0 0.1"/>
  </joint>
</robot>"""


def _rz(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def _rx(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[1.0, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])


def _trans(x, y, z):
    T = np.eye(4)
    T[:3, 3] = (x, y, z)
    return T


def _standard_dh(q, a, d, alpha, base=np.eye(4)):
    """Written out independently: T = base prod_i Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)."""
    T = base.copy()
    for qi, ai, di, al in zip(q, a, d, alpha):
        ct, st, ca, sa = np.cos(qi), np.sin(qi), np.cos(al), np.sin(al)
        T = T @ np.array([[ct, -st * ca, st * sa, ai * ct],
                          [st, ct * ca, -ct * sa, ai * st],
                          [0.0, sa, ca, di],
                          [0.0, 0.0, 0.0, 1.0]])
    return T


def _toy_by_hand(q):
    spin, slide, tilt = q
    axis = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    T = _trans(0, 0, 0.3) @ _rz(spin) @ _trans(0.2, 0, 0) @ _rz(0.5) @ _trans(0, 0.1, 0)
    T = T @ _trans(*(axis * slide)) @ _trans(0, 0, 0.05) @ _rx(0.3) @ _rx(-tilt)
    return T @ _trans(0, 0, 0.1)


@pytest.fixture(scope='module')
def puma():
    return KinematicChain.from_file(PUMA, tip_link='marker')


@pytest.fixture(scope='module')
def toy():
    return KinematicChain.from_urdf(TOY_URDF, tip_link='tool0')


@pytest.fixture(scope='module')
def desk():
    return KinematicChain.from_file(DESK, tip_link='marker')


def _random_q(chain, m, rng):
    lo = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)
    hi = np.where(np.isfinite(chain.upper), chain.upper, np.pi)
    return rng.uniform(lo, hi, size=(m, chain.n_joints))


def test_puma_matches_standard_dh(puma):
    rng = np.random.default_rng(0)
    q = _random_q(puma, 200, rng)
    tool0 = KinematicChain.from_file(PUMA, tip_link='tool0')
    poses = tool0.fk_pose(q)
    ref = np.array([_standard_dh(qi, PUMA_A, PUMA_D, PUMA_ALPHA) for qi in q])
    assert poses.shape == (200, 4, 4)
    assert np.max(np.abs(poses[:, :3, 3] - ref[:, :3, 3])) < 1e-12
    assert np.max(np.abs(poses[:, :3, :3] - ref[:, :3, :3])) < 1e-12
    marker_ref = ref[:, :3, :3] @ np.array([0.0, 0.0, 0.05]) + ref[:, :3, 3]
    assert np.max(np.abs(puma.fk(q) - marker_ref)) < 1e-12
    point = np.array([0.01, -0.02, 0.03])
    expected = ref[:, :3, :3] @ (point + [0.0, 0.0, 0.05]) + ref[:, :3, 3]
    assert np.max(np.abs(puma.fk(q, point) - expected)) < 1e-12


def test_puma_chain_attributes(puma):
    assert puma.joint_names == [f'joint_{i}' for i in range(1, 7)]
    assert puma.n_joints == 6
    assert puma.joint_types == ['revolute'] * 6
    qlim = np.deg2rad([[-160, 160], [-45, 225], [-225, 45], [-110, 170], [-100, 100],
                       [-266, 266]])
    np.testing.assert_allclose(puma.lower, qlim[:, 0], atol=1e-12)
    np.testing.assert_allclose(puma.upper, qlim[:, 1], atol=1e-12)
    assert puma.chain_links == [f'link_{i}' for i in range(1, 7)]
    np.testing.assert_allclose(puma.link_masses, [0, 17.4, 4.8, 0.82, 0.34, 0.09])
    np.testing.assert_allclose(puma.effort_limits, [97.6, 186.4, 89.4, 24.2, 20.1, 21.3])
    assert puma.n_errors == 7 * 6 + 6 == len(puma.error_names)
    assert puma.error_names[:7] == ['joint_1/offset', 'joint_1/tx', 'joint_1/ty', 'joint_1/tz',
                                    'joint_1/rx', 'joint_1/ry', 'joint_1/rz']
    assert puma.error_names[-6:] == ['tip/tx', 'tip/ty', 'tip/tz', 'tip/rx', 'tip/ry', 'tip/rz']
    no_tip = KinematicChain.from_file(PUMA, tip_link='marker', tip_errors=False)
    assert no_tip.n_errors == 42


def test_link_coms_are_corke_centres_of_mass(puma):
    """Each link COM, taken into DH frame i, must be Corke's r_i."""
    rng = np.random.default_rng(5)
    q = _random_q(puma, 20, rng)
    frames = puma.link_frames(q)
    corke_r = [[0, 0, 0], [-0.3638, 0.006, 0.2275], [-0.0203, -0.0141, 0.070], [0, 0.019, 0],
               [0, 0, 0], [0, 0, 0.032]]
    for m in range(len(q)):
        for i in range(6):
            dh = _standard_dh(q[m, :i + 1], PUMA_A[:i + 1], PUMA_D[:i + 1], PUMA_ALPHA[:i + 1])
            com_world = frames[m, i, :3, :3] @ puma.link_coms[i] + frames[m, i, :3, 3]
            np.testing.assert_allclose(dh[:3, :3] @ corke_r[i] + dh[:3, 3], com_world,
                                       atol=1e-12)


def test_link_frames_end_at_the_tip(puma):
    rng = np.random.default_rng(1)
    q = _random_q(puma, 50, rng)
    frames = puma.link_frames(q)
    assert frames.shape == (50, 6, 4, 4)
    tip = puma.fk_pose(q)
    # marker is 0.05 m along link_6 z (tool0 is identity)
    np.testing.assert_allclose(frames[:, 5] @ _trans(0, 0, 0.05), tip, atol=1e-13)
    # link_2's frame is joint_2's child: base Rz(q1) Rx(pi/2) Rz(q2)
    ref = np.array([_rz(a) @ _rx(np.pi / 2) @ _rz(b) for a, b in q[:, :2]])
    np.testing.assert_allclose(frames[:, 1], ref, atol=1e-13)


def test_ur5_matches_dh_and_known_home_pose():
    chain = KinematicChain.from_file(UR5, tip_link='tool0')
    assert chain.joint_names == ['shoulder_pan_joint', 'shoulder_lift_joint', 'elbow_joint',
                                 'wrist_1_joint', 'wrist_2_joint', 'wrist_3_joint']
    rng = np.random.default_rng(2)
    q = _random_q(chain, 100, rng)
    base = _rz(np.pi)   # ur_description's base_link is the DH base turned by pi about z
    ref = np.array([_standard_dh(qi, UR5_A, UR5_D, UR5_ALPHA, base) for qi in q])
    np.testing.assert_allclose(chain.fk_pose(q), ref, atol=1e-12)
    home = chain.fk_pose(np.zeros(6))[0]
    np.testing.assert_allclose(home[:3, 3], [0.81725, 0.19145, -0.005491], atol=1e-12)
    # at home the tool points along +y of base_link
    np.testing.assert_allclose(home[:3, 2], [0.0, 1.0, 0.0], atol=1e-12)
    # base_link_inertia is fixed to the base: it loads no joint
    np.testing.assert_allclose(chain.link_masses,
                               [3.7, 8.393, 2.275, 1.219, 1.219, 0.1879])


def test_desk_arm_geometry(desk):
    tool0 = KinematicChain.from_file(DESK, tip_link='tool0')
    assert desk.joint_types[3] == 'continuous' and np.isinf(desk.upper[3])
    home = tool0.fk_pose(np.zeros(6))[0]
    np.testing.assert_allclose(home[:3, 3], [0.28, 0.0, 0.48], atol=1e-15)
    np.testing.assert_allclose(home[:3, 2], [1.0, 0.0, 0.0], atol=1e-15)
    # shoulder up by 90 deg about y: the whole arm swings down in the x-z plane about (0,0,0.2)
    swung = tool0.fk_pose([0.0, np.pi / 2, 0.0, 0.0, 0.0, 0.0])[0]
    np.testing.assert_allclose(swung[:3, 3], [0.28, 0.0, -0.08], atol=1e-15)
    # the shoulder-to-wrist distance depends on the elbow only
    rng = np.random.default_rng(8)
    q = _random_q(desk, 100, rng)
    q[:, 2] = 0.7
    frames = desk.link_frames(q)
    dist = np.linalg.norm(frames[:, 4, :3, 3] - frames[:, 1, :3, 3], axis=1)
    elbow = np.array([0.12 + 0.1, 0.0, 0.03])    # wrist from elbow in link_3
    upper = np.array([0.0, 0.0, 0.25])
    c, s = np.cos(0.7), np.sin(0.7)
    expected = np.linalg.norm(upper + np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ elbow)
    np.testing.assert_allclose(dist, expected, atol=1e-14)
    # the marker stays 0.04 m from the tool origin along tool z
    np.testing.assert_allclose(desk.fk(q) - tool0.fk(q), tool0.fk_pose(q)[:, :3, 2] * 0.04,
                               atol=1e-15)


def test_toy_chain_matches_hand_computation(toy):
    assert toy.joint_names == ['spin', 'slide', 'tilt']
    assert toy.joint_types == ['continuous', 'prismatic', 'revolute']
    assert toy.lower[0] == -np.inf and toy.upper[0] == np.inf
    np.testing.assert_allclose(toy.lower[1:], [-0.1, -1.0])
    rng = np.random.default_rng(3)
    q = np.column_stack([rng.uniform(-7, 7, 30), rng.uniform(-0.1, 0.4, 30),
                         rng.uniform(-1, 1, 30)])
    ref = np.array([_toy_by_hand(qi) for qi in q])
    np.testing.assert_allclose(toy.fk_pose(q), ref, atol=1e-13)
    point = np.array([0.02, 0.03, -0.01])
    np.testing.assert_allclose(toy.fk(q, point), ref[:, :3, :3] @ point + ref[:, :3, 3],
                               atol=1e-13)


def test_toy_rigid_mass_includes_off_chain_fixed_links(toy):
    # 'side' (2 kg, com 0.1 m along its y) hangs off link c, turned by pi/2 about z
    np.testing.assert_allclose(toy.link_masses, [0.0, 2.0, 0.0])
    np.testing.assert_allclose(toy.link_coms[1], [-0.1, 0.0, 0.0], atol=1e-15)


def _central_difference(f, x0, h):
    cols = []
    for k in range(len(x0)):
        dx = np.zeros_like(x0)
        dx[k] = h
        cols.append((f(x0 + dx) - f(x0 - dx)) / (2 * h))
    return np.stack(cols, axis=-1)


def _relative_error(J, J_fd):
    return np.max(np.abs(J - J_fd)) / np.max(np.abs(J_fd))


def _random_errors(chain, rng, scale=1.0):
    sig = chain.error_vector(offset=0.05, translation=0.01, rotation=0.1)
    return scale * sig * rng.standard_normal(chain.n_errors)


@pytest.mark.parametrize('which', ['puma', 'toy', 'desk'])
@pytest.mark.parametrize('with_errors', [False, True])
def test_jacobian_q_matches_finite_differences(which, with_errors, puma, toy, desk):
    chain = {'puma': puma, 'toy': toy, 'desk': desk}[which]
    rng = np.random.default_rng(10)
    q = _random_q(chain, 20, rng)
    errors = _random_errors(chain, rng) if with_errors else None
    point = np.array([0.03, -0.01, 0.02])
    J = chain.jacobian_q(q, point, errors)
    assert J.shape == (20, 3, chain.n_joints)
    J_fd = np.stack([_central_difference(lambda v: chain.fk(v, point, errors)[0], qi, 1e-6)
                     for qi in q])
    assert _relative_error(J, J_fd) < 1e-6


@pytest.mark.parametrize('which', ['puma', 'toy', 'desk'])
@pytest.mark.parametrize('with_errors', [False, True])
def test_jacobian_errors_matches_finite_differences(which, with_errors, puma, toy, desk):
    chain = {'puma': puma, 'toy': toy, 'desk': desk}[which]
    rng = np.random.default_rng(11)
    q = _random_q(chain, 10, rng)
    errors = _random_errors(chain, rng) if with_errors else np.zeros(chain.n_errors)
    point = np.array([0.03, -0.01, 0.02])
    J = chain.jacobian_errors(q, point, errors)
    assert J.shape == (10, 3, chain.n_errors)
    J_fd = _central_difference(lambda e: chain.fk(q, point, e), errors, 1e-6)
    assert _relative_error(J, J_fd) < 1e-6
    # the offset columns are the joint columns
    np.testing.assert_allclose(J[:, :, 0:7 * chain.n_joints:7],
                               chain.jacobian_q(q, point, errors), atol=1e-15)


def test_errors_none_equals_zeros(puma):
    rng = np.random.default_rng(4)
    q = _random_q(puma, 15, rng)
    zeros = np.zeros(puma.n_errors)
    point = (0.0, 0.01, 0.0)
    np.testing.assert_array_equal(puma.fk(q, point), puma.fk(q, point, zeros))
    np.testing.assert_array_equal(puma.fk_pose(q), puma.fk_pose(q, zeros))
    np.testing.assert_array_equal(puma.jacobian_q(q, point), puma.jacobian_q(q, point, zeros))
    np.testing.assert_array_equal(puma.jacobian_errors(q, point),
                                  puma.jacobian_errors(q, point, zeros))


def test_error_parameters_act_as_documented(puma):
    rng = np.random.default_rng(6)
    q = _random_q(puma, 10, rng)
    names = puma.error_names
    # an offset is a shift of the joint value
    e = np.zeros(puma.n_errors)
    e[names.index('joint_3/offset')] = 0.2
    np.testing.assert_allclose(puma.fk(q, errors=e), puma.fk(q + [0, 0, 0.2, 0, 0, 0]),
                               atol=1e-14)
    # a rotation error about a revolute joint's own axis is the same as its offset
    e = np.zeros(puma.n_errors)
    e[names.index('joint_2/rz')] = 0.2
    np.testing.assert_allclose(puma.fk(q, errors=e), puma.fk(q + [0, 0.2, 0, 0, 0, 0]),
                               atol=1e-14)
    # a tip translation error moves the point by that vector in the tip frame
    e = np.zeros(puma.n_errors)
    e[-6:-3] = [0.001, -0.002, 0.003]
    np.testing.assert_allclose(puma.fk(q, errors=e), puma.fk(q, point=e[-6:-3]), atol=1e-14)
    # translation errors of a joint origin are DH link changes (t is in the joint frame, after
    # Rx(alpha) of the DH row before): joint_3/tx is a_2, joint_2/ty is d_1 (alpha_1 = pi/2)
    e = np.zeros(puma.n_errors)
    e[names.index('joint_3/tx')] = 0.004
    e[names.index('joint_2/ty')] = -0.003
    a, d = list(PUMA_A), list(PUMA_D)
    a[1] += 0.004
    d[0] -= 0.003
    ref = np.array([_standard_dh(qi, a, d, PUMA_ALPHA) @ [0, 0, 0.05, 1] for qi in q])
    np.testing.assert_allclose(puma.fk(q, errors=e), ref[:, :3], atol=1e-13)


def test_error_vector_fills_kinds(toy):
    v = toy.error_vector(offset=1.0, translation=2.0, rotation=3.0, prismatic_offset=4.0,
                         tip_translation=5.0, tip_rotation=6.0)
    assert v.shape == (toy.n_errors,)
    by_name = dict(zip(toy.error_names, v))
    assert by_name['spin/offset'] == 1.0 and by_name['slide/offset'] == 4.0
    assert by_name['tilt/ty'] == 2.0 and by_name['tilt/rx'] == 3.0
    assert by_name['tip/tz'] == 5.0 and by_name['tip/ry'] == 6.0


def test_index_map_reordered_and_extra_joints(puma):
    names = ['gripper', 'joint_6', 'joint_2', 'joint_4', 'camera_pan', 'joint_1', 'joint_5',
             'joint_3']
    idx = puma.index_map(names)
    positions = np.array([9.0, 0.6, 0.2, 0.4, 8.0, 0.1, 0.5, 0.3])
    np.testing.assert_array_equal(positions[idx], [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    assert [names[i] for i in idx] == puma.joint_names
    # works on a batch of JointState rows too
    batch = np.tile(positions, (4, 1))
    np.testing.assert_array_equal(batch[:, idx][2], [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])


def test_index_map_missing_and_repeated_joint(puma):
    with pytest.raises(ValueError, match='joint_4'):
        puma.index_map(['joint_1', 'joint_2', 'joint_3', 'joint_5', 'joint_6'])
    with pytest.raises(ValueError, match='joint_3'):
        puma.index_map(['joint_1', 'joint_2', 'joint_3', 'joint_3', 'joint_4', 'joint_5',
                        'joint_6'])
    with pytest.raises(ValueError):
        puma.index_map('joint_1')


def test_shapes_and_argument_checks(puma):
    assert puma.fk(np.zeros(6)).shape == (1, 3)
    assert puma.fk_pose(np.zeros((7, 6))).shape == (7, 4, 4)
    assert puma.jacobian_errors(np.zeros(6)).shape == (1, 3, 48)
    np.testing.assert_allclose(puma.fk(np.zeros(6))[0], [0.4521, -0.15005, 0.4818 + 0.0],
                               atol=1e-12)
    with pytest.raises(ValueError, match='q must have shape'):
        puma.fk(np.zeros(5))
    with pytest.raises(ValueError, match='errors must have shape'):
        puma.fk(np.zeros(6), errors=np.zeros(3))
    with pytest.raises(ValueError, match='point must have shape'):
        puma.fk(np.zeros((2, 6)), point=np.zeros((3, 3)))
    # a per-configuration point is accepted
    pts = np.array([[0, 0, 0.0], [0, 0, 0.1]])
    out = puma.fk(np.zeros((2, 6)), point=pts)
    np.testing.assert_allclose(out[1] - out[0], [0, 0, 0.1], atol=1e-14)


def test_no_chain_between_frames_is_named():
    model = load_urdf(PUMA)
    with pytest.raises(ValueError, match="'marker'.*'link_3'|'link_3'.*'marker'"):
        KinematicChain(model, base_frame='marker', tip_link='link_3')
    with pytest.raises(ValueError, match='world'):
        KinematicChain(model, base_frame='world', tip_link='tool0')
    with pytest.raises(ValueError, match='no movable joint'):
        KinematicChain(model, base_frame='link_6', tip_link='marker')


def test_gravity_torques_are_minus_gradient_of_potential(puma, toy, desk):
    g = np.array([1.0, -2.0, -9.5])   # tilted so that the toy's slide feels it too
    for chain in (puma, toy, desk):
        rng = np.random.default_rng(7)
        q = _random_q(chain, 8, rng)

        def potential(v, chain=chain):
            frames = chain.link_frames(v)
            com = np.einsum('mkij,kj->mki', frames[..., :3, :3], chain.link_coms)
            com += frames[..., :3, 3]
            return -np.einsum('k,mki,i->m', chain.link_masses, com, g)

        tau = chain.gravity_torques(q, g)
        assert tau.shape == (8, chain.n_joints)
        grad = np.stack([_central_difference(lambda v: potential(v[None])[0], qi, 1e-6)
                         for qi in q])
        np.testing.assert_allclose(tau, -grad, atol=1e-6 * np.max(np.abs(grad)) + 1e-12)
    # PUMA joint 1 turns about the vertical: gravity exerts no torque on it
    assert np.max(np.abs(puma.gravity_torques(_random_q(puma, 5, rng))[:, 0])) < 1e-12
    assert np.max(np.abs(toy.gravity_torques(_random_q(toy, 5, rng))[:, :2])) < 1e-12
