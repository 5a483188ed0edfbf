"""``--queries file.jsonl``: many queries with the models loaded once, one JSON line out per line in.

Input lines: ``{"image": PATH, "prompt": TEXT, "box": [x0, y0, x1, y1] | "x0,y0,x1,y1", "mask": PATH,
"id": ANY}`` (box, mask and id optional, ``query_id`` is accepted for ``id``; relative paths are relative to the JSONL file). Output lines carry
``id`` (the line number when absent) and either the full result or ``error``; a bad line never stops the
batch.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

from pipeline.query.errors import QueryError


def read_queries(path: str | Path) -> Iterator[tuple[object, dict | None, str | None]]:
    """(id, query dict or None, error or None) per non-blank line."""
    path = Path(path)
    base = path.parent
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise QueryError(f"queries file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise QueryError(f"cannot read queries file {path}: {exc}") from None
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            item = json.loads(line)
        except json.JSONDecodeError as exc:
            yield n, None, f"line {n} is not JSON: {exc.msg}"
            continue
        if not isinstance(item, dict):
            yield n, None, f"line {n} must be a JSON object"
            continue
        qid = item.get("id", item.get("query_id", n))
        missing = [k for k in ("image", "prompt") if k not in item]
        if missing:
            yield qid, None, f"line {n} lacks {' and '.join(missing)}"
            continue
        q = {"image": _resolve(base, item["image"]), "prompt": item["prompt"]}
        if item.get("box") is not None:
            q["box"] = item["box"]
        if item.get("mask") is not None:
            q["mask"] = _resolve(base, item["mask"])
        yield qid, q, None


def _resolve(base: Path, value):
    if isinstance(value, str):
        p = Path(value).expanduser()
        return str(p if p.is_absolute() else base / p)
    return value


def run_batch(retriever, queries_path, out, *, progress: bool, **rank_args) -> tuple[int, int]:
    """Answer every line of ``queries_path`` into the text stream ``out``; returns (n_ok, n_failed)."""
    from pipeline.progress import iterate

    items = list(read_queries(queries_path))
    ok = failed = 0
    for qid, q, error in iterate(items, "queries", unit="query", enabled=progress):
        if q is not None:
            try:
                result = retriever.query(
                    q["image"], q["prompt"], box=q.get("box"), mask=q.get("mask"), **rank_args
                )
                line = {"id": qid, **result.to_dict()}
                ok += 1
            except QueryError as exc:
                error = str(exc)
        if error is not None:
            line = {"id": qid, "error": error}
            failed += 1
        out.write(json.dumps(line) + "\n")
        out.flush()
    return ok, failed
