"""
An output directory that a run replaces as a whole: checked first, locked, written, committed.

``armcal calibrate`` writes a set of files (``<camera>.yaml``, ``extrinsics.yaml``,
``calibration.json``, ``report.json``, ``epochs/...``).  Files of an earlier run that this run
does not write (a camera it no longer calibrates) must not stay beside the new
``extrinsics.yaml`` as if they belonged to it, a second run into the same directory must not
interleave its files with the first's, and a run that fails or is interrupted must leave the
directory as it was.  So:

1. before any work the directory is checked (it exists or can be created, is a directory, is
   writable) and locked (``.armcal.lock``, an advisory ``flock``: a concurrent run is refused
   with the holder's pid);
2. the run writes into a staging directory inside it (``.armcal-staging-<pid>``);
3. :meth:`OutputDirectory.commit` removes the files the previous run listed in its manifest
   (``.armcal_files.json``) that this run does not write, moves the new files into place (each
   ``os.replace`` is atomic) and writes the manifest last.  SIGINT is held off during those
   renames (milliseconds) so that Ctrl-C never leaves half a set.

Files the directory holds that no run of armcal wrote are never touched.
"""

import fcntl
import json
import os
import shutil
import signal
import threading

MANIFEST = '.armcal_files.json'
LOCK = '.armcal.lock'
#: What an armcal run wrote before manifests existed (a directory's first run of this version
#: then still removes a camera file the earlier run wrote and this one does not).
_LEGACY = ('extrinsics.yaml', 'calibration.json', 'report.json', 'samples.npz',
           'changes.json', 'target.yaml')


class OutputDirError(ValueError):
    """The output directory cannot be used; the message says which and why."""


class OutputDirectory:
    """
    A checked, locked output directory with a staging area; use as a context manager.

    ``staging`` is where the run writes; :meth:`commit` puts its files in place.  Leaving the
    context without a commit (an error, Ctrl-C) removes the staging area and leaves the
    directory as it was.
    """

    def __init__(self, path):
        self.path = os.path.abspath(os.fspath(path))
        self.staging = None
        self._lock_fd = None
        self._check_and_lock()

    def _check_and_lock(self):
        p = self.path
        if os.path.exists(p) and not os.path.isdir(p):
            raise OutputDirError(f'--output {p} exists and is not a directory')
        try:
            os.makedirs(p, exist_ok=True)
        except OSError as exc:
            raise OutputDirError(f'--output {p} cannot be created: {exc.strerror or exc}') \
                from None
        if not os.access(p, os.W_OK | os.X_OK):
            raise OutputDirError(f'--output {p} is not writable')
        try:
            fd = os.open(os.path.join(p, LOCK), os.O_RDWR | os.O_CREAT, 0o644)
        except OSError as exc:
            raise OutputDirError(f'--output {p} is not writable: {exc.strerror or exc}') \
                from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.read(fd, 32).decode(errors='replace').strip() or 'unknown'
            os.close(fd)
            raise OutputDirError(f'--output {p} is being written by another armcal run (pid '
                                 f'{holder}); wait for it to end or choose another directory') \
                from None
        os.ftruncate(fd, 0)
        os.write(fd, str(os.getpid()).encode())
        self._lock_fd = fd
        self.staging = os.path.join(p, f'.armcal-staging-{os.getpid()}')
        shutil.rmtree(self.staging, ignore_errors=True)
        os.makedirs(self.staging)

    def previous_files(self):
        """Return the files (relative paths) the previous run wrote here."""
        try:
            with open(os.path.join(self.path, MANIFEST), encoding='utf-8') as f:
                return [str(x) for x in json.load(f)['files']]
        except (OSError, ValueError, KeyError, TypeError):
            pass
        out = [n for n in _LEGACY if os.path.exists(os.path.join(self.path, n))]
        try:
            with open(os.path.join(self.path, 'calibration.json'), encoding='utf-8') as f:
                out += [f'{name}.yaml' for name in json.load(f)['cameras']]
        except (OSError, ValueError, KeyError, TypeError):
            pass
        return out

    def commit(self):
        """
        Replace the previous run's files by the staged ones; return the new files' paths.

        A previous file this run does not write is removed; then each staged file is moved into
        place and the manifest written.
        """
        new = []
        for root, _, files in os.walk(self.staging):
            for name in files:
                new.append(os.path.relpath(os.path.join(root, name), self.staging))
        new.sort()
        stale = [f for f in self.previous_files() if f not in set(new)]
        with _sigint_held():
            for rel in stale:
                target = os.path.join(self.path, rel)
                if os.path.isfile(target):
                    os.remove(target)
                    _remove_empty_parents(os.path.dirname(target), self.path)
            for rel in new:
                target = os.path.join(self.path, rel)
                os.makedirs(os.path.dirname(target), exist_ok=True)
                os.replace(os.path.join(self.staging, rel), target)
            tmp = os.path.join(self.path, MANIFEST + '.tmp')
            with open(tmp, 'w', encoding='utf-8') as f:
                json.dump({'files': new}, f, indent=1)
            os.replace(tmp, os.path.join(self.path, MANIFEST))
        return [os.path.join(self.path, rel) for rel in new]

    def close(self):
        """Remove the staging area and release the lock."""
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None
        if self._lock_fd is not None:
            fcntl.flock(self._lock_fd, fcntl.LOCK_UN)
            os.close(self._lock_fd)
            self._lock_fd = None

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        self.close()
        return False


def _remove_empty_parents(directory, stop):
    while os.path.abspath(directory) != os.path.abspath(stop):
        try:
            os.rmdir(directory)
        except OSError:
            return
        directory = os.path.dirname(directory)


class _sigint_held:
    """Defer SIGINT (main thread only) until the block ends, then raise KeyboardInterrupt."""

    def __enter__(self):
        self.pressed = False
        self.old = None
        if threading.current_thread() is threading.main_thread():
            self.old = signal.signal(signal.SIGINT, self._note)
        return self

    def _note(self, signum, frame):
        self.pressed = True

    def __exit__(self, exc_type, exc, tb):
        if self.old is not None:
            signal.signal(signal.SIGINT, self.old)
        if self.pressed and exc_type is None:
            raise KeyboardInterrupt
        return False
