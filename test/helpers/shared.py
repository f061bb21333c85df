"""A test recording written once into a folder that several pytest runs share."""
import fcntl
import os
import shutil
from pathlib import Path


def shared_output(folder, name, write):
    """
    Return ``folder/name/out``, written by ``write(path) -> bool`` unless already there.

    Concurrent callers (the pytest-xdist workers, a second run) take ``folder/name.lock`` in
    turn; the first writes into a scratch folder and renames it into place only when
    ``write`` succeeded, so a run that died half-way leaves nothing that looks complete.
    """
    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    done = root / name / 'out'
    with open(root / f'{name}.lock', 'w') as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            scratch = root / f'{name}.partial'
            shutil.rmtree(scratch, ignore_errors=True)
            scratch.mkdir()
            assert write(scratch / 'out'), f'writing the shared {name} failed'
            os.makedirs(root / name, exist_ok=True)
            os.rename(scratch / 'out', done)
            shutil.rmtree(scratch, ignore_errors=True)
    return done
