"""Helpers of the query tests: novel-view queries rendered from meshes, and hand-made stores.

``render_query_view`` renders a mesh from a viewpoint that is not one of the onboarding views (so the
query is not a stored image) and returns the image with the object's mask.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa

GRAY = (205, 205, 205)


def render_query_view(
    mesh_path: str | Path,
    azimuth: float = 20.0,
    elevation: float = 8.0,
    resolution: int = 256,
    fill: float = 0.7,
):
    """(PIL RGB image, bool mask) of ``mesh_path`` seen from (azimuth, elevation), on the onboarding gray."""
    from PIL import Image

    from pipeline.mesh.load import load_mesh
    from pipeline.mesh.render import Renderer
    from pipeline.mesh.settings import RenderConfig

    fmt = Path(mesh_path).suffix.lstrip(".").lower()
    mesh = load_mesh(str(mesh_path), fmt, max_faces=2_000_000)
    # two views on one ring: azimuth 0 and ``azimuth``; the second is the query
    cfg = RenderConfig(
        resolution=resolution,
        fill=fill,
        elevations_deg=(elevation, elevation),
        views_per_ring=1,
        upper_ring_offset_deg=azimuth,
    )
    renderer = Renderer(cfg)
    try:
        view = renderer.render(mesh)[1]
    finally:
        renderer.close()
    img = view.image
    mask = np.any(img != np.asarray(GRAY, dtype=np.uint8), axis=2)
    from scipy import ndimage

    mask = ndimage.binary_fill_holes(mask)
    return Image.fromarray(img), mask


def embedding_table(mesh_ids, view_index, vectors, encoder_id: str, fp: str, run_id: str) -> pa.Table:
    from pipeline import schemas

    vectors = np.asarray(vectors, dtype=np.float32)
    dim = vectors.shape[1]
    return pa.Table.from_pydict(
        {
            "mesh_id": list(mesh_ids),
            "view_index": np.asarray(view_index, dtype=np.int16),
            "encoder_id": [encoder_id] * len(vectors),
            "dim": np.full(len(vectors), dim, np.int32),
            "embedding": pa.FixedSizeListArray.from_arrays(pa.array(vectors.reshape(-1)), dim),
            "fingerprint": [fp] * len(vectors),
            "source_fingerprint": ["src"] * len(vectors),
            "run_id": [run_id] * len(vectors),
        },
        schema=schemas.embedding_schema(dim),
    )


def make_store(
    path: str | Path,
    meshes: dict[str, dict],
    *,
    profile: str = "offline",
    models: dict[str, str | None] | None = None,
    run_id: str = "20250101T000000000000Z-aaaaaa",
    status: str = "ok",
) -> Path:
    """A store written row by row (no rendering, no models).

    ``meshes``: mesh_id -> {"name", "captions": (n, d) vectors, "views": (m, d) vectors, optional
    "status", "source_path", "library_root", "images": list of PIL images for the views, "learned": (m, d)
    learned-encoder vectors of the views (stored under the profile's learned-encoder fingerprint)}.
    """
    from datetime import datetime, timezone

    from pipeline import schemas
    from pipeline.mesh.render import encode_png
    from pipeline.profiles import get_profile
    from pipeline.store import Store, slug

    prof = get_profile(profile)
    if models is None:
        models = {r: (s.key() if s else None) for r, s in prof.roles().items()}
    fps = {
        "render": "fp-render",
        "caption": "fp-caption",
        "embed_text": "fp-text",
        "embed_image:view_encoder": "fp-view",
    }
    now = datetime(2025, 1, 1, tzinfo=timezone.utc)
    store = Store.open(path, create=True)
    mesh_rows, cap_ids, cap_idx, cap_vecs, view_ids, view_idx, view_vecs, view_rows = (
        [],
        [],
        [],
        [],
        [],
        [],
        [],
        [],
    )
    learned_rows = [
        (mesh_id, i, v) for mesh_id, m in meshes.items() for i, v in enumerate(m.get("learned", []))
    ]
    if learned_rows:
        from pipeline.onboard.stages import encoder_fingerprint

        fps["embed_image:learned_encoder"] = encoder_fingerprint(None, prof.learned_encoder, fps["render"])
    for mesh_id, m in meshes.items():
        mesh_rows.append(
            {
                "mesh_id": mesh_id,
                "source_path": m.get("source_path", f"{m['name']}/model.obj"),
                "library_root": m.get("library_root", "/library"),
                "name": m["name"],
                "format": "obj",
                "status": m.get("status", "active"),
                "seen_at": now,
                "run_id": run_id,
            }
        )
        for i, v in enumerate(m.get("captions", [])):
            cap_ids.append(mesh_id)
            cap_idx.append(i)
            cap_vecs.append(v)
        for i, v in enumerate(m.get("views", [])):
            view_ids.append(mesh_id)
            view_idx.append(i)
            view_vecs.append(v)
        for i, im in enumerate(m.get("images", [])):
            view_rows.append(
                {
                    "mesh_id": mesh_id,
                    "view_index": i,
                    "image": encode_png(np.asarray(im)),
                    "fingerprint": "fp-render",
                    "run_id": run_id,
                }
            )
    tables = {"meshes": pa.Table.from_pylist(mesh_rows, schema=schemas.MESHES)}
    if cap_vecs:
        tables[f"text_embeddings/{slug(models['text_encoder'])}"] = embedding_table(
            cap_ids, cap_idx, cap_vecs, models["text_encoder"], fps["embed_text"], run_id
        )
    if view_vecs:
        tables[f"image_embeddings/{slug(models['view_encoder'])}"] = embedding_table(
            view_ids, view_idx, view_vecs, models["view_encoder"], fps["embed_image:view_encoder"], run_id
        )
    if learned_rows:
        ids, idx, vecs = zip(*learned_rows, strict=True)
        tables[f"image_embeddings/{slug(models['learned_encoder'])}"] = embedding_table(
            ids, idx, vecs, models["learned_encoder"], fps["embed_image:learned_encoder"], run_id
        )
    if view_rows:
        tables["views"] = pa.Table.from_pylist(view_rows, schema=schemas.VIEWS)
    config = {"profile": profile, "models": models, "fingerprints": fps}
    run = {"run_id": run_id, "profile": profile, "config_json": json.dumps(config), "status": status}
    tables["runs"] = pa.Table.from_pylist([run], schema=schemas.RUNS)
    store.commit(tables, run_id)
    store.close()
    return Path(path)


def unit(rows) -> np.ndarray:
    rows = np.asarray(rows, dtype=np.float32)
    return rows / np.linalg.norm(rows, axis=-1, keepdims=True)


# ---------------------------------------------------------------------------- fake adapters
WORDS = ("red", "yellow", "blue", "green", "can", "bottle", "box", "banana")
COLOURS = {"red": (200, 30, 30), "yellow": (230, 200, 40), "blue": (40, 60, 200), "green": (40, 160, 60)}


class WordEncoder:
    """Text -> counts of a few words (one axis each, plus a bias axis), L2-normalised."""

    model_id = "fake-words"
    dim = len(WORDS) + 1

    def encode_text(self, texts):
        rows = []
        for t in texts:
            words = t.lower().replace(",", " ").replace(".", " ").split()
            rows.append([words.count(w) for w in WORDS] + [0.5])
        return unit(rows)


def _object_pixels(image) -> np.ndarray:
    arr = np.asarray(image.convert("RGB"), dtype=np.float32)
    fg = np.abs(arr - np.asarray(GRAY, np.float32)).sum(axis=2) > 30
    return arr[fg] if fg.any() else arr.reshape(-1, 3)


class ColourCaptioner:
    """Names the dominant colour and a shape from the aspect ratio of the object's box."""

    model_id = "fake-captioner"

    def caption(self, images, prompt=""):
        out = []
        for im in images:
            mean = _object_pixels(im).mean(axis=0)
            colour = min(COLOURS, key=lambda c: np.linalg.norm(mean - np.asarray(COLOURS[c])))
            w, h = im.size
            shape = "bottle" if h > 1.6 * w else "box" if w > 1.3 * h else "can"
            out.append(f"a {colour} {shape}")
        return out


class ColourDescriptor:
    """Mean object colour + aspect ratio, L2-normalised."""

    model_id = "fake-descriptor"
    dim = 4

    def encode_image(self, images):
        rows = []
        for im in images:
            mean = _object_pixels(im).mean(axis=0) / 255.0
            w, h = im.size
            rows.append([*mean, np.log(h / w)])
        return unit(rows)


class AspectEncoder:
    """A stand-in learned encoder: the object's box aspect ratio only (blind to colour)."""

    model_id = "fake-learned"
    dim = 3

    def encode_image(self, images):
        rows = []
        for im in images:
            arr = np.abs(np.asarray(im.convert("RGB"), np.int16) - 205).sum(axis=2) > 30
            ys, xs = np.nonzero(arr)
            h, w = (np.ptp(ys) + 1, np.ptp(xs) + 1) if len(ys) else im.size[::-1]
            rows.append([np.log(h / w), 1.0, 0.2])
        return unit(rows)


def fake_models() -> dict:
    return {"captioner": ColourCaptioner(), "text_encoder": WordEncoder(), "view_encoder": ColourDescriptor()}


def object_image(colour: str, w: int, h: int, pad: int = 10):
    """An object of ``colour`` and size w x h centred on the onboarding gray."""
    from PIL import Image

    arr = np.zeros((h + 2 * pad, w + 2 * pad, 3), np.uint8)
    arr[:] = GRAY
    arr[pad : pad + h, pad : pad + w] = COLOURS[colour]
    return Image.fromarray(arr)


#: the fake library: name -> (colour, w, h) of its "renders"
FAKE_LIBRARY = {
    "red_can": ("red", 40, 50),
    "yellow_bottle": ("yellow", 30, 70),
    "blue_box": ("blue", 80, 40),
    "green_can": ("green", 40, 50),
}


def make_fake_store(path, library=FAKE_LIBRARY, learned=None, **kw) -> Path:
    """A store of ``library`` embedded with the fake adapters (keys of the offline profile's models), and
    with ``learned`` view vectors too when that stand-in learned encoder is given."""
    models = fake_models()
    meshes = {}
    for name, (colour, w, h) in library.items():
        views = [object_image(colour, w, h), object_image(colour, int(w * 1.1), h)]
        caps = models["captioner"].caption(views)
        meshes[f"id-{name}"] = {
            "name": name,
            "captions": models["text_encoder"].encode_text(caps),
            "views": models["view_encoder"].encode_image(views),
            "images": views,
        }
        if learned is not None:
            meshes[f"id-{name}"]["learned"] = learned.encode_image(views)
    return make_store(path, meshes, **kw)
