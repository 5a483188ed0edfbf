"""Explicit Arrow schemas for every table of the store.

Writers always cast to these schemas; nothing is inferred. Embedding tables are partitioned by encoder
(``text_embeddings/<encoder_slug>/``) because each encoder has its own fixed vector width.
"""

from __future__ import annotations

import pyarrow as pa

TS = pa.timestamp("us", tz="UTC")
VEC3 = pa.list_(pa.float64(), 3)
MAT4 = pa.list_(pa.float64(), 16)

DEP = pa.struct([("path", pa.string()), ("size", pa.int64()), ("mtime_ns", pa.int64())])

MESHES = pa.schema(
    [
        pa.field("mesh_id", pa.string(), nullable=False),  # sha256 of the mesh file + every referenced file
        pa.field("source_path", pa.string(), nullable=False),  # path relative to library_root
        pa.field("library_root", pa.string(), nullable=False),
        pa.field("name", pa.string()),  # human-readable model name (parent folder or file stem)
        pa.field("format", pa.string()),
        pa.field("file_size", pa.int64()),
        pa.field("mtime_ns", pa.int64()),
        pa.field("deps", pa.list_(DEP)),  # referenced files (.mtl, textures, .bin) with size and mtime
        pa.field("n_vertices", pa.int64()),
        pa.field("n_faces", pa.int64()),
        pa.field("bounds_min", VEC3),  # in file units
        pa.field("bounds_max", VEC3),
        pa.field("units_guess", pa.string()),  # "m" | "mm"
        pa.field("scale_to_unit", pa.float64()),  # factor that maps the mesh to a unit bounding sphere
        pa.field("status", pa.string(), nullable=False),  # "active" | "removed" | "failed"
        pa.field("seen_at", TS, nullable=False),
        pa.field("run_id", pa.string(), nullable=False),
    ]
)

VIEWS = pa.schema(
    [
        pa.field("mesh_id", pa.string(), nullable=False),
        pa.field("view_index", pa.int16(), nullable=False),
        pa.field("azimuth_deg", pa.float32()),
        pa.field("elevation_deg", pa.float32()),
        pa.field("camera_pose", MAT4),  # camera-to-world, OpenGL convention, row-major
        pa.field("yfov_deg", pa.float32()),
        pa.field("width", pa.int32()),
        pa.field("height", pa.int32()),
        pa.field("image", pa.binary()),  # PNG bytes
        pa.field("fingerprint", pa.string(), nullable=False),
        pa.field("run_id", pa.string(), nullable=False),
    ]
)

CAPTIONS = pa.schema(
    [
        pa.field("mesh_id", pa.string(), nullable=False),
        pa.field("view_index", pa.int16(), nullable=False),
        pa.field("captioner_id", pa.string(), nullable=False),
        pa.field("prompt_style", pa.string()),
        pa.field("prompt", pa.string()),
        pa.field("caption", pa.string()),
        pa.field("fingerprint", pa.string(), nullable=False),
        pa.field("view_fingerprint", pa.string(), nullable=False),
        pa.field("run_id", pa.string(), nullable=False),
    ]
)


VIEW_FEATURES = pa.schema(
    [
        pa.field("mesh_id", pa.string(), nullable=False),
        pa.field("view_index", pa.int16(), nullable=False),
        pa.field("detector_id", pa.string(), nullable=False),  # e.g. "opencv:sift-256@384"
        pa.field("n_keypoints", pa.int32(), nullable=False),
        pa.field("keypoints", pa.list_(pa.float32())),  # x0, y0, x1, y1, ... in the working frame
        pa.field("descriptor_dim", pa.int16(), nullable=False),  # bytes per keypoint (SIFT 128, ORB 32)
        pa.field("descriptors", pa.binary()),  # n_keypoints x descriptor_dim uint8, row-major
        pa.field("fingerprint", pa.string(), nullable=False),  # features config + render fingerprint
        pa.field("source_fingerprint", pa.string(), nullable=False),  # the view's render fingerprint
        pa.field("run_id", pa.string(), nullable=False),
    ]
)


#: the learned view encoder's object patch tokens of each view (:mod:`pipeline.onboard.stages.patches`), read
#: by the open-set verdict's patch agreement (:mod:`pipeline.query.patches`) instead of encoding the view
VIEW_PATCHES = pa.schema(
    [
        pa.field("mesh_id", pa.string(), nullable=False),
        pa.field("view_index", pa.int16(), nullable=False),
        pa.field("encoder_id", pa.string(), nullable=False),  # the learned view encoder's model key
        pa.field("n_patches", pa.int16(), nullable=False),  # the patches that hold the object
        pa.field("dim", pa.int16(), nullable=False),
        pa.field("tokens", pa.binary()),  # n_patches x dim float16, little-endian, row-major, each row L2 = 1
        pa.field("fingerprint", pa.string(), nullable=False),  # encoder, patch settings, render fingerprint
        pa.field("source_fingerprint", pa.string(), nullable=False),  # the view's render fingerprint
        pa.field("run_id", pa.string(), nullable=False),
    ]
)


