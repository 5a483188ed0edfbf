"""The Ray engine's step actors, run as plain objects (no cluster): consecutive steps on one model share an
actor (one model copy; the learned encoder's patch tokens come from the pass that embeds the views) and
give what one actor per step gives. The cluster tests (test_ray_engine.py) run the real thing."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from conftest import SAMPLE_LIBRARY

from pipeline.mesh.settings import RenderConfig
from pipeline.models.focus_encoder import LearnedViewEncoder
from pipeline.onboard.config import OnboardConfig
from pipeline.onboard.engines.ray_workers import RenderWorker, StepWorker, row_schema, step_groups, unpack

LEARNED = ("embed_image:learned_encoder", "probe", "patches")


def keys(groups) -> list[tuple[str, ...]]:
    return [tuple(s.key for s in g) for g in groups]


def test_steps_on_one_model_share_an_actor():
    offline = OnboardConfig().resolve()
    assert keys(step_groups(list(offline.downstream))) == [
        ("caption",),
        ("embed_text",),
        ("embed_image:view_encoder",),
        LEARNED,
        ("features",),
    ]
    # a step left out of the round (stored already) leaves the rest of its group together
    assert LEARNED[1:] in keys(step_groups([s for s in offline.downstream if s.key != LEARNED[0]]))
    paper = OnboardConfig(profile="paper").resolve()  # two image encoders, each its own model
    assert all(len(g) == 1 for g in keys(step_groups(list(paper.downstream))))


@pytest.fixture(scope="module")
def rendered():
    """One sample mesh rendered by the render actor's code, as a one-row batch of the Ray dataset."""
    run = OnboardConfig(render=RenderConfig(resolution=128), workers=0).resolve()
    mesh = SAMPLE_LIBRARY / "011_banana" / "model.obj"
    row = dict.fromkeys(row_schema(run).names)
    row.update(mesh_id="m1", abs_path=str(mesh), format="obj", todo=[s.key for s in run.steps])
    batch = pa.Table.from_pylist([row], schema=row_schema(run))
    return run, RenderWorker(run, "r1", True, str(SAMPLE_LIBRARY))(batch)


def test_a_shared_actor_encodes_each_view_once_and_writes_the_same(rendered, monkeypatch):
    run, batch = rendered
    calls = []
    real = LearnedViewEncoder.object_patches_batch

    def counted(self, images):
        calls.append(len(images))
        return real(self, images)

    monkeypatch.setattr(LearnedViewEncoder, "object_patches_batch", counted)
    shared = StepWorker(run, "r1", LEARNED)(batch).to_pylist()[0]
    assert calls == []  # the patch tokens came from the embedding pass
    separate = batch
    for key in LEARNED:  # one actor per step, as before
        separate = StepWorker(run, "r1", (key,))(separate)
    separate = separate.to_pylist()[0]
    assert calls == [unpack(batch.column("render")[0].as_py()).num_rows]  # the patches actor: every view again
    for key in LEARNED:
        a, b = unpack(shared[key]), unpack(separate[key])
        assert a.num_rows == b.num_rows > 0 and a.column_names == b.column_names
        for col in a.column_names:
            x, y = a.column(col).to_pylist(), b.column(col).to_pylist()
            if col == "tokens":
                for u, v in zip(x, y, strict=True):
                    np.testing.assert_allclose(np.frombuffer(u, np.float16), np.frombuffer(v, np.float16), atol=2e-3)
            elif col == "embedding":
                np.testing.assert_allclose(np.asarray(x, np.float32), np.asarray(y, np.float32), atol=1e-5)
            else:  # ids, fingerprints, counts, errors
                assert x == y, col
    for key in LEARNED:  # each step's seconds are its own
        stage = run.step(key).stage.name
        assert shared[f"t_{stage}"] > 0
