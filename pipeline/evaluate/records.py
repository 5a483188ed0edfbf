"""The evaluation query record and the error of an unreadable query file (shared by the query-file
and BOP readers)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field


@dataclass
class Query:
    """One evaluation query: an image, a prompt, optionally where the object is, and what is correct."""

    query_id: str
    image: str  # absolute path
    prompt: str
    expected: list[str]  # mesh_id, path or name of each correct mesh
    box: tuple[float, float, float, float] | None = None  # x0, y0, x1, y1 in pixels (x1, y1 exclusive)
    mask: str | None = None  # absolute path of a binary mask PNG (non-zero = object)
    label: str | None = None  # class label for class-level relevance
    meta: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        d = asdict(self)
        d["box"] = list(self.box) if self.box else None
        return d


class QueryFileError(ValueError):
    """A query file that cannot be read; the message names the file and line."""
