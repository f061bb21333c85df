"""
Run the bundle adjustment in a separate process, one call at a time.

Why a process and not a thread: the solver is Python and numpy working on many small and
medium arrays, and holds the interpreter for most of a solve.  In the node a solve on a thread
took the interpreter from the front end for seconds at a time, and the front end dropped the
images that arrived meanwhile (docs/BENCHMARKS.md, section "node").  In a child process the
solve runs on another core; the node's solver thread only waits on a pipe, which releases the
interpreter.  The inputs and the result cross the pipe pickled: a few hundred kB of samples in,
a few MB out (the result carries the adjustment's covariance), milliseconds either way.

The child is started with ``spawn`` (never ``fork``: the parent runs DDS threads, and a forked
copy of a threaded process may inherit a held lock), lazily on the first call, and started again
on the next call if it died.  It ignores SIGINT, so that Ctrl-C in a terminal (which signals
the whole process group) stops the parent, which then ends the child, instead of leaving a
traceback from each.  Its BLAS runs single-threaded, like the in-process solve.
"""

import multiprocessing
import signal
import threading
import traceback
from typing import Callable, Optional


class SolverProcessError(RuntimeError):
    """The solver process ended (or could not start) before it returned a result."""


def _serve(conn, after_call):
    """Child: run each ``(fn, args, kwargs)`` received; send ``(ok, value)`` back."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    from threadpoolctl import threadpool_limits
    threadpool_limits(limits=1, user_api='blas')
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return              # the parent is gone
        if job is None:
            return
        fn, args, kwargs = job
        try:
            reply = (True, fn(*args, **kwargs))
        except Exception as exc:  # noqa: B902 - every error goes back to the caller
            reply = (False, exc, traceback.format_exc())
        try:
            conn.send(reply)
        except Exception as exc:  # noqa: B902 - e.g. an exception that does not pickle
            conn.send((False, SolverProcessError(f'{type(exc).__name__}: {exc}'),
                       traceback.format_exc()))
        del reply, job
        if after_call is not None:
            after_call()


class SolverProcess:
    """
    A child process that runs functions for the caller: ``call(fn, *args, **kwargs)``.

    ``fn`` and its arguments must pickle (module-level functions, arrays, dataclasses);
    ``after_call`` (module-level, no arguments) runs in the child after each call, e.g. to give
    freed heap pages back to the system.  Thread safe: concurrent calls wait for each other.
    An exception raised by ``fn`` is raised again in the caller (with the child's traceback
    as its note); a child that dies during a call raises :class:`SolverProcessError`, and the
    next call starts a new one.
    """

    def __init__(self, after_call: Optional[Callable[[], None]] = None):
        self._after_call = after_call
        self._ctx = multiprocessing.get_context('spawn')
        self._lock = threading.Lock()
        self._proc = None
        self._conn = None
        self._closed = False
        #: Children started so far (1 after the first call; more if one died).
        self.starts = 0

    @property
    def pid(self) -> Optional[int]:
        """Return the child's process id (None before the first call or after it ended)."""
        p = self._proc
        return p.pid if p is not None and p.is_alive() else None

    def _start(self):
        parent, child = self._ctx.Pipe()
        proc = self._ctx.Process(target=_serve, args=(child, self._after_call),
                                 name='armcal-solver', daemon=True)
        proc.start()
        child.close()
        self._proc, self._conn = proc, parent
        self.starts += 1

    def _reap(self):
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        if conn is not None:
            conn.close()
        if proc is not None:
            proc.join(1.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
        return None if proc is None else proc.exitcode

    def call(self, fn, *args, **kwargs):
        """Run ``fn(*args, **kwargs)`` in the child and return its result."""
        with self._lock:
            if self._closed:
                raise SolverProcessError('the solver process was closed')
            if self._proc is None or not self._proc.is_alive():
                self._reap()
                self._start()
            conn = self._conn
            try:
                conn.send((fn, args, kwargs))
                reply = conn.recv()
            except (EOFError, OSError, BrokenPipeError) as exc:
                code = self._reap()
                raise SolverProcessError(
                    'the solver process ended during the call (exit code '
                    f'{code}{"" if self._closed else "; a new one starts with the next call"})'
                ) from exc
        if reply[0]:
            return reply[1]
        exc = reply[1]
        if hasattr(exc, 'add_note'):
            exc.add_note('in the solver process:\n' + reply[2])
        raise exc

    def close(self, timeout=1.0):
        """
        End the child; a call running in it is abandoned (its caller gets SolverProcessError).

        Asks the child to stop when it is idle; ends it by signal when it is busy or does not
        stop within ``timeout`` s.
        """
        self._closed = True
        if self._lock.acquire(blocking=False):
            try:
                if self._conn is not None:
                    try:
                        self._conn.send(None)
                    except (OSError, ValueError):
                        pass
                    self._proc.join(timeout)
                self._reap()
            finally:
                self._lock.release()
            return
        proc = self._proc       # busy: the caller's thread reaps it when its pipe breaks
        if proc is not None and proc.is_alive():
            proc.terminate()
            proc.join(timeout)
            if proc.is_alive():
                proc.kill()
