"""Synthetic queries from a library: each mesh rendered at novel viewpoints (never an onboarding view),
random distances, rolls and in-plane offsets, random light intensity and colour, over solid, gradient,
noise or real-photo backgrounds, with the exact object mask from the depth pass.

Seeded and deterministic: the random state of a mesh depends only on the seed and its source path, so adding
meshes to the library does not change the other meshes' queries.

``python -m pipeline.evaluate.synth --store STORE --out DIR`` (or ``--library DIR``) writes
``DIR/queries.jsonl``, ``DIR/images/*.png``, ``DIR/masks/*.png`` and ``DIR/synth_config.json``.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from pipeline.evaluate.backgrounds import BACKGROUND_KINDS, make_background
from pipeline.evaluate.datasets import Query, write_queries
from pipeline.evaluate.degrade import DegradeConfig
from pipeline.evaluate.library import DEFAULT_CLASS_PATTERN, MeshRef, class_of
from pipeline.evaluate.prompts import DEFAULT_PROMPT_TEMPLATE, prompt_for
from pipeline.mesh.settings import RenderConfig
from pipeline.profiles import default_elevations


@dataclass(frozen=True)
class SynthConfig:
    """What the generator varies, and within which ranges."""

    per_mesh: int = 5
    seed: int = 0
    width: int = 640
    height: int = 480
    yfov_deg: float = 45.0
    fill: tuple[float, float] = (0.3, 0.8)  # object span as a fraction of the frame height
    elevation_deg: tuple[float, float] = (-30.0, 60.0)
    min_view_separation_deg: float = 10.0  # angular distance to every onboarding view
    roll_deg: float = 15.0  # in-plane camera roll, +-
    offset: float = 0.8  # in-plane offset, as a fraction of the free margin around the object
    light_intensity: tuple[float, float] = (1.5, 4.5)
    light_tint: float = 0.25  # max deviation of each light colour channel from white
    light_angle_deg: float = 35.0  # light direction deviates this much from the camera ray at most
    ambient: tuple[float, float] = (0.2, 0.6)
    backgrounds: tuple[str, ...] = ("solid", "gradient", "noise", "photo")
    photo_dirs: tuple[str, ...] = ()
    prompt_template: str = DEFAULT_PROMPT_TEMPLATE
    names: dict[str, str] = field(default_factory=dict)  # mesh name -> readable name for the prompt
    class_pattern: str | None = DEFAULT_CLASS_PATTERN
    # its views are avoided; --store uses the store's own; default: the offline profile's rings (a superset
    # of the paper's)
    onboarding: RenderConfig = field(
        default_factory=lambda: RenderConfig(elevations_deg=default_elevations("offline"))
    )
    max_faces: int = 2_000_000
    max_texture: int = 1024
    degrade: DegradeConfig | None = None  # the harder set (``--hard``): camera effects, occluders, loose ROIs

    def __post_init__(self) -> None:
        bad = [b for b in self.backgrounds if b not in BACKGROUND_KINDS]
        if bad:
            raise ValueError(f"unknown background kind {bad[0]!r}; choose from {', '.join(BACKGROUND_KINDS)}")
        if "photo" in self.backgrounds and not self.photo_dirs:
            object.__setattr__(self, "backgrounds", tuple(b for b in self.backgrounds if b != "photo"))
        if not self.backgrounds:
            raise ValueError("no background kinds left (photo backgrounds need --photo-dir)")


@dataclass
class SynthView:
    """Sampled parameters of one synthetic query."""

    azimuth_deg: float
    elevation_deg: float
    fill: float
    roll_deg: float
    offset_ndc: tuple[float, float]
    light_intensity: float
    light_color: tuple[float, float, float]
    light_direction: tuple[float, float, float]
    ambient: float
    background: str


def mesh_rng(seed: int, source_path: str) -> np.random.Generator:
    """Random state of one mesh: a function of the seed and the mesh's path only."""
    h = int(hashlib.sha256(source_path.encode()).hexdigest()[:12], 16)
    return np.random.default_rng([seed, h])


