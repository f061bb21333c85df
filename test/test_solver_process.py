"""
The solver's child process: results and errors come back, a dead child is replaced, close ends it.

The functions sent are the standard library's (they pickle by name in any child) and the
engine's own ``calibrate``; the child is a real process started with ``spawn``.
"""
import math
import os
import signal
import threading
import time

import numpy as np
import pytest

from armcal_ros.core.adjustment import SolverSettings
from armcal_ros.core.priors import PriorSettings
from armcal_ros.engine import CalibrationEngine, EngineSettings
from armcal_ros.sim.synthetic import make_problem
from armcal_ros.solver_process import SolverProcess, SolverProcessError
from helpers.point_samples import samples_of as _samples


@pytest.fixture
def proc():
    p = SolverProcess()
    yield p
    p.close()


def _wait_for(cond, timeout=10.0):
    end = time.monotonic() + timeout
    while not cond() and time.monotonic() < end:
        time.sleep(0.02)
    return cond()


def test_a_call_runs_in_another_process_and_its_result_comes_back(proc):
    """The child's pid differs from ours, and one child serves every call."""
    pid = proc.call(os.getpid)
    assert pid != os.getpid()
    assert proc.call(os.getpid) == pid == proc.pid
    assert proc.call(math.hypot, 3.0, 4.0) == 5.0
    assert proc.starts == 1


def test_an_error_in_the_child_is_raised_again_here_with_its_type(proc):
    """A ValueError stays a ValueError (the board solve catches exactly that)."""
    with pytest.raises(ValueError, match='math domain error'):
        proc.call(math.sqrt, -1.0)
    assert proc.call(math.sqrt, 4.0) == 2.0        # the child survived it


def test_a_child_killed_during_a_call_fails_that_call_and_the_next_starts_a_new_one(proc):
    """SIGKILL mid-call: SolverProcessError at once, never a caller waiting forever."""
    first = proc.call(os.getpid)
    outcome = {}

    def run():
        try:
            outcome['value'] = proc.call(time.sleep, 30.0)
        except Exception as exc:  # noqa: B902 - the test looks at whatever it was
            outcome['error'] = exc
    t = threading.Thread(target=run)
    t.start()
    time.sleep(0.5)
    os.kill(first, signal.SIGKILL)
    t.join(10.0)
    assert not t.is_alive()
    assert isinstance(outcome.get('error'), SolverProcessError), outcome
    assert 'ended during the call' in str(outcome['error'])
    second = proc.call(os.getpid)
    assert second != first and proc.starts == 2


def test_close_ends_an_idle_child_and_a_busy_one():
    """Idle: asked to stop; busy: ended by signal, its caller told so."""
    p = SolverProcess()
    pid = p.call(os.getpid)
    p.close()
    assert p.pid is None
    assert _wait_for(lambda: not os.path.exists(f'/proc/{pid}') or
                     open(f'/proc/{pid}/stat').read().split()[2] == 'Z')
    with pytest.raises(SolverProcessError, match='closed'):
        p.call(os.getpid)

    busy = SolverProcess()
    pid = busy.call(os.getpid)
    errors = []
    t = threading.Thread(target=lambda: errors.append(pytest.raises(
        SolverProcessError, busy.call, time.sleep, 30.0)))
    t.start()
    time.sleep(0.5)
    t0 = time.monotonic()
    busy.close(timeout=1.0)
    t.join(10.0)
    assert time.monotonic() - t0 < 5.0 and not t.is_alive() and errors


def _engine(prob):
    eng = CalibrationEngine(EngineSettings([c.name for c in prob.cameras],
                                           PriorSettings('correlated'),
                                           SolverSettings(pixel_sigma=0.3)))
    for c in prob.cameras:
        eng.set_image_size(c.name, c.width, c.height)
    for smp in _samples(prob):
        eng.add_sample(smp)
    return eng


def test_an_engine_solving_in_the_child_gets_the_same_calibration_as_in_process(proc):
    """The same samples, solved here and there: identical cameras (the same arithmetic)."""
    prob = make_problem(80, 4)
    here = _engine(prob).solve()
    eng = _engine(prob)
    eng.run_solver = proc.call
    there = eng.solve()
    assert here.accepted and there.accepted
    for name, c in here.calibration.cameras.items():
        o = there.calibration.cameras[name]
        np.testing.assert_allclose(o.camera.K, c.camera.K, rtol=1e-9)
        np.testing.assert_allclose(o.camera.rotation, c.camera.rotation, atol=1e-12)
        np.testing.assert_allclose(o.camera.translation, c.camera.translation, atol=1e-12)
        np.testing.assert_allclose(o.camera.dist, c.camera.dist, atol=1e-12)
        assert o.n_inliers == c.n_inliers


def _broken(*args, **kwargs):
    raise SolverProcessError('the solver process ended during the call (exit code -9)')


def test_a_background_solve_that_fails_unexpectedly_ends_in_a_reported_outcome():
    """The solver thread must not die silently: the listeners hear a failed outcome."""
    prob = make_problem(40, 5)
    eng = _engine(prob)
    eng.run_solver = _broken
    heard = []
    eng.on_result(heard.append)
    assert eng.maybe_solve_async(force=True)
    assert eng.wait(10.0)
    assert len(heard) == 1 and not heard[0].accepted
    assert 'SolverProcessError' in heard[0].reason and 'exit code -9' in heard[0].reason
    assert eng.current is None and eng.n_solves == 1


def test_a_solve_along_the_recording_that_fails_unexpectedly_is_an_outcome_not_the_end():
    """
    Offline, an error in a solve made while a recording is read ends that solve, not the job.

    ``solve_if_grown`` (``armcal calibrate``'s solves along the bag) reports a failed outcome
    as the node's solver thread does; the next solve due runs as usual.
    """
    prob = make_problem(40, 5)
    eng = CalibrationEngine(EngineSettings([c.name for c in prob.cameras],
                                           PriorSettings('correlated'),
                                           SolverSettings(pixel_sigma=0.3), min_samples=15))
    for c in prob.cameras:
        eng.set_image_size(c.name, c.width, c.height)
    samples = _samples(prob)
    real = eng.run_solver
    eng.run_solver = _broken
    for s in samples[:20]:
        eng.add_sample(s)
    out = eng.solve_if_grown()
    assert out is not None and not out.accepted and out.result is None
    assert out.reason.startswith('solve failed: SolverProcessError'), out.reason
    assert eng.n_solves == 1 and eng.current is None
    eng.run_solver = real
    for s in samples[20:]:
        eng.add_sample(s)
    out = eng.solve_if_grown()
    assert out is not None and out.accepted, out.reason
