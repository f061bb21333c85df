"""Parameter files of the node (``--params-file``) and of ``armcal calibrate`` (``--params``)."""

import os

import yaml

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
PUMA_URDF = os.path.join(ROOT, 'urdf', 'puma560.urdf')


def write_params(path, defaults, **values):
    """Write ``defaults`` updated by ``values`` as the parameters of node ``armcal``; the path."""
    params = dict(defaults, **values)
    with open(path, 'w') as f:
        yaml.safe_dump({'armcal': {'ros__parameters': params}}, f)
    return str(path)
