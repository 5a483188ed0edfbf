"""Data files the package reads at run time, through ``importlib.resources``.

The SQL of the repo's top-level ``sql/`` ships inside the wheel as ``pipeline/_sql`` (``setup.py`` maps
it), so an installed package (``pip install .``, a wheel, an image) needs no checkout. Run from a source
checkout (``PYTHONPATH``, an editable install), the same files are read from ``sql/`` beside the package.
"""

from __future__ import annotations

from functools import cache
from importlib.resources import files
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from importlib.abc import Traversable


@cache
def sql_root() -> Traversable:
    """The folder of the SQL files: ``pipeline/_sql`` when installed, else ``sql/`` of the checkout."""
    shipped = files("pipeline") / "_sql"
    if shipped.is_dir():
        return shipped
    checkout = Path(__file__).resolve().parent.parent / "sql"
    if checkout.is_dir():
        return checkout
    raise FileNotFoundError(
        "the SQL files of the package are missing (neither pipeline/_sql nor a checkout's sql/); "
        "reinstall oscar-pipeline"
    )


def sql_file(name: str) -> Traversable:
    """The resource ``<sql root>/<name>.sql``; ``name`` may include a sub-folder (``audit/short_captions``)."""
    res = sql_root()
    for part in f"{name}.sql".split("/"):
        res = res / part
    return res


def sql_names(folder: str) -> list[str]:
    """Sorted names (without ``.sql``) of the SQL files of a sub-folder, e.g. ``views`` or ``audit``."""
    d = sql_root() / folder
    if not d.is_dir():
        return []
    return sorted(p.name[: -len(".sql")] for p in d.iterdir() if p.name.endswith(".sql") and p.is_file())
