"""The ``oscar`` console command: table-driven dispatch to the ``python -m pipeline.<verb>`` mains."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from conftest import REPO

from pipeline import cli

REPO_ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def test_help_lists_the_verbs_of_this_installation(capsys):
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    for verb in ("onboard", "query", "evaluate", "sql", "compact"):
        assert f"  {verb} " in out
    assert cli.main([]) == 2  # no verb: usage, non-zero


def test_help_imports_nothing_heavy():
    code = (
        "import sys; from pipeline.cli import main; main(['--help']); "
        "heavy = {'torch', 'numpy', 'pyarrow', 'duckdb', 'transformers', 'pyrender'} & set(sys.modules); "
        "sys.exit(sorted(heavy) or 0)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=REPO_ENV, timeout=60)
    assert r.returncode == 0, r.stderr


def test_unknown_and_missing_verbs_are_one_line_errors(capsys, monkeypatch):
    assert cli.main(["frobnicate"]) == 2
    assert capsys.readouterr().err.startswith("error: unknown verb 'frobnicate'")
    monkeypatch.setitem(cli.COMMANDS, "later", ("pipeline.not_written_yet", "a verb of a later version"))
    assert cli.main(["later", "x"]) == 2
    err = capsys.readouterr().err
    assert (
        err.strip()
        == "error: `oscar later` is not available in this installation (no module pipeline.not_written_yet)"
    )
    assert cli.main(["--help"]) == 0
    assert "later" not in capsys.readouterr().out


def test_dispatch_passes_args_and_exit_code(tmp_path, monkeypatch, capsys):
    (tmp_path / "fake_verb.py").write_text(
        "import sys\nprint('argv', sys.argv[1:])\nif __name__ == '__main__':\n    sys.exit(int(sys.argv[-1]))\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(cli.COMMANDS, "fake", ("fake_verb", "test verb"))
    assert cli.main(["fake", "--flag", "3"]) == 3
    assert "argv ['--flag', '3']" in capsys.readouterr().out  # argv[0] is the module's file, as with -m
    assert cli.main(["fake", "0"]) == 0
    assert not sys.argv[0].endswith("fake_verb.py")  # restored


@pytest.mark.parametrize("verb", ["onboard", "query", "evaluate", "sql", "compact"])
def test_every_verb_reaches_its_main(verb):
    r = subprocess.run(
        [sys.executable, "-m", "pipeline", verb, "--help"],
        capture_output=True,
        text=True,
        env=REPO_ENV,
        timeout=60,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("usage:") and f"pipeline.{verb}" in r.stdout
