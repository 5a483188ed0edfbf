"""The Ray driver in a child process, so that a run whose driver Ray ends abruptly still says why.

When the head node, or the raylet the driver is attached to, dies, Ray's core worker ends the driver's
process at once: no exception reaches Python, so the run could print neither a message nor an exit code of
its own. With ``--engine ray`` the CLI therefore runs the onboarding in a child process (the same command,
marked by ``OSCAR_ONBOARD_CHILD``) and waits for it. The child records its exit code in a small status file
just before it returns (and the Ray log folder once connected). A child that ends without recording one was
ended from outside Python: the CLI prints one line naming the likely cause, that the store keeps every
commit, and where Ray's logs are, and exits :data:`EXIT_DRIVER_LOST`.

Signals behave as without the child: it runs in its own process group, the CLI passes each SIGINT or
SIGTERM it gets on once (a terminal's Ctrl-C reaches the CLI's whole foreground group, so the child would
otherwise count one Ctrl-C twice and stop at once instead of after the running step), and the child dies
with the CLI (``PR_SET_PDEATHSIG`` on Linux), so killing the driver's process still kills the run.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD_ENV = "OSCAR_ONBOARD_CHILD"
STATUS_ENV = "OSCAR_ONBOARD_STATUS"
#: the CLI's exit code when the driver was ended from outside (BSD's EX_TEMPFAIL: try again later)
EXIT_DRIVER_LOST = 75
DEFAULT_RAY_LOGS = "/tmp/ray/session_latest/logs"


def is_child() -> bool:
    return os.environ.get(CHILD_ENV) == "1"


def _record(**fields) -> None:
    """Merge ``fields`` into the status file the supervising CLI reads (no-op outside a child)."""
    path = os.environ.get(STATUS_ENV)
    if not path or not is_child():
        return
    try:
        known = json.loads(Path(path).read_text() or "{}")
    except (OSError, ValueError):
        known = {}
    tmp = f"{path}.{os.getpid()}.tmp"
    try:
        Path(tmp).write_text(json.dumps({**known, **fields}))
        os.replace(tmp, path)
    except OSError:
        pass


def note_ray_logs(directory: str) -> None:
    """Tell the supervising CLI where this Ray session's logs are (called once connected)."""
    _record(ray_logs=directory)


def note_exit(code: int) -> None:
    """Tell the supervising CLI that the run ended in Python with ``code``."""
    _record(exit=int(code))


def _child_setup() -> None:  # runs in the child between fork and exec
    os.setpgid(0, 0)  # its own process group: terminal signals reach only the CLI, which passes them on
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass  # not Linux: a killed CLI leaves its driver running, as a plain process would not


def supervise(argv: list[str], command: list[str] | None = None) -> int:
    """Run ``python -m pipeline.onboard ARGV`` (or ``command``) as a child and return its exit code, or
    print why it ended abruptly and return :data:`EXIT_DRIVER_LOST`."""
    fd, status = tempfile.mkstemp(prefix="oscar-onboard-", suffix=".json")
    os.close(fd)
    env = {**os.environ, CHILD_ENV: "1", STATUS_ENV: status}
    cmd = command or [sys.executable, "-m", "pipeline.onboard", *argv]
    proc = subprocess.Popen(cmd, env=env, preexec_fn=_child_setup)  # noqa: PLW1509
    forwarded = {}

    def forward(signum, _frame):
        if proc.poll() is None:
            proc.send_signal(signum)

    for s in (signal.SIGINT, signal.SIGTERM):
        forwarded[s] = signal.signal(s, forward)
    try:
        code = proc.wait()
    finally:
        for s, handler in forwarded.items():
            signal.signal(s, handler)
    try:
        info = json.loads(Path(status).read_text() or "{}")
    except (OSError, ValueError):
        info = {}
    finally:
        Path(status).unlink(missing_ok=True)
    if "exit" in info:
        return int(info["exit"])
    how = f"signal {signal.Signals(-code).name}" if code < 0 else f"exit code {code}"
    logs = info.get("ray_logs") or f"{DEFAULT_RAY_LOGS} on the head node"
    print(
        f"error: the Ray driver ended abruptly ({how}): the head node or its raylet was most likely lost; "
        f"everything committed so far is kept and the store is consistent: run the same command again "
        f"once the cluster is back (Ray logs: {logs})",
        file=sys.stderr,
    )
    return EXIT_DRIVER_LOST
