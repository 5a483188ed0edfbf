"""Query sets: a JSONL/CSV file of (image, prompt, box or mask, expected mesh, class label), or a BOP-format
dataset folder mapped to library meshes by object id.

JSONL, one object per line (paths relative to the file's folder)::

    {"query_id": "q1", "image": "images/q1.png", "prompt": "the mustard bottle",
     "box": [x0, y0, x1, y1], "mask": "masks/q1.png",
     "expected": "006_mustard_bottle/textured.obj", "label": "006"}

``expected`` names the expected mesh by path (relative to the library root, or absolute), mesh_id or mesh
name, and may be a list when several meshes are correct. ``expected_mesh_id`` / ``expected_path`` are
accepted too. CSV uses the same column names, with the box as ``x0 y0 x1 y1`` (or columns x0, y0, x1, y1).
"""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

from pipeline.evaluate.records import Query, QueryFileError

__all__ = ["QUERY_FILE_SUFFIXES", "Query", "QueryFileError", "load_queries", "write_queries"]

QUERY_FILE_SUFFIXES = (".jsonl", ".json", ".csv")


def load_queries(path: str | os.PathLike, **bop_options) -> list[Query]:
    """Queries from a JSONL/JSON/CSV file or a BOP-format folder (``bop_options`` go to :func:`load_bop`)."""
    p = Path(path)
    if p.is_dir():
        from pipeline.evaluate.bop import load_bop

        return load_bop(p, **bop_options)
    if not p.is_file():
        raise QueryFileError(f"query file or BOP folder not found: {p}")
    suffix = p.suffix.lower()
    if suffix == ".csv":
        return _from_rows(_csv_rows(p), p)
    if suffix in (".jsonl", ".json"):
        return _from_rows(_json_rows(p), p)
    raise QueryFileError(
        f"{p}: unknown query file type; use {', '.join(QUERY_FILE_SUFFIXES)} or a BOP folder"
    )


def write_queries(queries: list[Query], path: str | os.PathLike) -> None:
    """Write queries as JSONL with paths relative to the file's folder (so the set can be moved)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    base = p.parent.resolve()
    with open(p, "w") as fh:
        for q in queries:
            d = q.to_json()
            d["image"] = _rel(q.image, base)
            d["mask"] = _rel(q.mask, base) if q.mask else None
            fh.write(json.dumps({k: v for k, v in d.items() if v not in (None, {}, [])}) + "\n")


def _rel(path: str, base: Path) -> str:
    try:
        return Path(path).resolve().relative_to(base).as_posix()
    except ValueError:
        return str(path)


def _json_rows(p: Path) -> list[tuple[int, dict]]:
    text = p.read_text()
    if p.suffix.lower() == ".json" and text.lstrip().startswith("["):
        return list(enumerate(json.loads(text), start=1))
    rows = []
    for n, line in enumerate(text.splitlines(), start=1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        try:
            rows.append((n, json.loads(line)))
        except json.JSONDecodeError as exc:
            raise QueryFileError(f"{p}:{n}: not JSON: {exc.msg}") from None
    return rows


def _csv_rows(p: Path) -> list[tuple[int, dict]]:
    with open(p, newline="") as fh:
        reader = csv.DictReader(line for line in fh if not line.lstrip().startswith("#"))
        return [
            (n, {k.strip(): (v or "").strip() for k, v in r.items() if k}) for n, r in enumerate(reader, 2)
        ]


def _parse_box(raw, where: str) -> tuple[float, float, float, float] | None:
    if raw in (None, "", []):
        return None
    vals = raw.replace(",", " ").split() if isinstance(raw, str) else list(raw)
    try:
        box = tuple(float(v) for v in vals)
    except (TypeError, ValueError):
        raise QueryFileError(f"{where}: box must be 4 numbers x0 y0 x1 y1, got {raw!r}") from None
    if len(box) != 4 or box[2] <= box[0] or box[3] <= box[1]:
        raise QueryFileError(f"{where}: box must be x0 y0 x1 y1 with x1 > x0 and y1 > y0, got {raw!r}")
    return box  # type: ignore[return-value]


def _expected(row: dict) -> list[str]:
    out: list[str] = []
    for key in ("expected", "expected_mesh_id", "expected_path"):
        v = row.get(key)
        if isinstance(v, list):
            out.extend(str(x) for x in v if x)
        elif isinstance(v, str):
            out.extend(s.strip() for s in v.split("|") if s.strip())  # CSV: several paths joined by |
        elif v:
            out.append(str(v))
    return out


def _from_rows(rows: list[tuple[int, dict]], p: Path) -> list[Query]:
    base = p.parent.resolve()
    queries = []
    for n, row in rows:
        where = f"{p}:{n}"
        if not isinstance(row, dict):
            raise QueryFileError(f"{where}: expected an object")
        image = row.get("image")
        if not image:
            raise QueryFileError(f"{where}: missing 'image'")
        if not row.get("prompt"):
            raise QueryFileError(f"{where}: missing 'prompt'")
        expected = _expected(row)
        if not expected:
            raise QueryFileError(f"{where}: missing 'expected' (mesh path, mesh_id or name)")
        box_raw = row.get("box")
        if box_raw in (None, "") and all(row.get(k) not in (None, "") for k in ("x0", "y0", "x1", "y1")):
            box_raw = [row["x0"], row["y0"], row["x1"], row["y1"]]
        img = (base / image).resolve()
        if not img.is_file():
            raise QueryFileError(f"{where}: image not found: {img}")
        mask = (base / row["mask"]).resolve() if row.get("mask") else None
        if mask is not None and not mask.is_file():
            raise QueryFileError(f"{where}: mask not found: {mask}")
        known = {"query_id", "image", "prompt", "box", "mask", "label", "meta", "x0", "y0", "x1", "y1"}
        known |= {"expected", "expected_mesh_id", "expected_path"}
        meta = dict(row.get("meta") or {})
        meta.update({k: v for k, v in row.items() if k not in known and v not in (None, "")})
        queries.append(
            Query(
                query_id=str(row.get("query_id") or f"{p.stem}-{n}"),
                image=str(img),
                prompt=str(row["prompt"]),
                expected=expected,
                box=_parse_box(box_raw, where),
                mask=str(mask) if mask else None,
                label=str(row["label"]) if row.get("label") not in (None, "") else None,
                meta=meta,
            )
        )
    ids = [q.query_id for q in queries]
    if len(set(ids)) != len(ids):
        dup = next(i for i in ids if ids.count(i) > 1)
        raise QueryFileError(f"{p}: duplicate query_id {dup!r}")
    return queries
