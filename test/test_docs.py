"""The README stays true: every parameter and every command it must document is there."""
import os
import re

from armcal_ros.cli import SUBCOMMANDS
from armcal_ros.params import PARAMS

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _readme():
    with open(os.path.join(ROOT, 'README.md')) as f:
        return f.read()


def test_readme_shows_the_two_commands_first():
    text = _readme()
    first = text.index('make demo'), text.index('make test')
    assert max(first) < text.index('## Install')


def test_every_parameter_is_documented_with_its_default():
    text = _readme()
    for p in PARAMS:
        row = re.search(rf'^\| `{re.escape(p.name)}` \| {re.escape(p.type)} \|(.*)$', text, re.M)
        assert row, f'README lacks parameter {p.name}'
        if isinstance(p.default, (int, float)) and not isinstance(p.default, bool):
            assert f'`{p.default}`' in row.group(1), f'README default of {p.name}'


def test_every_subcommand_is_documented():
    text = _readme()
    for name in SUBCOMMANDS:
        assert f'armcal {name}' in text, f'README lacks armcal {name}'
