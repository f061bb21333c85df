"""The ``armcal`` command run as a user runs it: a subprocess of this interpreter."""
import subprocess
import sys


def armcal(*args, timeout=600):
    """Run ``armcal ARGS``; assert it succeeded; return its standard output."""
    proc = subprocess.run([sys.executable, '-m', 'armcal_ros.cli', *map(str, args)],
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout
