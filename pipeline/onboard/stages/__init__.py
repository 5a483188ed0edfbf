"""Onboarding stages, and :data:`STAGES`: the one declaration of the stages, their order and inputs.

Each stage (``render``, ``caption``, ``embed``, ``probe``, ``patches``, ``features``) is a callable object over Arrow tables that holds its
model for its whole life: it maps an input ``pa.Table`` to an output ``pa.Table`` whose rows either
conform to a store table or carry an ``error`` (one row per failed mesh), so the same code runs in the
local engine and under Ray Data ``map_batches`` (:func:`pipeline.onboard.stages.base.split_errors`
separates the two). The planner, both engines, ``--force`` and the fingerprints iterate :data:`STAGES`
(through :func:`resolve_steps`); nothing else lists the stages.

This module stays light (the CLI reads :data:`STAGE_NAMES` for ``--help``): the stage classes, pyarrow
and the models are imported by the functions that build them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from pipeline.fingerprint import fingerprint
from pipeline.onboard.stages.step import Stage, Step

if TYPE_CHECKING:
    import pyarrow as pa

    from pipeline.models.registry import ModelSpec
    from pipeline.profiles import Profile


# ---------------------------------------------------------------- the stage objects
def render_runner(cfg: Any, run_id: str, step: Step, model: Any = None):
    from pipeline.onboard.stages.render import RenderStage

    return RenderStage(cfg, run_id, step, model)


def caption_runner(cfg: Any, run_id: str, step: Step, model: Any = None):
    from pipeline.onboard.stages.caption import CaptionStage

    return CaptionStage(cfg, run_id, step, model)


def text_embed_runner(cfg: Any, run_id: str, step: Step, model: Any = None):
    from pipeline.onboard.stages.embed import TextEmbedStage

    return TextEmbedStage(cfg, run_id, step, model)


def image_embed_runner(cfg: Any, run_id: str, step: Step, model: Any = None):
    from pipeline.onboard.stages.embed import ImageEmbedStage

    return ImageEmbedStage(cfg, run_id, step, model)


def probe_runner(cfg: Any, run_id: str, step: Step, model: Any = None):
    from pipeline.onboard.stages.probe import ProbeStage

    return ProbeStage(cfg, run_id, step, model)


def patches_runner(cfg: Any, run_id: str, step: Step, model: Any = None):
    from pipeline.onboard.stages.patches import PatchStage

    return PatchStage(cfg, run_id, step, model)


def features_runner(cfg: Any, run_id: str, step: Step, model: Any = None):
    from pipeline.onboard.stages.features import FeatureStage

    return FeatureStage(cfg, run_id, step, model)


# ---------------------------------------------------------------- model roles of each stage
def no_model(profile: Profile) -> tuple[str | None, ...]:
    return (None,)


def captioner(profile: Profile) -> tuple[str | None, ...]:
    return ("captioner",)


def text_encoder(profile: Profile) -> tuple[str | None, ...]:
    return ("text_encoder",)


def image_encoders(profile: Profile) -> tuple[str | None, ...]:
    """The stage-2 encoder, plus the learned encoder and CLIP image where the profile has them."""
    optional = ("learned_encoder", "clip_image_encoder")
    return ("view_encoder",) + tuple(r for r in optional if getattr(profile, r) is not None)


def learned_encoder(profile: Profile) -> tuple[str | None, ...]:
    """The learned view encoder, where the profile has one (else the stage has no step)."""
    return ("learned_encoder",) if getattr(profile, "learned_encoder", None) is not None else ()


# ---------------------------------------------------------------- whether a stage runs with a config
def features_enabled(cfg: Any) -> bool:
    """``--local-features none`` drops the features stage."""
    return cfg.features.enabled


def probes_enabled(cfg: Any) -> bool:
    """``--probes 0`` drops the probe stage (and with it the store's query adapter)."""
    return cfg.probes.enabled


def patches_enabled(cfg: Any) -> bool:
    """``--no-patch-tokens`` drops the patches stage (the query then encodes the top-1's views)."""
    return cfg.patch_tokens


# ---------------------------------------------------------------- fingerprints, chained through inputs
def render_fingerprint(cfg: Any, spec: ModelSpec | None, upstream: str | None) -> str:
    return cfg.render.fingerprint()


def caption_fingerprint(cfg: Any, spec: ModelSpec | None, upstream: str | None) -> str:
    return fingerprint({"model": spec.key(), "opts": spec.options, "prompt": cfg.prompt, "in": upstream})


def encoder_fingerprint(cfg: Any, spec: ModelSpec | None, upstream: str | None) -> str:
    """The fingerprint of an embedding step: the model, its options (less those that do not change what
    is stored, :data:`pipeline.profiles.UNFINGERPRINTED_OPTIONS`) and the upstream step's fingerprint."""
    from pipeline.profiles import UNFINGERPRINTED_OPTIONS

    opts = {k: v for k, v in spec.options.items() if k not in UNFINGERPRINTED_OPTIONS}
    return fingerprint({"model": spec.key(), "opts": opts, "in": upstream})


def probe_fingerprint(cfg: Any, spec: ModelSpec | None, upstream: str | None) -> str:
    """The encoder's (as :func:`encoder_fingerprint`), the probe generator's config and the render gray the
    object is cut from."""
    return fingerprint(
        {
            "encoder": encoder_fingerprint(cfg, spec, upstream),
            "probes": cfg.probes.describe(),
            "background": list(cfg.render.background),
        }
    )


def patches_fingerprint(cfg: Any, spec: ModelSpec | None, upstream: str | None) -> str:
    """The encoder's (as :func:`encoder_fingerprint`), which patches are kept and how they are stored
    (:func:`pipeline.onboard.stages.patches.settings`) and the render gray they are told from."""
    from pipeline.onboard.stages.patches import settings

    return fingerprint(
        {
            "encoder": encoder_fingerprint(cfg, spec, upstream),
            "patches": settings(),
            "background": list(cfg.render.background),
        }
    )


def features_fingerprint(cfg: Any, spec: ModelSpec | None, upstream: str | None) -> str:
    return cfg.features.fingerprint(upstream)


# ---------------------------------------------------------------- table schemas of the outputs
def views_schema(out: pa.Table) -> pa.Schema:
    from pipeline import schemas

    return schemas.VIEWS


def captions_schema(out: pa.Table) -> pa.Schema:
    from pipeline import schemas

    return schemas.CAPTIONS


def embeddings_schema(out: pa.Table) -> pa.Schema:
    """The embedding table of the output's vector width (its schema fixes it; no model needed)."""
    from pipeline import schemas

    return schemas.embedding_schema(out.schema.field("embedding").type.list_size)


def view_patches_schema(out: pa.Table) -> pa.Schema:
    from pipeline import schemas

    return schemas.VIEW_PATCHES


def view_features_schema(out: pa.Table) -> pa.Schema:
    from pipeline import schemas

    return schemas.VIEW_FEATURES


#: The stages, in order; each reads its ``input`` stage's output. The first reads the mesh files.
STAGES: tuple[Stage, ...] = (
    Stage("render", None, "views", no_model, render_fingerprint, render_runner, views_schema),
    Stage("caption", "render", "captions", captioner, caption_fingerprint, caption_runner, captions_schema),
    Stage(
        "embed_text",
        "caption",
        "text_embeddings",
        text_encoder,
        encoder_fingerprint,
        text_embed_runner,
        embeddings_schema,
        per_encoder=True,
    ),
    Stage(
        "embed_image",
        "render",
        "image_embeddings",
        image_encoders,
        encoder_fingerprint,
        image_embed_runner,
        embeddings_schema,
        per_encoder=True,
        per_role=True,
    ),
    Stage(
        "probe",
        "render",
        "probe_embeddings",
        learned_encoder,
        probe_fingerprint,
        probe_runner,
        embeddings_schema,
        per_encoder=True,
        enabled=probes_enabled,
    ),
    Stage(
        "patches",
        "render",
        "view_patches",
        learned_encoder,
        patches_fingerprint,
        patches_runner,
        view_patches_schema,
        enabled=patches_enabled,
    ),
    Stage(
        "features",
        "render",
        "view_features",
        no_model,
        features_fingerprint,
        features_runner,
        view_features_schema,
        enabled=features_enabled,
    ),
)
STAGE_NAMES: tuple[str, ...] = tuple(s.name for s in STAGES)


def resolve_steps(cfg: Any, profile: Profile) -> tuple[Step, ...]:
    """The steps of a run, in stage order: one per stage and model role, fingerprints chained."""
    from pipeline.store import slug

    steps: list[Step] = []
    first_of: dict[str, Step] = {}
    for stage in STAGES:
        if stage.enabled is not None and not stage.enabled(cfg):
            continue
        upstream = first_of.get(stage.input) if stage.input else None
        for role in stage.roles(profile):
            spec = getattr(profile, role) if role else None
            step = Step(
                stage=stage,
                role=role,
                spec=spec,
                key=f"{stage.name}:{role}" if stage.per_role else stage.name,
                fingerprint=stage.fingerprint(cfg, spec, upstream.fingerprint if upstream else None),
                input=upstream.key if upstream else None,
                dataset=f"{stage.table}/{slug(spec.key())}" if stage.per_encoder else stage.table,
            )
            steps.append(step)
            first_of.setdefault(stage.name, step)
    return tuple(steps)


__all__ = ["STAGES", "STAGE_NAMES", "Stage", "Step", "resolve_steps"]
