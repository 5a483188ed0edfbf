"""A stage as declared (:class:`Stage`) and as resolved for one run and model role (:class:`Step`).

Light on purpose (no pyarrow, no models): the CLI reads the stage names to build ``--help``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

if TYPE_CHECKING:
    import pyarrow as pa

    from pipeline.adapter.probes import ProbeConfig
    from pipeline.localfeat.config import FeatureConfig
    from pipeline.mesh.settings import RenderConfig
    from pipeline.models.registry import ModelSpec
    from pipeline.profiles import Profile


class StageConfig(Protocol):
    """What the stages read of a run's config (:class:`pipeline.onboard.config.OnboardConfig` has it):
    a protocol, so the stages do not import the config module that imports them."""

    render: RenderConfig
    features: FeatureConfig
    probes: ProbeConfig
    max_faces: int
    max_texture_pixels: int
    prompt_style: str
    model_options: dict[str, dict]

    @property
    def prompt(self) -> str: ...


@dataclass(frozen=True)
class Stage:
    """One onboarding stage as declared in :data:`pipeline.onboard.stages.STAGES` (module-level
    functions only, so that a stage pickles into worker processes and Ray actors)."""

    name: str  # --force NAME, errors.stage, progress bar, timings
    input: str | None  # the stage whose output it reads (None: the mesh files)
    table: str  # output table; a folder of one table per encoder when ``per_encoder``
    roles: Callable[[Profile], tuple[str | None, ...]]  # its model roles: one step each
    fingerprint: Callable[[Any, ModelSpec | None, str | None], str]  # (config, model, input's fp)
    runner: Callable[..., Any]  # runner(cfg, run_id, step, model=None): a callable pa.Table -> pa.Table
    target: Callable[[pa.Table], pa.Schema]  # table schema of its output rows (errors split off)
    per_encoder: bool = False
    per_role: bool = False  # step keys are "NAME:ROLE"
    enabled: Callable[[Any], bool] | None = None  # enabled(config): False drops the stage from the run


@dataclass(frozen=True)
class Step:
    """A stage resolved for one run and one model role: what it writes, and under which fingerprint."""

    stage: Stage
    role: str | None
    spec: ModelSpec | None
    key: str  # "render", "caption", "embed_text", "embed_image:view_encoder", ...
    fingerprint: str
    input: str | None  # key of the step whose output it reads
    dataset: str  # "views", "captions", "text_embeddings/<encoder>", ...
