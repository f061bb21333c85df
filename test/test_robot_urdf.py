"""Tests of the URDF parser."""

from pathlib import Path

import numpy as np
import pytest

from armcal_ros.robot import load_urdf, origin_matrix, parse_urdf, rpy_to_matrix

URDF_DIR = Path(__file__).resolve().parents[1] / 'urdf'


def _robot(body):
    return f'<?xml version="1.0"?>\n<robot name="r">\n{body}\n</robot>'


TWO_LINKS = '<link name="a"/><link name="b"/>'


def _joint(jtype='revolute', extra='<limit lower="-1" upper="1" effort="1" velocity="1"/>',
           name='j', parent='a', child='b'):
    return (f'<joint name="{name}" type="{jtype}"><parent link="{parent}"/>'
            f'<child link="{child}"/>{extra}</joint>')


def test_puma_file_parses():
    model = load_urdf(URDF_DIR / 'puma560.urdf')
    assert model.name == 'puma560'
    assert model.root_link == 'base_link'
    assert [j for j in model.joints] == [f'joint_{i}' for i in range(1, 7)] + [
        'tool0_joint', 'marker_joint']
    j3 = model.joints['joint_3']
    assert (j3.type, j3.parent, j3.child) == ('revolute', 'link_2', 'link_3')
    np.testing.assert_array_equal(j3.axis, [0.0, 0.0, 1.0])
    np.testing.assert_allclose(j3.origin[:3, 3], [0.4318, 0.0, 0.0])
    np.testing.assert_allclose(j3.lower, np.deg2rad(-225))
    assert model.links['link_2'].mass == 17.4
    np.testing.assert_allclose(model.links['link_2'].com, [0.4318 - 0.3638, 0.006, 0.2275])
    assert model.links['tool0'].mass == 0.0
    np.testing.assert_allclose(model.joints['marker_joint'].origin[:3, 3], [0, 0, 0.05])


def test_origin_convention_is_fixed_axis_rpy():
    r, p, y = 0.3, -0.7, 1.1
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    Rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    Ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    Rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    np.testing.assert_allclose(rpy_to_matrix([r, p, y]), Rz @ Ry @ Rx, atol=1e-15)
    text = _robot(TWO_LINKS + _joint(extra=(
        '<origin xyz="1 2 3" rpy="0.3 -0.7 1.1"/><axis xyz="0 3 4"/>'
        '<limit lower="-1" upper="2" effort="5" velocity="6"/>')))
    joint = parse_urdf(text).joints['j']
    np.testing.assert_allclose(joint.origin, origin_matrix([1, 2, 3], [r, p, y]))
    np.testing.assert_allclose(joint.origin[:3, :3], Rz @ Ry @ Rx, atol=1e-15)
    np.testing.assert_allclose(joint.axis, [0.0, 0.6, 0.8])
    assert (joint.lower, joint.upper, joint.effort, joint.velocity) == (-1, 2, 5, 6)


