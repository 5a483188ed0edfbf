"""``--explain out.png``: a contact sheet of the ROI and, per top candidate, its best-matching view."""

from __future__ import annotations

import io
import textwrap
from pathlib import Path

from PIL import Image, ImageDraw, ImageFont

from pipeline.query.errors import QueryError
from pipeline.query.results import QueryResult

TILE = 256
TEXT_H = 92
PAD = 8


def _fit(img: Image.Image, size: int = TILE) -> Image.Image:
    img = img.convert("RGB")
    img.thumbnail((size, size), Image.BILINEAR)
    tile = Image.new("RGB", (size, size), (255, 255, 255))
    tile.paste(img, ((size - img.width) // 2, (size - img.height) // 2))
    return tile


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1
        return ImageFont.load_default()


def contact_sheet(result: QueryResult, views: list[dict]) -> Image.Image:
    """The sheet as an image: ROI first, then one column per candidate (best view, scores, caption)."""
    by_key = {(v["mesh_id"], v["view_index"]): v for v in views}
    tiles = []
    roi = getattr(result, "roi", None)
    roi_img = roi.image if roi is not None else Image.new("RGB", (TILE, TILE), (205, 205, 205))
    caption = (result.query.get("embedding") or {}).get("roi_caption") or ""
    tiles.append((_fit(roi_img), ["query ROI", repr(result.query.get("prompt", ""))[:40], caption]))
    for c in result.candidates:
        v = by_key.get((c.mesh_id, c.best_view))
        img = Image.open(io.BytesIO(v["image"])) if v is not None else Image.new("RGB", (TILE, TILE), "white")
        text = "-" if c.text_score is None else f"{c.text_score:.3f}"
        image = "-" if c.image_score is None else f"{c.image_score:.3f}"
        tiles.append(
            (
                _fit(img),
                [
                    f"#{c.rank} {c.name}"[:36],
                    f"text {text}  image {image}  view {c.best_view}",
                    (v or {}).get("caption") or "",
                ],
            )
        )
    sheet = Image.new("RGB", (PAD + len(tiles) * (TILE + PAD), PAD * 2 + TILE + TEXT_H), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    bold, small = _font(15), _font(11)
    for i, (tile, (title, scores, cap)) in enumerate(tiles):
        x = PAD + i * (TILE + PAD)
        sheet.paste(tile, (x, PAD))
        y = PAD + TILE + 4
        draw.text((x, y), title, fill=(0, 0, 0), font=bold)
        draw.text((x, y + 19), scores, fill=(40, 40, 40), font=small)
        for j, line in enumerate(textwrap.wrap(cap, 44)[:4]):
            draw.text((x, y + 35 + 13 * j), line, fill=(90, 90, 90), font=small)
    return sheet


def write_explain(result: QueryResult, views: list[dict], path: str | Path) -> Path:
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        contact_sheet(result, views).save(path)
    except (OSError, ValueError) as exc:
        raise QueryError(f"cannot write the contact sheet {path}: {exc}") from None
    return path
