"""BOP-format datasets as query sets: one query per visible annotated object instance.

A BOP scene folder holds ``scene_gt.json`` (object ids per image), ``scene_gt_info.json`` (``bbox_visib`` as
x, y, w, h and ``visib_fract``), ``mask_visib/<im>_<idx>.png`` and ``rgb/<im>.png|jpg``; a split folder holds
scene folders. Object ids map to library meshes through an objects file::

    {"2": {"mesh": "hope/hope_000002.ply", "prompt": "the bbq sauce bottle", "label": "sauce"}}

(``"2": "hope/hope_000002.ply"`` is enough), or, without one, by BOP's naming: the library mesh whose name
ends in the zero-padded id (``obj_000002``, ``hope_000002``).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

from pipeline.evaluate.library import Library
from pipeline.evaluate.prompts import DEFAULT_PROMPT_TEMPLATE, prompt_for
from pipeline.evaluate.records import Query, QueryFileError


def load_bop(
    folder: str | Path,
    *,
    library: Library | None = None,
    objects: str | Path | None = None,
    prompt_template: str = DEFAULT_PROMPT_TEMPLATE,
    min_visib: float = 0.1,
    max_per_object: int | None = None,
) -> list[Query]:
    """Queries of every annotated instance with ``visib_fract >= min_visib`` (scenes and images sorted)."""
    root = Path(folder)
    scenes = (
        [root]
        if (root / "scene_gt.json").is_file()
        else sorted(d for d in root.iterdir() if d.is_dir() and (d / "scene_gt.json").is_file())
    )
    if not scenes:
        raise QueryFileError(f"{root}: no scene_gt.json here or in its sub-folders (not a BOP folder)")
    mapping = _load_objects(objects) if objects else {}
    per_object: dict[int, int] = {}
    queries: list[Query] = []
    for scene in scenes:
        gt = _read_json(scene / "scene_gt.json")
        info = _read_json(scene / "scene_gt_info.json")
        for im_key in sorted(gt, key=int):
            image = _find_image(scene, int(im_key))
            for idx, inst in enumerate(gt[im_key]):
                obj_id = int(inst["obj_id"])
                meta = (info.get(im_key) or [{}] * (idx + 1))[idx]
                if float(meta.get("visib_fract", 1.0)) < min_visib:
                    continue
                if max_per_object is not None and per_object.get(obj_id, 0) >= max_per_object:
                    continue
                obj = mapping.get(obj_id) or _by_naming(obj_id, library, scene)
                mask = scene / "mask_visib" / f"{int(im_key):06d}_{idx:06d}.png"
                x, y, w, h = meta.get("bbox_visib") or meta.get("bbox_obj") or (0, 0, 0, 0)
                box = (float(x), float(y), float(x + w), float(y + h)) if w > 0 and h > 0 else None
                if box is None and not mask.is_file():
                    continue  # BOP writes bbox -1s for invisible instances
                name = Path(obj["mesh"]).stem if "/" in obj["mesh"] or "." in obj["mesh"] else obj["mesh"]
                if library is not None:
                    keys = library.resolve(obj["mesh"])
                    name = library.name_of(next(iter(keys))) if keys else name
                queries.append(
                    Query(
                        query_id=f"{scene.name}-{int(im_key):06d}-{idx:06d}",
                        image=str(image),
                        prompt=obj.get("prompt") or prompt_for(name, prompt_template),
                        expected=[obj["mesh"]],
                        box=box,
                        mask=str(mask) if mask.is_file() else None,
                        label=obj.get("label"),
                        meta={"obj_id": obj_id, "visib_fract": meta.get("visib_fract")},
                    )
                )
                per_object[obj_id] = per_object.get(obj_id, 0) + 1
    return queries


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise QueryFileError(f"BOP scene {path.parent} has no {path.name}")
    return json.loads(path.read_text())


def _find_image(scene: Path, im_id: int) -> Path:
    for sub in ("rgb", "gray"):
        for ext in (".png", ".jpg", ".jpeg", ".tif"):
            p = scene / sub / f"{im_id:06d}{ext}"
            if p.is_file():
                return p.resolve()
    raise QueryFileError(f"BOP scene {scene}: no rgb/{im_id:06d}.png or .jpg")


def _load_objects(path: str | Path) -> dict[int, dict]:
    data = json.loads(Path(path).read_text())
    out: dict[int, dict] = {}
    for k, v in data.items():
        obj = {"mesh": v} if isinstance(v, str) else dict(v)
        if "mesh" not in obj:
            raise QueryFileError(f"{path}: object {k} has no 'mesh'")
        out[int(str(k).removeprefix("obj_"))] = obj
    return out


def _by_naming(obj_id: int, library: Library | None, scene: Path) -> dict:
    if library is None:
        return {"mesh": f"obj_{obj_id:06d}"}
    pat = re.compile(rf"(?:^|[^0-9])0*{obj_id}$")
    hits = sorted(m.name for m in library.meshes if pat.search(m.name))
    if len(hits) != 1:
        what = "no" if not hits else f"{len(hits)}"
        raise QueryFileError(
            f"BOP scene {scene}: {what} library mesh named like obj_{obj_id:06d}; pass an objects file "
            "(--bop-objects) mapping object ids to meshes"
        )
    return {"mesh": hits[0]}
