"""Failure gallery: for each query whose top-1 model is wrong, one strip with the query ROI, the expected
model's best view and the top retrieved models' best views, with their scores."""

from __future__ import annotations

import io
from pathlib import Path

TILE = 200
CAPTION_H = 46


def load_views(store_path: str, mesh_ids: set[str]) -> dict[tuple[str, int], bytes]:
    """PNG bytes of the stored views of ``mesh_ids`` (newest render per mesh and view index)."""
    import pyarrow.compute as pc

    from pipeline.store import Store, StoreError

    if not mesh_ids:
        return {}
    try:
        with Store.open(store_path) as store:
            t = store.read(
                "views",
                columns=["mesh_id", "view_index", "image", "run_id"],
                filter=pc.field("mesh_id").isin(sorted(mesh_ids)),
            )
    except StoreError:
        return {}  # the gallery then shows captions without view images
    out: dict[tuple[str, int], tuple[str, bytes]] = {}
    for r in t.to_pylist():
        key = (r["mesh_id"], int(r["view_index"]))
        if key not in out or r["run_id"] > out[key][0]:
            out[key] = (r["run_id"], r["image"])
    return {k: v[1] for k, v in out.items()}


def _tile(image, caption: str):
    from PIL import Image, ImageDraw

    tile = Image.new("RGB", (TILE, TILE + CAPTION_H), "white")
    if image is not None:
        im = image.convert("RGB").copy()
        im.thumbnail((TILE, TILE))
        tile.paste(im, ((TILE - im.width) // 2, (TILE - im.height) // 2))
    else:
        ImageDraw.Draw(tile).text((10, TILE // 2), "(no image)", fill="gray")
    draw = ImageDraw.Draw(tile)
    for i, line in enumerate(caption.split("\n")[:3]):
        draw.text((4, TILE + 2 + 14 * i), line[:34], fill="black")
    return tile


def _fmt(x) -> str:
    return "-" if x is None else f"{x:.3f}"


def write_gallery(
    records, store_path: str, out_dir: Path, limit: int = 24, top: int = 3, library=None
) -> list[dict]:
    """Write one PNG strip per failure (worst first: expected model ranked lowest); return their entries."""
    from PIL import Image

    fails = [r for r in records if r.metrics.get("rank") != 1]  # top-1 misses, whatever the metric set
    fails.sort(key=lambda r: (-(r.metrics.get("rank") or 10**9), r.query.query_id))
    fails = fails[:limit]
    if not fails:
        return []
    need: set[str] = set()
    for r in fails:
        need |= set(r.ranked.ids[:top]) | set(r.rel.instance)
    views = load_views(store_path, need)

    def view(mesh_id: str, idx):
        data = views.get((mesh_id, int(idx) if idx is not None else 0)) or views.get((mesh_id, 0))
        return Image.open(io.BytesIO(data)) if data else None

    out_dir.mkdir(parents=True, exist_ok=True)
    entries = []
    for r in fails:
        rk = r.ranked
        exp_id = sorted(r.rel.instance)[0]
        pos = rk.ids.index(exp_id) if exp_id in rk.ids else None
        exp_view = rk.best_views[pos] if pos is not None else 0
        exp_rank = f"rank {pos + 1}" if pos is not None else "not returned"
        tiles = [
            _tile(r.roi_image, f"query: {r.query.prompt}\n{r.query.query_id}"),
            _tile(
                view(exp_id, exp_view),
                f"EXPECTED ({exp_rank})\n{_name(rk, pos, exp_id, library)}\n"
                f"txt {_fmt(rk.text_scores[pos] if pos is not None else None)} "
                f"img {_fmt(rk.image_scores[pos] if pos is not None else None)}",
            ),
        ]
        for i in range(min(top, len(rk.ids))):
            tiles.append(
                _tile(
                    view(rk.ids[i], rk.best_views[i]),
                    f"#{i + 1} {rk.names[i]}\ntxt {_fmt(rk.text_scores[i])} img {_fmt(rk.image_scores[i])}",
                )
            )
        strip = Image.new("RGB", (TILE * len(tiles) + 4 * (len(tiles) - 1), TILE + CAPTION_H), "#dddddd")
        for i, t in enumerate(tiles):
            strip.paste(t, (i * (TILE + 4), 0))
        name = f"{_safe(r.query.query_id)}.png"
        strip.save(out_dir / name)
        entries.append(
            {
                "query_id": r.query.query_id,
                "prompt": r.query.prompt,
                "file": f"{out_dir.name}/{name}",
                "expected": _name(rk, pos, exp_id, library),
                "expected_rank": pos + 1 if pos is not None else None,
                "retrieved": rk.names[:top],
            }
        )
    return entries


def _name(rk, pos, mesh_id: str, library=None) -> str:
    if pos is not None:
        return rk.names[pos]
    return library.name_of(mesh_id) if library is not None else mesh_id[:12]


def _safe(s: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in s)[:120]
