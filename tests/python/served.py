"""Where a `driftwatch serve` started with `--listen 127.0.0.1:0` listens: the system picks the
port (no race for a free one) and the service prints it ("driftwatch serving ... on
http://ADDR (...")."""

import re
import signal
import subprocess
import time

_SERVING = re.compile(rb"driftwatch serving .* on http://([0-9.]+:[0-9]+) ")


def wait_served(proc, log_path, offset=0, timeout=30.0):
    """The base URL `serve` printed to `log_path` after byte `offset`; None if the process
    ended or said nothing within `timeout` seconds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        with open(log_path, "rb") as f:
            f.seek(offset)
            m = _SERVING.search(f.read())
        if m:
            return "http://" + m.group(1).decode()
        time.sleep(0.05)
    return None


def stop(proc: subprocess.Popen) -> None:
    """SIGTERM, then SIGKILL if the service has not stopped within 20 s."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
