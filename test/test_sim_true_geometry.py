"""The true geometry as a URDF (sim/true_geometry.py) moves the marker as the true arm does."""
import numpy as np

from armcal_ros.robot.kinematics import KinematicChain
from armcal_ros.sim.cell import bundled_urdf
from armcal_ros.sim.true_geometry import true_geometry_urdf, true_marker_offset
from armcal_ros.sim.true_robot import draw_geometric_errors


def test_the_written_urdf_reproduces_the_true_arm_for_the_bundled_arms():
    for name, tip in (('puma560.urdf', 'marker'), ('ur5.urdf', 'marker'),
                      ('desk_arm6.urdf', 'marker')):
        text = open(bundled_urdf(name)).read()
        chain = KinematicChain.from_urdf(text, 'base_link', tip)
        rng = np.random.default_rng(3)
        # Ten times the simulator's errors, so that a mistake in the composition shows.
        errors = 10 * draw_geometric_errors(chain, rng)
        point = np.array([0.01, -0.02, 0.05])
        true = KinematicChain.from_urdf(true_geometry_urdf(text, chain, errors), 'base_link', tip)
        q = rng.uniform(-2.0, 2.0, size=(50, chain.n_joints))
        want = chain.fk(q, point, errors)
        got = true.fk(q, true_marker_offset(chain, errors, point))
        assert np.max(np.abs(got - want)) < 1e-9, name
        # Nothing moves without errors.
        same = true_geometry_urdf(text, chain, np.zeros(chain.n_errors))
        assert np.allclose(KinematicChain.from_urdf(same, 'base_link', tip).fk(q, point),
                           chain.fk(q, point), atol=1e-12)
