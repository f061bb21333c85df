"""The output directory a run replaces as a whole: checks, lock, staging, commit."""

import json
import os

import pytest

from armcal_ros.io.output_dir import MANIFEST, OutputDirectory, OutputDirError


def _run(directory, files):
    """One run writing ``files`` {relative path: text}; return the committed paths."""
    with OutputDirectory(directory) as out:
        for rel, text in files.items():
            path = os.path.join(out.staging, rel)
            os.makedirs(os.path.dirname(path), exist_ok=True)
            with open(path, 'w') as f:
                f.write(text)
        return out.commit()


def test_a_run_replaces_the_previous_runs_files_and_keeps_foreign_ones(tmp_path):
    (tmp_path / 'notes.txt').write_text('mine')
    _run(tmp_path, {'cam1.yaml': 'a1', 'cam3.yaml': 'a3', 'extrinsics.yaml': 'a',
                    'epochs/epoch_0/cam3.yaml': 'e'})
    got = _run(tmp_path, {'cam1.yaml': 'b1', 'extrinsics.yaml': 'b'})
    assert sorted(os.path.relpath(p, tmp_path) for p in got) == ['cam1.yaml', 'extrinsics.yaml']
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ['.armcal.lock', MANIFEST, 'cam1.yaml', 'extrinsics.yaml', 'notes.txt']
    assert (tmp_path / 'cam1.yaml').read_text() == 'b1'
    assert (tmp_path / 'notes.txt').read_text() == 'mine'
    assert json.loads((tmp_path / MANIFEST).read_text())['files'] == ['cam1.yaml',
                                                                      'extrinsics.yaml']


def test_a_run_of_an_earlier_version_is_recognised_by_its_calibration_json(tmp_path):
    (tmp_path / 'calibration.json').write_text(json.dumps({'cameras': {'cam1': {}, 'cam3': {}}}))
    (tmp_path / 'cam3.yaml').write_text('old')
    (tmp_path / 'other.yaml').write_text('not ours')
    _run(tmp_path, {'cam1.yaml': 'new', 'calibration.json': '{}'})
    assert not (tmp_path / 'cam3.yaml').exists()
    assert (tmp_path / 'other.yaml').exists()


def test_a_failed_run_leaves_the_directory_as_it_was(tmp_path):
    _run(tmp_path, {'cam1.yaml': 'a'})
    with pytest.raises(RuntimeError):
        with OutputDirectory(tmp_path) as out:
            (tmp_path / out.staging / 'cam1.yaml').write_text('half')
            raise RuntimeError('solver failed')
    assert (tmp_path / 'cam1.yaml').read_text() == 'a'
    assert not [p for p in tmp_path.iterdir() if p.name.startswith('.armcal-staging')]


def test_a_concurrent_run_is_refused_with_the_holders_pid(tmp_path):
    with OutputDirectory(tmp_path):
        with pytest.raises(OutputDirError, match=f'another armcal run \\(pid {os.getpid()}\\)'):
            OutputDirectory(tmp_path)
    OutputDirectory(tmp_path).close()        # free again once the first has ended


@pytest.mark.parametrize('case', ['file', 'under_a_file', 'cannot_create'])
def test_unusable_directories_are_refused_with_the_reason(tmp_path, case):
    (tmp_path / 'f').write_text('x')
    path, words = {'file': (tmp_path / 'f', 'not a directory'),
                   'under_a_file': (tmp_path / 'f' / 'out', 'cannot be created'),
                   # Not creatable even by root (tests may run as root, for whom mode bits
                   # do not refuse a write).
                   'cannot_create': ('/proc/armcal_out', 'cannot be created')}[case]
    with pytest.raises(OutputDirError, match=words):
        OutputDirectory(path)
