"""Load, validate and normalise meshes (any format trimesh reads) for rendering."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.mesh.errors import MeshError  # noqa: F401  (re-exported: callers catch it here)


@dataclass
class LoadedMesh:
    """Normalised geometries (centred at the origin, bounding sphere radius 1, z up) and stats."""

    geometries: list  # trimesh.Trimesh, already transformed
    n_vertices: int
    n_faces: int
    bounds_min: list[float]
    bounds_max: list[float]
    units_guess: str
    scale_to_unit: float
    sample_points: np.ndarray  # up to 4096 normalised vertices, for camera fitting


def load_mesh(
    path: str,
    fmt: str,
    *,
    max_faces: int,
    up: str = "auto",
    max_texture: int = 1024,
    max_texture_pixels: int | None = None,
) -> LoadedMesh:
    """Load ``path``; raise :class:`MeshError` with a one-line reason for unusable meshes.

    Textures the file references must decode and hold at most ``max_texture_pixels`` pixels (a
    decompression-bomb guard): a texture that fails is an error, never a silently untextured mesh. OBJ
    files are checked for truncation (face lines parsed against face lines present, a cut last line).
    """
    import trimesh

    from pipeline.mesh.textures import check_textures, declared_textures, textures_loaded

    _require_file(path)
    textures = declared_textures(path, fmt)
    check_textures(path, textures, max_texture_pixels)
    declared = quick_face_count(path, fmt)
    if declared is not None and declared > max_faces:
        raise MeshError(f"too many faces: {declared:,} > --max-faces {max_faces:,}")
    if fmt == "obj":
        _check_obj_tail(path)
    try:
        with _pixel_limit(max_texture_pixels):
            # not maintain_order: OBJ vertices must split where their UVs differ (tests/test_uv_seams.py)
            loaded = trimesh.load(path, file_type=fmt, process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise MeshError(f"cannot parse {fmt.upper()} file: {_parse_reason(exc, fmt)}") from None
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump(concatenate=False) if isinstance(g, trimesh.Trimesh)]
    elif isinstance(loaded, trimesh.Trimesh):
        geoms = [loaded]
    else:
        geoms = []
    geoms = [g for g in geoms if len(g.faces) > 0 and len(g.vertices) > 0]
    if not geoms:
        raise MeshError("empty mesh: no faces")
    n_faces = int(sum(len(g.faces) for g in geoms))
    n_vertices = int(sum(_positions(g) for g in geoms))
    if fmt == "obj" and declared is not None and n_faces < declared:
        raise MeshError(
            f"truncated or malformed OBJ: {declared:,} face lines but only {n_faces:,} faces parsed"
        )
    if textures and not textures_loaded(geoms):
        raise MeshError(
            f"texture {textures[0]!r} was not applied (unsupported or corrupt image?): refusing a blank mesh"
        )
    if n_faces > max_faces:
        raise MeshError(f"too many faces: {n_faces:,} > --max-faces {max_faces:,}")
    verts = np.concatenate([np.asarray(g.vertices, dtype=np.float64) for g in geoms])
    if not np.isfinite(verts).all():
        raise MeshError("non-finite (NaN or inf) vertex coordinates")
    area = float(sum(g.area for g in geoms))
    lo, hi = verts.min(axis=0), verts.max(axis=0)
    extent = float(np.max(hi - lo))
    if not np.isfinite(area) or area <= 1e-12 * max(extent, 1e-12) ** 2 or extent <= 0:
        raise MeshError("zero-area mesh: all faces are degenerate")

    rot = up_rotation(fmt, up)
    centre = (lo + hi) / 2.0
    radius = float(np.max(np.linalg.norm(verts - centre, axis=1)))
    scale = 1.0 / radius
    transform = np.eye(4)
    transform[:3, :3] = rot * scale
    transform[:3, 3] = -(rot @ centre) * scale
    for g in geoms:
        g.apply_transform(transform)
        _shrink_texture(g, max_texture)
    pts = (verts - centre) @ rot.T * scale
    if len(pts) > 4096:
        pts = pts[np.linspace(0, len(pts) - 1, 4096).astype(int)]
    return LoadedMesh(
        geometries=geoms,
        n_vertices=n_vertices,
        n_faces=n_faces,
        bounds_min=lo.tolist(),
        bounds_max=hi.tolist(),
        units_guess="mm" if extent > 20.0 else "m",
        scale_to_unit=scale,
        sample_points=pts,
    )


def _require_file(path: str) -> None:
    import os
    import stat

    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise MeshError("mesh file not found (deleted or moved during the run?)") from None
    except OSError as exc:
        raise MeshError(f"cannot read mesh file: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise MeshError("mesh path is not a regular file (FIFO, socket or device?)")


def _parse_reason(exc: Exception, fmt: str) -> str:
    if fmt == "obj" and isinstance(exc, IndexError):
        return f"a face references a vertex that does not exist ({str(exc)[:120]})"
    return f"{type(exc).__name__}: {str(exc)[:160]}"


def _check_obj_tail(path: str) -> None:
    """Raise for an OBJ whose last line was cut (no final newline and an incomplete record)."""
    with open(path, "rb") as fh:
        fh.seek(0, 2)
        size = fh.tell()
        fh.seek(max(0, size - 4096))
        tail = fh.read()
    if not tail or tail.endswith((b"\n", b"\r")):
        return
    last = tail.rsplit(b"\n", 1)[-1].split()
    if not last:
        return
    kind, refs = last[0], last[1:]
    cut = False
    if kind == b"f":
        shapes = {r.count(b"/") for r in refs}
        cut = len(refs) < 3 or any(r.endswith(b"/") or not r.split(b"/")[0] for r in refs) or len(shapes) > 1
    elif kind in (b"v", b"vn"):
        cut = len(refs) < 3
    if cut:
        raise MeshError(
            f"truncated OBJ file: the last line is incomplete ({b' '.join(last)[:60].decode('latin-1')!r})"
        )


class _pixel_limit:
    """Make PIL refuse images above ``limit`` pixels while trimesh decodes textures (glb, embedded)."""

    def __init__(self, limit: int | None):
        self.limit = limit

    def __enter__(self):
        import warnings

        from PIL import Image

        self._old = Image.MAX_IMAGE_PIXELS
        self._warn = warnings.catch_warnings()
        self._warn.__enter__()
        if self.limit:
            Image.MAX_IMAGE_PIXELS = self.limit
            warnings.simplefilter("error", Image.DecompressionBombWarning)
        return self

    def __exit__(self, *exc):
        from PIL import Image

        Image.MAX_IMAGE_PIXELS = self._old
        self._warn.__exit__(*exc)


def quick_face_count(path: str, fmt: str) -> int | None:
    """Face count from the file header (PLY, OFF, binary STL) or a byte scan (OBJ), without parsing.

    Lets a 5M-face mesh fail in milliseconds instead of spending the render timeout on parsing it.
    Returns ``None`` when the count cannot be read cheaply (the full load checks again).
    """
    try:
        with open(path, "rb") as fh:
            if fmt == "ply":
                for _ in range(200):
                    parts = fh.readline().split()
                    if parts[:2] == [b"element", b"face"] and len(parts) == 3:
                        return int(parts[2])
                    if not parts or parts[0] == b"end_header":
                        return None
            elif fmt == "off":
                lines = [
                    ln for ln in (fh.readline() for _ in range(50)) if ln.strip() and not ln.startswith(b"#")
                ]
                head = lines[0].split()
                counts = head[1:] if head[0].upper().endswith(b"OFF") and len(head) > 1 else lines[1].split()
                return int(counts[1])
            elif fmt == "stl":
                head = fh.read(84)
                if len(head) == 84 and not head[:5].lower() == b"solid":
                    return int.from_bytes(head[80:84], "little")
            elif fmt == "obj":
                n, tail = 0, b"\n"
                while chunk := fh.read(1 << 24):
                    n += (tail + chunk).count(b"\nf ")
                    tail = chunk[-2:]
                return n
    except (OSError, ValueError, IndexError):
        return None
    return None


def _positions(geom) -> int:
    """Distinct vertex positions of ``geom``: the file's vertex count, although a vertex on a UV seam is
    loaded once per chart (so ``n_vertices`` means what it meant before the split)."""
    v = np.ascontiguousarray(geom.vertices, dtype=np.float64)
    return len(np.unique(v.view(np.dtype((np.void, v.dtype.itemsize * v.shape[1]))).ravel()))


def up_rotation(fmt: str, up: str) -> np.ndarray:
    """Rotation that makes the mesh z-up (glTF is y-up by specification)."""
    if up == "auto":
        up = "y" if fmt in ("glb", "gltf") else "z"
    if up == "z":
        return np.eye(3)
    if up == "y":
        return np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])  # +90 deg about x: y -> z
    raise MeshError(f"unknown up axis {up!r}")


def _shrink_texture(geom, max_edge: int) -> None:
    """Downscale large textures in place: software GL uploads 4k textures slowly, captions need no more."""
    from PIL import Image

    visual = getattr(geom, "visual", None)
    material = getattr(visual, "material", None)
    if material is None:
        return
    for attr in ("image", "baseColorTexture"):
        img = getattr(material, attr, None)
        if img is not None and hasattr(img, "size") and max(img.size) > max_edge:
            if getattr(img, "format", None) == "JPEG" and getattr(img, "_im", 1) is None:
                img.draft("RGB", (max_edge, max_edge))  # JPEG decodes at 1/2..1/8 scale directly (DCT)
            img = img.convert("RGBA" if img.mode in ("RGBA", "LA", "P") else "RGB")
            factor = max(img.size) // max_edge
            if factor > 1:  # box-average by an integer factor: ~50x faster than a bicubic resize of 4k
                img = img.reduce(factor)
            if max(img.size) > max_edge:
                s = max_edge / max(img.size)
                img = img.resize(
                    (max(1, round(img.size[0] * s)), max(1, round(img.size[1] * s))), Image.BILINEAR
                )
            new = img
            setattr(material, attr, new)