def _unit(az_deg: float, el_deg: float) -> np.ndarray:
    az, el = math.radians(az_deg), math.radians(el_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def sample_views(cfg: SynthConfig, rng: np.random.Generator) -> list[SynthView]:
    """``cfg.per_mesh`` view parameter sets, each at least ``min_view_separation_deg`` from onboarding views."""
    from pipeline.mesh.cameras import view_directions

    onboard = np.stack([d for _, _, d in view_directions(cfg.onboarding)])
    min_cos = math.cos(math.radians(cfg.min_view_separation_deg))
    views = []
    for _ in range(cfg.per_mesh):
        for _attempt in range(1000):
            az = float(rng.uniform(0.0, 360.0))
            el = float(rng.uniform(*cfg.elevation_deg))
            if float(np.max(onboard @ _unit(az, el))) < min_cos:
                break
        tint = 1.0 - rng.uniform(0.0, cfg.light_tint, size=3)
        ld = rng.normal(size=3)
        views.append(
            SynthView(
                azimuth_deg=az,
                elevation_deg=el,
                fill=float(rng.uniform(*cfg.fill)),
                roll_deg=float(rng.uniform(-cfg.roll_deg, cfg.roll_deg)),
                offset_ndc=(float(rng.uniform(-1, 1)), float(rng.uniform(-1, 1))),
                light_intensity=float(rng.uniform(*cfg.light_intensity)),
                light_color=tuple(float(c) for c in tint / tint.max()),
                light_direction=tuple(float(c) for c in ld / np.linalg.norm(ld)),
                ambient=float(rng.uniform(*cfg.ambient)),
                background=str(rng.choice(list(cfg.backgrounds))),
            )
        )
    return views


class SynthRenderer:
    """One offscreen GL context for every query of a run."""

    def __init__(self, cfg: SynthConfig):
        from pipeline.mesh.render import setup_headless_gl

        setup_headless_gl()
        import pyrender

        self.cfg = cfg
        self._pyrender = pyrender
        self._renderer = pyrender.OffscreenRenderer(cfg.width, cfg.height)

    def render(self, mesh, view: SynthView) -> tuple[np.ndarray, np.ndarray]:
        """RGB (HxWx3 uint8, black background) and the exact object mask (depth > 0) of one view."""
        from pipeline.mesh.cameras import fit_distance, look_at_pose

        pyrender, cfg = self._pyrender, self.cfg
        scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 1.0], ambient_light=[view.ambient] * 3)
        for g in mesh.geometries:
            pm = pyrender.Mesh.from_trimesh(g, smooth=len(g.faces) < 2_000_000)
            for prim in pm.primitives:
                mat = prim.material
                if mat is not None and hasattr(mat, "metallicFactor"):
                    mat.metallicFactor, mat.roughnessFactor = 0.0, 0.9  # see pipeline.mesh.render
            scene.add(pm)
        direction = _unit(view.azimuth_deg, view.elevation_deg)
        dist = fit_distance(mesh.sample_points, direction, cfg.yfov_deg, view.fill)
        pose = look_at_pose(direction, dist)
        # in-plane offset: slide the camera sideways within the free margin around the object
        t, aspect = math.tan(math.radians(cfg.yfov_deg) / 2.0), cfg.width / cfg.height
        ox = view.offset_ndc[0] * cfg.offset * max(0.0, 1.0 - view.fill / aspect) * aspect
        oy = view.offset_ndc[1] * cfg.offset * max(0.0, 1.0 - view.fill)
        pose[:3, 3] += dist * t * (ox * pose[:3, 0] + oy * pose[:3, 1])
        r = math.radians(view.roll_deg)
        roll = np.array([[math.cos(r), -math.sin(r), 0.0], [math.sin(r), math.cos(r), 0.0], [0.0, 0.0, 1.0]])
        pose[:3, :3] = pose[:3, :3] @ roll
        camera = pyrender.PerspectiveCamera(yfov=math.radians(cfg.yfov_deg), znear=0.05, zfar=100.0)
        scene.add(camera, pose=pose)
        scene.add(
            pyrender.DirectionalLight(color=list(view.light_color), intensity=view.light_intensity),
            pose=_light_pose(pose, view.light_direction, cfg.light_angle_deg),
        )
        color, depth = self._renderer.render(scene)
        return np.ascontiguousarray(color[:, :, :3]), depth > 0

    def close(self) -> None:
        self._renderer.delete()


def _light_pose(cam_pose: np.ndarray, jitter: tuple[float, float, float], max_angle_deg: float) -> np.ndarray:
    """Camera pose tilted by up to ``max_angle_deg`` (a light from near the viewer, never from behind)."""
    axis = np.cross([0.0, 0.0, 1.0], np.asarray(jitter))
    n = np.linalg.norm(axis)
    if n < 1e-9:
        return cam_pose
    axis /= n
    a = math.radians(max_angle_deg) * abs(jitter[2])
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rot = np.eye(3) + math.sin(a) * k + (1 - math.cos(a)) * k @ k
    pose = cam_pose.copy()
    pose[:3, :3] = cam_pose[:3, :3] @ rot
    return pose


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", name).strip("-") or "mesh"


