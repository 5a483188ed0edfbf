"""``--torch-threads`` and the fast paths of the query/serve CLIs (no torch import for --help)."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest
from conftest import REPO

from pipeline.serve.cli import build_parser, check_args, is_loopback
from pipeline.threads import default_query_threads, positive_int


def run_py(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *code], capture_output=True, text=True, timeout=300, cwd=REPO)


def test_positive_int_and_default():
    assert positive_int("3") == 3
    for bad in ("0", "-1", "x", "1.5"):
        with pytest.raises(argparse.ArgumentTypeError):
            positive_int(bad)
    assert 1 <= default_query_threads() <= 4


def test_torch_threads_before_torch_is_imported():
    out = run_py(
        [
            "-c",
            "import os; from pipeline.threads import apply_torch_threads as a; a(2); "
            "import torch; print(torch.get_num_threads(), os.environ['OPENBLAS_NUM_THREADS'])",
        ]
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["2", "2"]


def test_torch_threads_applied_once():
    out = run_py(
        [
            "-c",
            "import torch; from pipeline.threads import apply_torch_threads as a; "
            "print(a(3), a(1), torch.get_num_threads())",
        ]
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["3", "3", "3"]


@pytest.mark.parametrize("module", ["pipeline.query", "pipeline.serve"])
def test_help_imports_no_torch(module):
    out = run_py(["-X", "importtime", "-m", module, "--help"])
    assert out.returncode == 0 and "--torch-threads" in out.stdout
    imported = {line.rsplit("|", 1)[-1].strip() for line in out.stderr.splitlines() if "|" in line}
    assert not imported & {"torch", "duckdb", "pyarrow", "fastapi", "uvicorn", "scipy"}, imported


def test_bad_torch_threads_is_a_usage_error():
    out = run_py(
        ["-m", "pipeline.query", "--store", "x", "--image", "y", "--prompt", "z", "--torch-threads", "0"]
    )
    assert out.returncode == 2 and "--torch-threads" in out.stderr and "Traceback" not in out.stderr


def test_serve_refuses_a_public_bind_without_token():
    p = build_parser()
    assert check_args(p.parse_args(["s"])) is None
    assert "token" in check_args(p.parse_args(["s", "--host", "0.0.0.0"]))
    assert check_args(p.parse_args(["s", "--host", "0.0.0.0", "--token", "t"])) is None
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("192.168.1.2") and not is_loopback("example.org")
