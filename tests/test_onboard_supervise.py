"""The Ray driver's supervising CLI (pipeline/onboard/supervise.py): exit codes pass through, a driver ended
from outside Python gets one clear line, signals are passed on once, and the driver dies with the CLI."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from conftest import REPO

from pipeline.onboard import supervise as sv


def child(code: str) -> list[str]:
    return [sys.executable, "-c", textwrap.dedent(code)]


def test_a_python_exit_code_passes_through(tmp_path, capfd):
    """A run that ends in Python (here: no such library) keeps its own code and message."""
    code = sv.supervise(["--engine", "ray", str(tmp_path / "missing"), "--store", str(tmp_path / "s")])
    err = capfd.readouterr().err
    assert code == 2 and "library folder not found" in err and "abruptly" not in err  # as without the child


def test_a_driver_ended_from_outside_gets_one_line(capfd):
    code = sv.supervise([], command=child("import os, signal; os.kill(os.getpid(), signal.SIGKILL)"))
    err = capfd.readouterr().err.strip().splitlines()
    assert code == sv.EXIT_DRIVER_LOST
    assert len(err) == 1 and "ended abruptly (signal SIGKILL)" in err[0] and "Traceback" not in err[0]
    assert "head node" in err[0] and "run the same command again" in err[0]


def test_the_ray_log_folder_is_named(capfd):
    code = sv.supervise(
        [],
        command=child(
            f"""
            import os, sys
            sys.path.insert(0, {str(REPO)!r})
            from pipeline.onboard.supervise import note_ray_logs
            note_ray_logs("/somewhere/ray/session_x/logs")
            os._exit(1)  # what Ray's core worker does when its raylet dies
            """
        ),
    )
    err = capfd.readouterr().err
    assert code == sv.EXIT_DRIVER_LOST and "exit code 1" in err and "/somewhere/ray/session_x/logs" in err


def test_each_signal_is_passed_on_once(tmp_path):
    """SIGINT to the CLI reaches the driver exactly once (the first one asks for a graceful stop)."""
    ready = tmp_path / "ready"
    script = child(
        f"""
        import signal, sys, time, pathlib
        sys.path.insert(0, {str(REPO)!r})
        from pipeline.onboard.supervise import note_exit
        got = []
        signal.signal(signal.SIGINT, lambda *a: got.append(1))
        pathlib.Path({str(ready)!r}).write_text("1")
        deadline = time.time() + 20
        while not got and time.time() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)  # a second, duplicated signal would arrive meanwhile
        note_exit(10 + len(got))
        """
    )

    def interrupt_when_ready():
        for _ in range(400):
            if ready.exists():
                os.kill(os.getpid(), signal.SIGINT)
                return
            time.sleep(0.05)

    import threading

    t = threading.Thread(target=interrupt_when_ready)
    t.start()
    previous = signal.getsignal(signal.SIGINT)
    code = sv.supervise([], command=script)
    t.join()
    assert code == 11
    assert signal.getsignal(signal.SIGINT) == previous  # the CLI's own handler is back


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_killing_the_cli_kills_the_driver(tmp_path):
    pid_file = tmp_path / "driver.pid"
    runner = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(REPO)!r})
        from pipeline.onboard.supervise import supervise
        supervise([], command=[sys.executable, "-c",
            "import os, time, pathlib; pathlib.Path({str(pid_file)!r}).write_text(str(os.getpid())); time.sleep(60)"])
        """
    )
    cli = subprocess.Popen([sys.executable, "-c", runner])
    for _ in range(400):
        if pid_file.exists() and pid_file.read_text():
            break
        time.sleep(0.05)
    driver = int(pid_file.read_text())
    cli.kill()
    cli.wait(timeout=10)
    for _ in range(100):
        try:
            os.kill(driver, 0)
        except ProcessLookupError:
            return
        time.sleep(0.05)
    os.kill(driver, signal.SIGKILL)
    pytest.fail("the driver outlived the killed CLI")
