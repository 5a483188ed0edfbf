"""Drift checks for the lock files and what is built or installed from them (used by install.sh, lock.sh, CI).

  python scripts/check_lock.py pyproject            # every pyproject requirement is met by its set's lock
  python scripts/check_lock.py env dev ray          # this interpreter has exactly the pins of those locks
  python scripts/check_lock.py sync dev ray         # uninstall what those locks do not pin, then `env`
  python scripts/check_lock.py wheel dist/X.whl     # the wheel holds every sql/**/*.sql, py.typed, modules

Exits 1 with one line per problem. ``env`` must run with the venv's interpreter (it reads that
environment's installed distributions); it needs ``packaging``, which every lock pins.
"""

from __future__ import annotations

import re
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LOCK_DIR = ROOT / "requirements"
SETS = ("base", "dev", "ray", "paper")
CUDA = re.compile(r"^(nvidia-|triton$|cuda-)")
# installer tooling and the project itself: never removed by `sync` (their pins, if any, are still checked)
NOT_LOCKED = {"pip", "setuptools", "wheel", "oscar-pipeline"}


def norm(name: str) -> str:
    """PEP 503 normalised project name."""
    return re.sub(r"[-_.]+", "-", name).lower()


def read_lock(name: str) -> dict[str, str]:
    """``{normalised name: version}`` of ``requirements/<name>.txt``."""
    pins: dict[str, str] = {}
    for line in (LOCK_DIR / f"{name}.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line or line.startswith("-"):
            continue
        m = re.fullmatch(r"([A-Za-z0-9][A-Za-z0-9._-]*)(\[[^\]]*\])?==([^\s;]+)", line)
        if not m:
            raise SystemExit(f"error: requirements/{name}.txt: not an exact pin: {line!r}")
        pins[norm(m.group(1))] = m.group(3)
    return pins


def check_pyproject() -> list[str]:
    """Problems: a pyproject requirement that its set's lock does not meet, or a CUDA package in a lock."""
    import tomllib
    from packaging.requirements import Requirement
    from packaging.version import Version

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    env = {"python_version": "3.11", "python_full_version": "3.11.7", "sys_platform": "linux"}
    env |= {"platform_system": "Linux", "platform_machine": "x86_64", "os_name": "posix"}
    problems = []
    for s in SETS:
        pins = read_lock(s)
        reqs = project["dependencies"] + (project["optional-dependencies"][s] if s != "base" else [])
        for text in reqs:
            req = Requirement(text)
            if req.marker is not None and not req.marker.evaluate(env | {"extra": s}):
                continue
            version = pins.get(norm(req.name))
            if version is None:
                problems.append(
                    f"requirements/{s}.txt lacks {req.name} (pyproject: {text}); run scripts/lock.sh"
                )
            elif not req.specifier.contains(Version(version), prereleases=True):
                problems.append(f"requirements/{s}.txt pins {req.name}=={version}, pyproject wants {text}")
        problems += [f"requirements/{s}.txt pins a CUDA package: {n}" for n in pins if CUDA.match(n)]
    return problems


def check_env(sets: list[str]) -> list[str]:
    """Problems: installed distributions that differ from the union of ``sets``' locks, either way."""
    from importlib.metadata import distributions

    from packaging.specifiers import SpecifierSet
    from packaging.version import Version

    want: dict[str, str] = {}
    for s in sets:
        want |= read_lock(s)
    have = {norm(d.metadata["Name"]): d.version for d in distributions() if d.metadata["Name"]}
    problems = []
    for name, version in sorted(want.items()):
        got = have.get(name)
        if got is None:
            problems.append(f"missing: {name}=={version}")
        elif not SpecifierSet(f"=={version}").contains(Version(got), prereleases=True):
            problems.append(f"drift: {name} {got} installed, lock has {version}")  # 2.13.0+cpu meets ==2.13.0
    for name, version in sorted(have.items()):
        if name not in want and name not in NOT_LOCKED:
            hint = (
                " (a CUDA build of torch? set TORCH_INDEX_URL, docs/install.md)" if CUDA.match(name) else ""
            )
            problems.append(f"not in the lock: {name}=={version}{hint}")
    return problems


def sync_env(sets: list[str]) -> None:
    """Uninstall the distributions that ``sets``' locks do not pin (a refreshed lock dropped them)."""
    import subprocess
    from importlib.metadata import distributions

    want: dict[str, str] = {}
    for s in sets:
        want |= read_lock(s)
    extra = sorted(
        {norm(d.metadata["Name"]) for d in distributions() if d.metadata["Name"]} - set(want) - NOT_LOCKED
    )
    if extra:
        print(f"[check] removing what the lock does not pin: {' '.join(extra)}", file=sys.stderr)
        subprocess.run([sys.executable, "-m", "pip", "uninstall", "-q", "-y", *extra], check=True)


def check_wheel(path: str) -> list[str]:
    """Problems: a file of ``sql/``, a module of ``pipeline/``, ``py.typed`` or the ``oscar`` script
    missing from the wheel."""
    names = set(zipfile.ZipFile(path).namelist())
    expected = [
        f"pipeline/_sql/{p.relative_to(ROOT / 'sql').as_posix()}" for p in (ROOT / "sql").rglob("*.sql")
    ]
    expected += [p.relative_to(ROOT).as_posix() for p in (ROOT / "pipeline").rglob("*.py")]
    expected.append("pipeline/py.typed")
    problems = [f"{path}: missing {e}" for e in sorted(expected) if e not in names]
    entry_points = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
    text = zipfile.ZipFile(path).read(entry_points[0]).decode() if entry_points else ""
    if not re.search(r"^oscar\s*=\s*pipeline\.cli:main", text, re.M):
        problems.append(f"{path}: no `oscar` console script")
    n_sql = sum(1 for n in names if n.startswith("pipeline/_sql/") and n.endswith(".sql"))
    print(f"[check] wheel: {len(names)} files, {n_sql} SQL files", file=sys.stderr)
    return problems


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in ("pyproject", "env", "sync", "wheel"):
        print(__doc__, file=sys.stderr)
        return 2
    cmd, args = argv[0], argv[1:]
    if cmd == "pyproject":
        problems = check_pyproject()
    elif cmd in ("env", "sync"):
        bad = [s for s in args if s not in SETS]
        if bad or not args:
            print(f"error: sets must be among {', '.join(SETS)}", file=sys.stderr)
            return 2
        if cmd == "sync":
            sync_env(args)
        problems = check_env(args)
    else:
        problems = [p for w in args for p in check_wheel(w)] if args else ["no wheel given"]
    for p in problems:
        print(f"[check] error: {p}", file=sys.stderr)
    if not problems:
        print(f"[check] {cmd}: ok", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
