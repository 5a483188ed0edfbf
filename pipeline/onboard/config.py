"""Onboarding configuration (:class:`OnboardConfig`) and its resolution for one run (:class:`RunSpec`:
the profile and every step's fingerprint and table, computed once and passed down)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from pipeline.adapter.fit import FitConfig
from pipeline.adapter.probes import ProbeConfig
from pipeline.localfeat.config import FeatureConfig
from pipeline.mesh.settings import RenderConfig
from pipeline.onboard.engines.ray_options import RayOptions
from pipeline.onboard.guard import DEFAULT_MAX_REMOVED
from pipeline.onboard.stages import STAGE_NAMES, Step, resolve_steps
from pipeline.profiles import DEFAULT_PROMPT_STYLE, PROMPT_STYLES, Profile, default_elevations, get_profile

#: Textures with more pixels than this fail their mesh (decompression-bomb guard); ``--max-texture-pixels``.
DEFAULT_MAX_TEXTURE_PIXELS = 8192 * 8192


@dataclass(frozen=True)
class OnboardConfig:
    """Everything that decides what onboarding writes, plus how it runs."""

    profile: str = "offline"
    model_overrides: dict[str, str] = field(default_factory=dict)
    prompt_style: str = DEFAULT_PROMPT_STYLE
    render: RenderConfig | None = None  # None: RenderConfig() with the profile's elevation rings
    max_faces: int = 2_000_000
    max_texture_pixels: int = DEFAULT_MAX_TEXTURE_PIXELS  # not fingerprinted: a guard, not a look
    render_timeout_s: float = 120.0
    workers: int = 2
    batch_size: int = 16
    retry_failed: bool = False
    force: tuple[str, ...] = ()
    engine: str = "local"
    model_options: dict[str, dict] = field(default_factory=dict)  # per-role extra adapter options
    ray: RayOptions = field(default_factory=RayOptions)  # --engine ray: cluster layout (no effect on output)
    features: FeatureConfig = field(default_factory=FeatureConfig)  # local features per view (verification)
    probes: ProbeConfig = field(default_factory=ProbeConfig)  # probe queries per model (query adapter)
    patch_tokens: bool = True  # the learned encoder's object patch tokens per view (the patches stage)
    adapter: FitConfig = field(default_factory=FitConfig)  # the query adapter's fit (pipeline.adapter)
    max_removed: float = DEFAULT_MAX_REMOVED  # removal guard: share of active files a run may remove
    allow_removal: bool = False  # removal guard off (--allow-removal)

    def __post_init__(self) -> None:
        if self.render is None:
            object.__setattr__(self, "render", RenderConfig(elevations_deg=default_elevations(self.profile)))
        if self.prompt_style not in PROMPT_STYLES:
            raise ValueError(
                f"unknown --prompt-style {self.prompt_style!r}; choose from {', '.join(PROMPT_STYLES)}"
            )
        import math

        if not (math.isfinite(self.render_timeout_s) and self.render_timeout_s > 0):
            raise ValueError(f"render timeout must be > 0 seconds, got {self.render_timeout_s}")
        for name in ("max_faces", "max_texture_pixels", "batch_size"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 <= self.max_removed <= 1.0:
            raise ValueError(f"max_removed must be a share within 0..1, got {self.max_removed}")
        if self.workers < 0:
            raise ValueError(f"workers must be >= 0, got {self.workers}")
        bad = [s for s in self.force if s not in STAGE_NAMES]
        if bad:
            raise ValueError(f"unknown --force stage {bad[0]!r}; stages: {', '.join(STAGE_NAMES)}")

    def get_profile(self) -> Profile:
        return get_profile(self.profile, self.model_overrides)

    @property
    def prompt(self) -> str:
        return PROMPT_STYLES[self.prompt_style]

    def resolve(self) -> RunSpec:
        """The profile and the steps of a run with this config (raises ValueError for a bad override)."""
        profile = self.get_profile()
        return RunSpec(self, profile, resolve_steps(self, profile))

    def fingerprints(self) -> dict[str, str]:
        """Fingerprint of each step's config and model, chained through its inputs."""
        return self.resolve().fingerprints

    def describe(self) -> dict:
        """JSON-ready description stored in the ``runs`` table."""
        return self.resolve().describe()


@dataclass(frozen=True)
class RunSpec:
    """An :class:`OnboardConfig` resolved once per run: its profile and its steps (one per stage and
    model role, in stage order), which the planner, the engines and the stages all take from here."""

    cfg: OnboardConfig
    profile: Profile
    steps: tuple[Step, ...]

    @property
    def fingerprints(self) -> dict[str, str]:
        return {s.key: s.fingerprint for s in self.steps}

    def step(self, key: str) -> Step:
        return next(s for s in self.steps if s.key == key)

    @property
    def source(self) -> Step:
        """The first step (rendering): the one that reads the mesh files."""
        return self.steps[0]

    @property
    def downstream(self) -> tuple[Step, ...]:
        """Every step after the first, in order."""
        return self.steps[1:]

    def describe(self) -> dict:
        """JSON-ready description stored in the ``runs`` table."""
        cfg = self.cfg
        return {
            "profile": cfg.profile,
            "models": {r: (s.key() if s else None) for r, s in self.profile.roles().items()},
            "prompt_style": cfg.prompt_style,
            "prompt": cfg.prompt,
            "render": asdict(cfg.render),
            "features": asdict(cfg.features),
            "probes": cfg.probes.describe(),
            "adapter": cfg.adapter.describe(),
            "max_faces": cfg.max_faces,
            "render_timeout_s": cfg.render_timeout_s,
            "removal_guard": {"max_removed": cfg.max_removed, "allow_removal": cfg.allow_removal},
            "fingerprints": self.fingerprints,
        }
