"""Onboarding configuration and the per-stage fingerprints that key incremental work."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from pipeline.fingerprint import fingerprint
from pipeline.mesh.settings import RenderConfig
from pipeline.onboard.engines.ray_options import RayOptions
from pipeline.profiles import DEFAULT_PROMPT_STYLE, PROMPT_STYLES, Profile, get_profile

STAGES = ("render", "caption", "embed_text", "embed_image")


@dataclass(frozen=True)
class OnboardConfig:
    """Everything that decides what onboarding writes, plus how it runs."""

    profile: str = "offline"
    model_overrides: dict[str, str] = field(default_factory=dict)
    prompt_style: str = DEFAULT_PROMPT_STYLE
    render: RenderConfig = field(default_factory=RenderConfig)
    max_faces: int = 2_000_000
    render_timeout_s: float = 120.0
    workers: int = 2
    batch_size: int = 16
    retry_failed: bool = False
    force: tuple[str, ...] = ()
    engine: str = "local"
    model_options: dict[str, dict] = field(default_factory=dict)  # per-role extra adapter options
    ray: RayOptions = field(default_factory=RayOptions)  # --engine ray: cluster layout (no effect on output)

    def __post_init__(self) -> None:
        if self.prompt_style not in PROMPT_STYLES:
            raise ValueError(
                f"unknown --prompt-style {self.prompt_style!r}; choose from {', '.join(PROMPT_STYLES)}"
            )
        bad = [s for s in self.force if s not in STAGES]
        if bad:
            raise ValueError(f"unknown --force stage {bad[0]!r}; stages: {', '.join(STAGES)}")

    def get_profile(self) -> Profile:
        return get_profile(self.profile, self.model_overrides)

    @property
    def prompt(self) -> str:
        return PROMPT_STYLES[self.prompt_style]

    def image_roles(self) -> list[str]:
        """Roles whose encoders embed the views: the stage-2 encoder, plus CLIP image where the profile has it."""
        p = self.get_profile()
        return ["view_encoder"] + (["clip_image_encoder"] if p.clip_image_encoder is not None else [])

    def fingerprints(self) -> dict[str, str]:
        """Fingerprint of each stage's config and model, chained through its inputs."""
        p = self.get_profile()
        render_fp = self.render.fingerprint()
        caption_fp = fingerprint(
            {"model": p.captioner.key(), "opts": p.captioner.options, "prompt": self.prompt, "in": render_fp}
        )
        fps = {
            "render": render_fp,
            "caption": caption_fp,
            "embed_text": fingerprint(
                {"model": p.text_encoder.key(), "opts": p.text_encoder.options, "in": caption_fp}
            ),
        }
        for role in self.image_roles():
            spec = getattr(p, role)
            fps[f"embed_image:{role}"] = fingerprint(
                {"model": spec.key(), "opts": spec.options, "in": render_fp}
            )
        return fps

    def describe(self) -> dict:
        """JSON-ready description stored in the ``runs`` table."""
        p = self.get_profile()
        return {
            "profile": self.profile,
            "models": {r: (s.key() if s else None) for r, s in p.roles().items()},
            "prompt_style": self.prompt_style,
            "prompt": self.prompt,
            "render": asdict(self.render),
            "max_faces": self.max_faces,
            "render_timeout_s": self.render_timeout_s,
            "fingerprints": self.fingerprints(),
        }