def generate(
    meshes: list[MeshRef], out_dir: str | Path, cfg: SynthConfig, progress: bool = False
) -> list[Query]:
    """Render ``cfg.per_mesh`` queries per mesh into ``out_dir``; return them (also written as JSONL)."""
    from PIL import Image

    from pipeline.mesh.load import MeshError, load_mesh
    from pipeline.progress import iterate

    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "masks").mkdir(parents=True, exist_ok=True)
    photos = _photo_paths(cfg.photo_dirs)
    renderer = SynthRenderer(cfg)
    queries: list[Query] = []
    skipped: list[dict] = []
    try:
        for m in iterate(meshes, "synthetic", unit="mesh", enabled=progress):
            rng = mesh_rng(cfg.seed, m.source_path)
            views = sample_views(cfg, rng)
            try:
                mesh = load_mesh(
                    m.abs_path, m.format, max_faces=cfg.max_faces, up="auto", max_texture=cfg.max_texture
                )
            except MeshError as exc:
                skipped.append({"mesh": m.source_path, "reason": str(exc)})
                continue
            for i, view in enumerate(views):
                rgb, mask = renderer.render(mesh, view)
                if not mask.any():
                    skipped.append({"mesh": m.source_path, "view": i, "reason": "object not visible"})
                    continue
                bg = make_background(view.background, cfg.width, cfg.height, rng, photos)
                image = np.where(mask[:, :, None], rgb, bg)
                qid = f"{_safe(m.name)}-{i:02d}"
                img_path, mask_path = out / "images" / f"{qid}.png", out / "masks" / f"{qid}.png"
                extra: dict = {}
                query_mask = mask
                if cfg.degrade is not None:  # its own random stream: the base set's draws stay the same
                    image, query_mask, extra = _degrade(image, mask, cfg, m.source_path, i, photos)
                Image.fromarray(image).save(img_path)
                Image.fromarray(query_mask.astype(np.uint8) * 255).save(mask_path)
                ys, xs = np.nonzero(mask if cfg.degrade is None else extra.pop("_visible"))
                box = (float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1))
                if "_box" in extra:
                    box = extra.pop("_box")
                queries.append(
                    Query(
                        query_id=qid,
                        image=str(img_path.resolve()),
                        prompt=prompt_for(m.name, cfg.prompt_template, cfg.names),
                        expected=[m.mesh_id or m.source_path],
                        box=box,
                        mask=str(mask_path.resolve()),
                        label=class_of(m.name, cfg.class_pattern),
                        meta={
                            "source_path": m.source_path,
                            "name": m.name,
                            **_view_meta(view, mask),
                            **extra,
                        },
                    )
                )
    finally:
        renderer.close()
    write_queries(queries, out / "queries.jsonl")
    cfg_json = {k: v for k, v in asdict(cfg).items()}
    (out / "synth_config.json").write_text(
        json.dumps({"config": cfg_json, "n_queries": len(queries), "skipped": skipped}, indent=2, default=str)
    )
    return queries


def _degrade(image, mask, cfg: SynthConfig, source_path: str, i: int, photos: list[Path]):
    """The harder set's degradations of one query: (image, query mask, metadata incl. the visible mask and
    the loose box under private keys)."""
    from pipeline.evaluate.degrade import grow_mask, jitter_box, occlude, photometric

    d = cfg.degrade
    rng = mesh_rng(cfg.seed, f"{source_path}#hard-{i}")
    visible, hidden = mask, 0.0
    if rng.random() < d.occlusion_prob:
        kind = "photo" if photos else "noise"
        texture = make_background(kind, cfg.width, cfg.height, rng, photos)
        occluded, vis, hid = occlude(image, mask, rng, d, texture)
        if vis.sum() >= 0.35 * mask.sum():  # keep at least a third of the object in view
            image, visible, hidden = occluded, vis, hid
    image, meta = photometric(image, rng, d)
    grow = int(rng.integers(d.mask_dilate_px[0], d.mask_dilate_px[1] + 1))
    ys, xs = np.nonzero(visible)
    tight = (float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1))
    box = jitter_box(tight, mask.shape, rng, d.box_jitter)
    meta.update({"occluded": round(hidden, 3), "mask_grow_px": grow, "_visible": visible, "_box": box})
    return image, grow_mask(visible, grow), meta


def _view_meta(view: SynthView, mask: np.ndarray) -> dict:
    d = asdict(view)
    d = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in d.items()}
    d["offset_ndc"] = [round(v, 4) for v in view.offset_ndc]
    d["light_color"] = [round(v, 4) for v in view.light_color]
    d.pop("light_direction")
    d["mask_fraction"] = round(float(mask.mean()), 5)
    d["truncated"] = bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())
    return d


def _photo_paths(dirs: tuple[str, ...]) -> list[Path]:
    out: list[Path] = []
    for d in dirs:
        p = Path(d)
        files = [p] if p.is_file() else sorted(p.rglob("*"))
        out += [f for f in files if f.suffix.lower() in (".png", ".jpg", ".jpeg")]
    return out
