"""The ROS packaging: parameter file, launch file, and a colcon build of the repository."""
import importlib.util
import os
import py_compile
import shutil
import subprocess
import sys

import pytest
import yaml

from armcal_ros.params import load_params_file, PARAMS

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE_FILES = ('package.xml', 'setup.py', 'setup.cfg', 'resource', 'armcal_ros', 'launch',
                 'config', 'urdf')


def test_config_file_sets_every_parameter_and_loads():
    path = os.path.join(ROOT, 'config', 'calibrator.yaml')
    with open(path) as f:
        doc = yaml.safe_load(f)['armcal']['ros__parameters']
    assert set(doc) == {p.name for p in PARAMS}
    values = load_params_file(path)
    assert os.path.isfile(values['robot_description_file'])
    assert values['marker_offset'] == [0.0, 0.0, 0.05]
    for p in PARAMS:
        if p.type == 'double':
            assert isinstance(doc[p.name], float), f'{p.name} must be written as a double'


def test_launch_file_compiles_and_builds_when_launch_is_installed(tmp_path):
    path = os.path.join(ROOT, 'launch', 'calibrator.launch.py')
    py_compile.compile(path, cfile=str(tmp_path / 'launch.pyc'), doraise=True)
    if importlib.util.find_spec('launch_ros') is None:
        pytest.skip('launch_ros is not installed here (no wheel): the launch file is only '
                    'compiled')
    spec = importlib.util.spec_from_file_location('calibrator_launch', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.generate_launch_description().entities


def _colcon():
    exe = shutil.which('colcon') or os.path.join(os.path.dirname(sys.executable), 'colcon')
    return exe if os.path.exists(exe) else None


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_colcon_build_installs_the_node_index_launch_and_config(tmp_path):
    colcon = _colcon()
    if colcon is None or importlib.util.find_spec('colcon_ros') is None:
        pytest.skip('colcon is not installed (pip install colcon-common-extensions colcon-ros)')
    src = tmp_path / 'ws' / 'src' / 'armcal_ros'
    src.mkdir(parents=True)
    for name in PACKAGE_FILES:
        from_path = os.path.join(ROOT, name)
        if os.path.isdir(from_path):
            shutil.copytree(from_path, src / name,
                            ignore=shutil.ignore_patterns('__pycache__', '*.pyc'))
        else:
            shutil.copy2(from_path, src / name)
    env = dict(os.environ, PATH=os.path.dirname(sys.executable) + os.pathsep +
               os.environ.get('PATH', ''))
    run = subprocess.run([colcon, 'build', '--event-handlers', 'console_direct-'],
                         cwd=tmp_path / 'ws', env=env, capture_output=True, text=True,
                         timeout=240)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    install = tmp_path / 'ws' / 'install' / 'armcal_ros'
    share = install / 'share' / 'armcal_ros'
    node = install / 'lib' / 'armcal_ros' / 'calibrator_node'
    assert node.is_file() and os.access(node, os.X_OK)
    assert "'console_scripts', 'calibrator_node'" in node.read_text()
    entry_points = list(install.glob('lib/python*/site-packages/armcal_ros*/entry_points.txt'))
    assert entry_points and 'calibrator_node = armcal_ros.ros.node:main' in \
        entry_points[0].read_text()
    assert (install / 'share' / 'ament_index' / 'resource_index' / 'packages' /
            'armcal_ros').is_file()
    assert (share / 'package.xml').is_file()
    assert (share / 'launch' / 'calibrator.launch.py').is_file()
    assert (share / 'config' / 'calibrator.yaml').is_file()
    # The installed parameter file finds the installed URDF through its relative path.
    assert load_params_file(str(share / 'config' / 'calibrator.yaml'))['robot_description_file'] \
        == str(share / 'urdf' / 'puma560.urdf')
