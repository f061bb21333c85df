"""Shared by the live-node benchmark scripts: following the calibrator's /diagnostics."""


def follow_calibration_diagnostics(node):
    """
    Subscribe ``node`` to /diagnostics; return the dict kept equal to the latest calibrator status.

    The dict holds the key/value pairs of the 'armcal: calibration' status, replaced as a whole
    on each message (empty until the first arrives).
    """
    from diagnostic_msgs.msg import DiagnosticArray

    from armcal_ros.ros.conversions import diagnostic_values
    diag = {}

    def on_diag(msg):
        v = diagnostic_values(msg, 'armcal: calibration')
        if v is not None:
            diag.clear()
            diag.update(v)
    node.create_subscription(DiagnosticArray, '/diagnostics', on_diag, 10)
    return diag


def wait_for_diagnostics(diag, timeout=60.0):
    """Wait until ``diag`` (:func:`follow_calibration_diagnostics`) fills; raise if it does not."""
    import time
    deadline = time.monotonic() + timeout
    while not diag and time.monotonic() < deadline:
        time.sleep(0.2)
    if not diag:
        raise RuntimeError(f'the node did not come up (no diagnostics in {timeout:g} s)')


def interrupt(proc, timeout=30.0):
    """SIGINT the node process ``proc`` and wait for it (killed after ``timeout`` s)."""
    import signal
    import subprocess
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