def embedding_schema(dim: int) -> pa.Schema:
    """Schema of one encoder's partition of ``text_embeddings`` or ``image_embeddings``."""
    return pa.schema(
        [
            pa.field("mesh_id", pa.string(), nullable=False),
            pa.field("view_index", pa.int16(), nullable=False),
            pa.field("encoder_id", pa.string(), nullable=False),
            pa.field("dim", pa.int32(), nullable=False),
            pa.field("embedding", pa.list_(pa.float32(), dim)),  # L2-normalised at write
            pa.field("fingerprint", pa.string(), nullable=False),
            pa.field("source_fingerprint", pa.string(), nullable=False),  # caption or view fingerprint
            pa.field("run_id", pa.string(), nullable=False),
        ]
    )


ERRORS = pa.schema(
    [
        pa.field("run_id", pa.string(), nullable=False),
        pa.field(
            "stage", pa.string(), nullable=False
        ),  # discover | render | caption | embed_text | embed_image | features
        pa.field("mesh_id", pa.string()),
        pa.field("source_path", pa.string()),
        pa.field("fingerprint", pa.string()),
        pa.field("error_type", pa.string()),
        pa.field("reason", pa.string(), nullable=False),
        pa.field("at", TS, nullable=False),
    ]
)

RUNS = pa.schema(
    [
        pa.field("run_id", pa.string(), nullable=False),
        pa.field("engine", pa.string()),
        pa.field("library_root", pa.string()),
        pa.field("profile", pa.string()),
        pa.field("config_json", pa.string()),  # full config incl. model ids and per-stage fingerprints
        pa.field("started_at", TS),
        pa.field("finished_at", TS),
        pa.field("n_files", pa.int64()),
        pa.field("n_added", pa.int64()),
        pa.field("n_removed", pa.int64()),
        pa.field("n_skipped", pa.int64()),
        pa.field("n_failed", pa.int64()),
        pa.field("stage_seconds_json", pa.string()),  # {"discover": s, "render": s, ...}
        pa.field("status", pa.string()),  # "ok" | "interrupted"
    ]
)

#: The per-store query adapter of the learned view encoder (:mod:`pipeline.adapter`): one row per fit; a
#: query uses the latest row whose ``provenance`` matches the models and fingerprints it reads.
ADAPTERS = pa.schema(
    [
        pa.field("encoder_id", pa.string(), nullable=False),  # the learned view encoder's model key
        pa.field("provenance", pa.string(), nullable=False),  # fingerprint of what it was fitted on
        pa.field("view_fingerprint", pa.string(), nullable=False),  # embed_image:learned_encoder step
        pa.field("probe_fingerprint", pa.string(), nullable=False),  # probe step
        pa.field("n_models", pa.int64(), nullable=False),
        pa.field("n_probes", pa.int64(), nullable=False),
        pa.field("dim", pa.int32(), nullable=False),
        pa.field("matrix", pa.binary(), nullable=False),  # dim x dim float32, little-endian, row-major
        pa.field("fit_json", pa.string()),  # FitConfig
        pa.field("seconds", pa.float64()),
        pa.field("run_id", pa.string(), nullable=False),
        pa.field("created_at", TS, nullable=False),
    ]
)

#: Fixed-schema tables; embedding tables are built with :func:`embedding_schema`.
TABLES: dict[str, pa.Schema] = {
    "meshes": MESHES,
    "views": VIEWS,
    "captions": CAPTIONS,
    "view_features": VIEW_FEATURES,
    "view_patches": VIEW_PATCHES,
    "adapters": ADAPTERS,
    "errors": ERRORS,
    "runs": RUNS,
}
#: ``probe_embeddings``: the learned encoder's vectors of probe queries made from views (``view_index``: the
#: view a probe was made from), :mod:`pipeline.adapter.probes`
EMBEDDING_TABLES = ("text_embeddings", "image_embeddings", "probe_embeddings")

#: Row keys: a row with the same key and a later run_id supersedes an earlier one.
KEYS: dict[str, tuple[str, ...]] = {
    "meshes": ("library_root", "source_path", "mesh_id"),
    "views": ("mesh_id", "view_index", "fingerprint"),
    "captions": ("mesh_id", "view_index", "fingerprint"),
    "view_features": ("mesh_id", "view_index", "fingerprint"),
    "view_patches": ("mesh_id", "view_index", "fingerprint"),
    "text_embeddings": ("mesh_id", "view_index", "fingerprint"),
    "image_embeddings": ("mesh_id", "view_index", "fingerprint"),
    "probe_embeddings": ("mesh_id", "view_index", "fingerprint"),
}


def schema_for(table: str, dim: int | None = None) -> pa.Schema:
    """Return the schema of ``table`` (``dim`` is required for embedding tables)."""
    if table in EMBEDDING_TABLES:
        if dim is None:
            raise ValueError(f"{table} needs the embedding dimension")
        return embedding_schema(dim)
    return TABLES[table]


def conform(table: pa.Table, schema: pa.Schema) -> pa.Table:
    """Select and cast ``table``'s columns to ``schema`` (missing nullable columns become nulls)."""
    cols = []
    for field in schema:
        if field.name in table.column_names:
            cols.append(table.column(field.name).cast(field.type))
        elif field.nullable:
            cols.append(pa.nulls(table.num_rows, field.type))
        else:
            raise ValueError(f"column {field.name!r} is required by the schema")
    return pa.Table.from_arrays(cols, schema=schema)