def test_defaults_axis_origin_and_continuous_limits():
    model = parse_urdf(_robot(TWO_LINKS + _joint('continuous', extra='')))
    joint = model.joints['j']
    np.testing.assert_array_equal(joint.axis, [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(joint.origin, np.eye(4))
    assert joint.lower == -np.inf and joint.upper == np.inf and joint.movable
    fixed = parse_urdf(_robot(TWO_LINKS + _joint('fixed', extra=''))).joints['j']
    assert not fixed.movable and fixed.lower == fixed.upper == 0.0
    # bytes are accepted too (as read from a parameter or a file)
    assert parse_urdf(_robot('<link name="a"/>').encode()).root_link == 'a'


def test_inertial_is_read_and_rotated():
    text = _robot('<link name="a"><inertial>'
                  '<origin xyz="0.1 0.2 0.3" rpy="0 0 1.5707963267948966"/>'
                  '<mass value="2.5"/><inertia ixx="1" ixy="0" ixz="0" iyy="2" iyz="0" izz="3"/>'
                  '</inertial></link>')
    link = parse_urdf(text).links['a']
    assert link.mass == 2.5
    np.testing.assert_allclose(link.com, [0.1, 0.2, 0.3])
    # a quarter turn about z swaps the x and y moments
    np.testing.assert_allclose(link.inertia, np.diag([2.0, 1.0, 3.0]), atol=1e-15)


def test_chain_walks_base_to_tip():
    model = load_urdf(URDF_DIR / 'ur5.urdf')
    names = [j.name for j in model.chain('base_link', 'tool0')]
    assert names[0] == 'base_link-base_link_inertia' and names[-1] == 'flange-tool0'
    assert 'base_link-base_fixed_joint' not in names
    assert [j.name for j in model.chain('forearm_link', 'wrist_2_link')] == [
        'wrist_1_joint', 'wrist_2_joint']
    assert model.chain('tool0', 'tool0') == []


@pytest.mark.parametrize('text, message', [
    ('<robot name="r"><link name="a"></robot>', 'not well-formed XML'),
    ('<robots name="r"><link name="a"/></robots>', 'root element must be <robot>'),
    (_robot(''), 'has no <link>'),
    (_robot('<link/>'), 'no name'),
    (_robot('<link name="a"/><link name="a"/>'), "link 'a' is defined twice"),
    (_robot(TWO_LINKS + _joint(child='c')), "child link 'c' is not defined"),
    (_robot(TWO_LINKS + _joint(parent='zz')), "parent link 'zz' is not defined"),
    (_robot(TWO_LINKS + _joint('revolut')), "type 'revolut'"),
    (_robot(TWO_LINKS + _joint(extra='')), "revolute joint 'j' has no <limit>"),
    (_robot(TWO_LINKS + _joint('prismatic', extra='')), "prismatic joint 'j' has no <limit>"),
    (_robot(TWO_LINKS + _joint(extra='<limit lower="2" upper="1" effort="1" velocity="1"/>')),
     r'lower \(2.0\) must be <= upper'),
    (_robot(TWO_LINKS + _joint(extra='<limit lower="a" upper="1"/>')), 'lower must be a number'),
    (_robot(TWO_LINKS + _joint('fixed', extra='<origin xyz="0 0"/>')),
     "joint 'j' origin xyz must be 3"),
    (_robot(TWO_LINKS + _joint('continuous', extra='<origin rpy="0 x 0"/>')),
     "joint 'j' origin rpy"),
    (_robot(TWO_LINKS + _joint('continuous', extra='<axis xyz="0 0 0"/>')), 'non-zero'),
    (_robot(TWO_LINKS + '<joint name="j" type="fixed"><child link="b"/></joint>'),
     "joint 'j' has no <parent"),
    (_robot(TWO_LINKS + '<joint type="fixed"/>'), 'no name'),
    (_robot(TWO_LINKS), 'exactly one root link'),
    (_robot(TWO_LINKS + '<link name="c"/>' + _joint('fixed', extra='')
            + _joint('fixed', extra='', name='k', parent='c')),
     "link 'b' is the child of two joints"),
    (_robot(TWO_LINKS + '<link name="c"/>' + _joint('fixed', extra='', parent='c', child='b')
            + _joint('fixed', extra='', name='k', parent='b', child='c')),
     r"links \['b', 'c'\] are not connected"),
    (_robot(TWO_LINKS + '<link name="c"/><link name="d"/>' + _joint('fixed', extra='')
            + _joint('fixed', extra='', name='k', parent='c', child='d')
            + _joint('fixed', extra='', name='m', parent='d', child='c')),
     'not connected to the root'),
    (_robot('<link name="a"><inertial><mass value="-1"/></inertial></link>'), 'mass'),
    (_robot(TWO_LINKS + _joint('continuous', extra='<mimic joint="nope"/>')),
     "mimics unknown joint 'nope'"),
])
def test_parse_errors_name_the_problem(text, message):
    with pytest.raises(ValueError, match=message):
        parse_urdf(text)


def test_chain_errors_name_frames_and_joints():
    text = _robot('<link name="world"/>' + TWO_LINKS + '<link name="c"/>'
                  + _joint('floating', extra='', name='free', parent='world', child='a')
                  + _joint('continuous', extra='', name='j', parent='a', child='b')
                  + _joint('continuous', extra='<mimic joint="j"/>', name='m', parent='b',
                           child='c'))
    model = parse_urdf(text)   # a floating joint elsewhere does not stop parsing
    assert [j.name for j in model.chain('a', 'b')] == ['j']
    with pytest.raises(ValueError, match="joint 'free'.*'floating'"):
        model.chain('world', 'b')
    with pytest.raises(ValueError, match="joint 'm'.*mimic"):
        model.chain('a', 'c')
    with pytest.raises(ValueError, match="from 'b' to 'a'"):
        model.chain('b', 'a')
    with pytest.raises(ValueError, match="tip link 'tool0' is not a link"):
        model.chain('a', 'tool0')
    with pytest.raises(ValueError, match="base frame 'base_link' is not a link"):
        model.chain('base_link', 'b')


def test_load_urdf_missing_file(tmp_path):
    with pytest.raises(OSError):
        load_urdf(tmp_path / 'missing.urdf')
    path = tmp_path / 'r.urdf'
    path.write_text(_robot(TWO_LINKS + _joint()))
    assert load_urdf(path).joints['j'].child == 'b'
