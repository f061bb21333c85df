"""A folder of captures through ``armcal import-folder`` and ``armcal calibrate``."""

import argparse
import json

from armcal_ros.cli import main
from armcal_ros.offline import run


def import_and_calibrate(folder, tmp_path, **marker):
    """
    Import ``folder`` into a bag, add ``marker`` to its params.yaml, calibrate; the report.

    ``marker`` holds the parameters the folder cannot know (marker type, place, model...);
    a list value is written as a YAML flow list.
    """
    bag = tmp_path / 'bag'
    assert main(['import-folder', str(folder), '--output', str(bag)]) == 0
    with open(bag / 'params.yaml', 'a') as f:
        for k, v in marker.items():
            f.write(f'    {k}: {json.dumps(v) if isinstance(v, list) else v}\n')
    out = tmp_path / 'out'
    assert run(argparse.Namespace(bag=str(bag), params=str(bag / 'params.yaml'),
                                  output=str(out), noise_model=None, quiet=True)) == 0
    return json.loads((out / 'report.json').read_text())
