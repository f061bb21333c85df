"""A calibrated camera and workspace points: the content of the messages the node publishes."""

import numpy as np

from armcal_ros.core.camera import Camera


def camera():
    """Camera ``cam1``, 640 x 480, with distortion, 1.5 m from the point it looks at."""
    return Camera.look_at('cam1', 640, 480, 810.0, 790.0, 330.0, 235.0,
                          [-0.17, 0.06, 0.001, -0.002, 0.01], eye=[1.2, -1.0, 0.9],
                          target=[0.5, 0.0, 0.0])


def points(n=50, seed=0):
    """``n`` points drawn uniformly in the workspace box the camera looks at."""
    rng = np.random.default_rng(seed)
    return rng.uniform([0.3, -0.3, -0.2], [0.8, 0.3, 0.3], (n, 3))
