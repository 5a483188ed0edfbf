"""Build the small sample library in data/sample_library from ../shared/data/ycb (run once, committed).

Geometry is kept (coordinates rounded to 0.1 mm) and textures are downscaled to 1024 px so the
quickstart stays small. Usage: python scripts/make_sample_data.py [SHARED_YCB_DIR]
"""

from __future__ import annotations

import sys
from pathlib import Path

from PIL import Image

OBJECTS = ["003_cracker_box", "005_tomato_soup_can", "006_mustard_bottle", "011_banana"]


def main() -> None:
    src_root = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).parents[2] / "shared/data/ycb")
    dst_root = Path(__file__).parents[1] / "data/sample_library"
    for name in OBJECTS:
        src, dst = src_root / name, dst_root / name
        dst.mkdir(parents=True, exist_ok=True)
        out = []
        for line in (src / "textured.obj").read_text().splitlines():
            if line.startswith("v ") or line.startswith("vt ") or line.startswith("vn "):
                tag, *nums = line.split()
                out.append(tag + " " + " ".join(f"{float(x):.4f}".rstrip("0").rstrip(".") for x in nums))
            elif line.startswith("mtllib"):
                out.append("mtllib model.mtl")
            else:
                out.append(line)
        (dst / "model.obj").write_text("\n".join(out) + "\n")
        (dst / "model.mtl").write_text("newmtl material_0\nmap_Kd texture.jpg\n")
        img = Image.open(src / "texture_map.jpg").convert("RGB").resize((1024, 1024), Image.LANCZOS)
        img.save(dst / "texture.jpg", quality=85)
    print(f"wrote {len(OBJECTS)} meshes to {dst_root}")


if __name__ == "__main__":
    main()
