"""
Fixtures shared by the test modules; the plain helpers they use are in ``helpers/``.

pytest puts this folder on sys.path for this file (it is not a package), so the tests import
``helpers.<module>`` from any working directory.  The ROS fixtures import rclpy only when a test
asks for them, after ``pytest.importorskip('rclpy')``: the other tests run without ROS.
"""

import os

import pytest

# Plain asserts in the helpers report their operands as the tests' own asserts do.
pytest.register_assert_rewrite('helpers')

#: A folder that outlives one pytest run (``make test`` sets it for both of its runs): the
#: session's costly recordings are written there once and read by the other run.
SHARED_ENV = 'ARMCAL_TEST_SHARED'


def pytest_collection_modifyitems(items):
    """
    Mark the tests that run ROS nodes over DDS with ``ros``; put slow modules first.

    A test that asks for ``ros_env`` runs nodes.  ``make test`` runs the others on both cores
    (pytest-xdist, a module per worker) and these one at a time after them: a live node
    replaying a bag in real time needs the cores the replay was sized for.  The modules with
    a test marked ``slow`` go first (in their own order), so that the workers end on short
    modules rather than one waiting for the other's last long one.
    """
    slow = set()
    for item in items:
        if 'ros_env' in getattr(item, 'fixturenames', ()):
            item.add_marker(pytest.mark.ros)
        if item.get_closest_marker('slow') is not None:
            slow.add(item.module.__name__)
    items.sort(key=lambda item: item.module.__name__ not in slow)


@pytest.fixture(scope='module')
def ros_env(request, tmp_path_factory):
    """
    Give the requesting module its own ROS 2 environment; yield it for subprocesses, restore.

    Its own ROS_DOMAIN_ID (from the pid and the module's name, never another module's of this
    run), a fresh ROS_LOG_DIR and discovery on localhost only (helpers.ros_nodes).
    """
    pytest.importorskip('rclpy')
    from helpers.ros_nodes import isolated_ros_env
    yield from isolated_ros_env(tmp_path_factory, request.module.__name__)


@pytest.fixture(scope='module')
def client(ros_env):
    """Spin the test's own rclpy node, in the module's domain, in a background thread."""
    from helpers.ros_nodes import Client
    c = Client()
    yield c
    c.close()


@pytest.fixture(scope='session')
def board_pose_bag(tmp_path_factory):
    """Write the board scene as a bag: a PoseStamped link pose and images (8 dwells)."""
    from helpers.board_scene import write_pose_bag
    path = str(tmp_path_factory.mktemp('posebag') / 'bag')
    write_pose_bag(path)
    return path


@pytest.fixture(scope='session')
def board_joint_bag(tmp_path_factory):
    """
    Write the board scene carried by a Cartesian robot: a folder with ``bag``, ``robot.urdf``.

    The bag holds the joint states at 100 Hz and the images at 10 Hz (8 dwells of 1 s).
    """
    from helpers.board_scene import CARTESIAN_URDF, write_joint_bag
    d = tmp_path_factory.mktemp('boardjoints')
    write_joint_bag(str(d / 'bag'))
    (d / 'robot.urdf').write_text(CARTESIAN_URDF)
    return d


@pytest.fixture(scope='session')
def knocked_bag(tmp_path_factory):
    """
    Simulate 150 s of the demo cell in which cam2 is knocked by 1 deg and 4 mm at 75 s.

    Written by ``armcal simulate --knock`` (uncompressed mcap), with its ground truth: the
    cameras at the end, ``epochs/`` and ``changes.yaml``, and the cell's ``params.yaml``.
    """
    from armcal_ros.cli import main

    def write(bag):
        return main(['simulate', '--output', str(bag), '--duration', '150', '--knock',
                     'cam2:75:1:4', '--no-zstd', '--quiet']) == 0
    shared = os.environ.get(SHARED_ENV)
    if not shared:
        bag = tmp_path_factory.mktemp('knocked') / 'bag'
        assert write(bag)
        return bag
    # One recording for both runs of make test (written once, under a lock).
    from helpers.shared import shared_output
    return shared_output(shared, 'knocked', write)
