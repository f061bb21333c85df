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
