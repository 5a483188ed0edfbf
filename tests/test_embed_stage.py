"""The text-embedding stage encodes each distinct caption once and maps the vectors back to every row."""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from pipeline.onboard.config import OnboardConfig
from pipeline.onboard.stages.embed import TextEmbedStage


class CountingEncoder:
    dim = 4

    def __init__(self) -> None:
        self.calls: list[list[str]] = []

    def encode_text(self, texts: list[str]) -> np.ndarray:
        self.calls.append(list(texts))
        return np.stack([np.array([len(t), t.count("a"), 1.0, ord(t[0]) if t else 0.0]) for t in texts])


def test_repeated_captions_are_encoded_once():
    spec = OnboardConfig().resolve().step("embed_text")
    enc = CountingEncoder()
    stage = TextEmbedStage(OnboardConfig(), "run", spec, model=enc)
    caps = ["a red can", "a blue box", "a red can", "", "a blue box", "a red can"]
    source = pa.table(
        {
            "mesh_id": ["m"] * 6,
            "view_index": pa.array(range(6), pa.int16()),
            "fingerprint": ["f"] * 6,
            "caption": caps,
        }
    )
    out = stage(source)
    assert enc.calls == [["a red can", "a blue box", ""]]
    vecs = np.stack(out.column("embedding").to_numpy(zero_copy_only=False))
    assert out.num_rows == 6 and out.column("view_index").to_pylist() == list(range(6))
    for i, j in [(0, 2), (0, 5), (1, 4)]:
        assert np.array_equal(vecs[i], vecs[j])
    assert not np.array_equal(vecs[0], vecs[1])
    assert np.allclose(np.linalg.norm(vecs, axis=1), 1.0)
