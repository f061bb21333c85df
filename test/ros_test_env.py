"""A test module's own ROS 2 domain, log directory and localhost discovery (for DDS tests)."""

import os

KEYS = ('ROS_DOMAIN_ID', 'ROS_LOG_DIR', 'ROS_AUTOMATIC_DISCOVERY_RANGE')


def isolated_ros_env(tmp_path_factory, domain_offset=0):
    """
    Set the variables for this process (and its children), yield the environment, restore.

    The domain id is derived from the pid (plus ``domain_offset`` so two modules of one run
    differ), so concurrent test runs on one machine do not see each other's nodes.
    """
    saved = {k: os.environ.get(k) for k in KEYS}
    os.environ['ROS_DOMAIN_ID'] = str(1 + (os.getpid() + domain_offset) % 200)
    os.environ['ROS_LOG_DIR'] = str(tmp_path_factory.mktemp('ros_log'))
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    yield dict(os.environ, PYTHONUNBUFFERED='1')
    for k, v in saved.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
