"""Printing query results as an aligned table, CSV, JSON or Markdown.

Cells are made readable, not lossless: PNG bytes print as ``<blob 1234 B>`` and long vectors are cut
(use Python or an exported DuckDB file for the raw values).
"""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
from collections.abc import Sequence

FORMATS = ("table", "csv", "json", "markdown")
MAX_LIST_ITEMS = 6


def _scalar(value: object) -> object:
    """A JSON-ready version of one value (blobs and long lists summarised)."""
    if isinstance(value, (bytes, bytearray, memoryview)):
        return f"<blob {len(bytes(value))} B>"
    if isinstance(value, float):
        return float(f"{value:.6g}")
    if isinstance(value, (dt.datetime, dt.date, dt.time)):
        return value.isoformat()
    if isinstance(value, dt.timedelta):
        return value.total_seconds()
    if isinstance(value, dict):
        return {str(k): _scalar(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        if len(value) > MAX_LIST_ITEMS:
            head = [_scalar(v) for v in value[:MAX_LIST_ITEMS]]
            return head + [f"... {len(value)} items"]
        return [_scalar(v) for v in value]
    if value is None or isinstance(value, (bool, int, str)):
        return value
    return str(value)


def _text(value: object, null: str) -> str:
    v = _scalar(value)
    if v is None:
        return null
    if isinstance(v, (list, dict)):
        return json.dumps(v, ensure_ascii=False)
    return str(v)


def _cut(text: str, width: int) -> str:
    text = text.replace("\n", " ")
    return text if width <= 0 or len(text) <= width else text[: max(1, width - 1)] + "…"


def render(
    columns: Sequence[str], rows: Sequence[Sequence[object]], fmt: str = "table", max_width: int = 60
) -> str:
    """``rows`` (tuples in ``columns`` order) formatted as ``fmt``."""
    if fmt == "csv":
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        w.writerow(columns)
        w.writerows([_text(v, "") for v in r] for r in rows)
        return buf.getvalue().rstrip("\n")
    if fmt == "json":
        records = [{c: _scalar(v) for c, v in zip(columns, r, strict=True)} for r in rows]
        return json.dumps(records, indent=2, ensure_ascii=False)
    cells = [[_cut(_text(v, "NULL"), max_width) for v in r] for r in rows]
    if fmt == "markdown":
        esc = [[c.replace("|", "\\|") for c in r] for r in [list(columns), *cells]]
        lines = ["| " + " | ".join(esc[0]) + " |", "|" + "|".join("---" for _ in columns) + "|"]
        lines += ["| " + " | ".join(r) + " |" for r in esc[1:]]
        return "\n".join(lines)
    if fmt != "table":
        raise ValueError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")
    widths = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(columns)]
    line = "  ".join(c.ljust(w) for c, w in zip(columns, widths, strict=True)).rstrip()
    out = [line, "  ".join("-" * w for w in widths)]
    out += ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)).rstrip() for r in cells]
    out.append(f"({len(rows)} row{'s' if len(rows) != 1 else ''})")
    return "\n".join(out)
