"""Texture checks before a mesh is rendered: every colour texture must decode and stay under a pixel limit.

trimesh swallows texture errors (a corrupt PNG, or one PIL refuses as a decompression bomb) and returns
an untextured mesh, which renders white and is captioned "a white object". These checks turn that into
a one-line :class:`~pipeline.mesh.load.MeshError` (an errors row) that names the file.
"""

from __future__ import annotations

import json
import os
import re
import struct
from pathlib import Path

_MAP_KD = re.compile(r"^\s*map_Kd\s+(.+?)\s*$", re.IGNORECASE)
EMBEDDED = "<embedded image>"


def declared_textures(path: str, fmt: str) -> list[str]:
    """Colour textures ``path`` references: file paths relative to its folder, or ``EMBEDDED`` entries."""
    from pipeline.mesh.discover import _obj_mtllibs, _ply_textures, open_regular

    base = Path(path).parent
    out: list[str] = []
    try:
        if fmt == "obj":
            for mtl in _obj_mtllibs(Path(path)):
                mtl_path = base / mtl
                if not mtl_path.is_file():
                    continue  # discovery reports missing material files
                with open_regular(mtl_path) as fh:
                    for line in fh.read().decode("utf-8", "replace").splitlines():
                        m = _MAP_KD.match(line)
                        if m:
                            tex = m.group(1).split()[-1]
                            out.append(os.path.relpath(mtl_path.parent / tex, base))
        elif fmt == "ply":
            out = _ply_textures(Path(path))
        elif fmt in ("gltf", "glb"):
            doc = _gltf_json(path, fmt)
            for img in doc.get("images", []):
                uri = img.get("uri")
                out.append(uri if uri and not uri.startswith("data:") else EMBEDDED)
    except (OSError, ValueError):
        return out  # the loader reports unreadable files
    return list(dict.fromkeys(out))


def _gltf_json(path: str, fmt: str) -> dict:
    with open(path, "rb") as fh:
        if fmt == "gltf":
            return json.loads(fh.read().decode("utf-8"))
        head = fh.read(20)
        if len(head) < 20 or head[:4] != b"glTF":
            return {}
        length, kind = struct.unpack("<II", head[12:20])
        if kind != 0x4E4F534A or length > 64 << 20:  # "JSON" chunk, sane size
            return {}
        return json.loads(fh.read(length).decode("utf-8"))


def check_textures(path: str, textures: list[str], max_pixels: int | None) -> None:
    """Decode every texture file (JPEG at reduced scale); raise ``MeshError`` naming the first bad one."""
    from PIL import Image

    from pipeline.mesh.discover import open_regular
    from pipeline.mesh.load import MeshError

    base = Path(path).parent
    for rel in textures:
        if rel == EMBEDDED:
            continue
        old = Image.MAX_IMAGE_PIXELS
        Image.MAX_IMAGE_PIXELS = None  # our limit below, with our message; no PIL warning or error
        try:
            with open_regular(base / rel) as fh, Image.open(fh) as img:
                w, h = img.size
                if max_pixels and w * h > max_pixels:
                    raise MeshError(
                        f"texture {rel!r} is {w}x{h} = {w * h / 1e6:.1f} MP, above --max-texture-pixels "
                        f"{max_pixels:,} (decompression-bomb guard)"
                    )
                if img.format == "JPEG":
                    img.draft("RGB", (max(1, w // 8), max(1, h // 8)))
                img.load()
        except MeshError:
            raise
        except FileNotFoundError:
            raise MeshError(f"texture {rel!r} not found (deleted during the run?)") from None
        except Image.UnidentifiedImageError:
            raise MeshError(f"texture {rel!r} cannot be decoded: not an image PIL can identify") from None
        except Exception as exc:  # PIL raises OSError, SyntaxError, ValueError... for corrupt images
            raise MeshError(f"texture {rel!r} cannot be decoded: {type(exc).__name__}: {exc}") from None
        finally:
            Image.MAX_IMAGE_PIXELS = old


def textures_loaded(geometries: list) -> bool:
    """True when at least one geometry carries a decoded colour texture."""
    for g in geometries:
        material = getattr(getattr(g, "visual", None), "material", None)
        for attr in ("image", "baseColorTexture"):
            if getattr(material, attr, None) is not None:
                return True
    return False
