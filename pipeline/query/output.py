"""Human-readable rendering of a :class:`QueryResult` (the CLI's default output)."""

from __future__ import annotations

import os

from pipeline.query.results import QueryResult


def _score(v: float | None) -> str:
    return "-" if v is None else f"{v:.3f}"


def _stage1_line(r: QueryResult) -> str:
    if getattr(r, "fused", False) and r.mode != "text-only":
        how = f"all {r.n_stage1} models ranked by the fused learned / descriptor / text score"
        if getattr(r, "adapted", False):  # the fused score is the adapted one; the learned cosine shown is plain
            how += " (learned cosine through the store's query adapter; the cosine shown is the plain one)"
        return how
    if r.mode == "image-only":
        return f"image-only: all {r.n_stage1} models ranked by stage 2"
    if r.mode == "text-only":
        return f"text-only: the top {r.n_stage1} models by stage-1 score"
    if r.used_fallback:
        unit = getattr(r, "fallback_unit", "meshes")
        kept = (
            f"none reached tau {r.threshold:.2f}: kept the top {r.n_stage1} "
            f"(fallback-k {r.fallback_k} {unit})"
        )
    else:
        kept = f"{r.n_stage1} model{'s' * (r.n_stage1 != 1)} reached tau {r.threshold:.2f}"
    return f"stage 1: {kept}; decided by {r.decided_by.replace('stage', 'stage ')}"


def size_text(c) -> str:
    """``0.097 x 0.067 x 0.191`` (metres, x y z), with ``*`` when the units are a guess; ``-`` unknown."""
    extent = getattr(c, "extent_m", None)
    if not extent:
        return "-"
    guess = "*" if getattr(c, "units_from", None) == "extent" else ""
    return " x ".join(f"{v:.3g}" for v in extent) + guess


def units_warnings(candidates) -> list[str]:
    """One warning line when a listed model's units are guessed from its size (OBJ/PLY/STL/OFF have none)."""
    guessed = [c for c in candidates if getattr(c, "units_from", None) == "extent"]
    if not guessed:
        return []
    mm = sum(1 for c in guessed if c.units_guess == "mm")
    kinds = f"{mm} as millimetres, {len(guessed) - mm} as metres" if mm else "all as metres"
    return [
        f"warning: * units are a guess from the file's size (longest side > 20 units = mm; {kinds}); "
        "check the size before handing the mesh to a pose estimator"
    ]


def acceptance_line(r: QueryResult) -> str:
    """The open-set verdict in words: whether the best model matches, or no model of the library does."""
    v = r.verdict
    if v is None:
        return "answer: not judged"
    if v.accepted is None:
        return f"answer: not judged ({v.note})"
    if not r.candidates:
        return "answer: no model in the library matches (the library holds no model to rank)"
    at = f"confidence {v.confidence:.2f}, accept threshold {v.threshold:.2f}"
    if v.accepted:
        return f"answer: accepted, {r.candidates[0].name} matches ({at})"
    return f"answer: NOT accepted: no model in the library matches this object ({at}); closest candidates:"


def format_result(r: QueryResult) -> str:
    """A short header (ROI, stage-1 outcome), the ranked table and the latency breakdown."""
    lines = []
    q = r.query
    if q:
        roi = q.get("roi", {})
        box = ",".join(f"{v:g}" for v in roi.get("box", []))
        lines.append(f"query: {q.get('prompt')!r} in {q.get('image')} ({q.get('profile')} profile)")
        lines.append(f"ROI: {roi.get('roi_mode')} from {roi.get('source')}, box {box}")
        caption = q.get("embedding", {}).get("roi_caption")
        if caption:
            lines.append(f"ROI caption: {caption}")
        for note in roi.get("notes", []):
            lines.append(f"note: {note}")
    lines.append(_stage1_line(r))
    lines.append(acceptance_line(r))
    verified = any(getattr(c, "inliers", None) is not None for c in r.candidates)
    learned = any(getattr(c, "learned_score", None) is not None for c in r.candidates)
    rows = [("rank", "model", "text", "image", "view", "size (m)", "source")]
    if learned:
        lines.append("image: learned cosine / descriptor cosine (fused score, verification inliers)")
    for c in r.candidates:
        path = os.path.join(c.library_root, c.source_path) if c.library_root else c.source_path
        view = "-" if c.best_view is None else str(c.best_view)
        image = _score(c.image_score)
        if learned:  # "learned / descriptor (fused, inliers)"
            inl = "" if c.inliers is None else f", {c.inliers} inl"
            image = f"{_score(c.learned_score)} / {image} ({_score(c.score)}{inl})"
        elif verified:  # "image (fused, inliers)"
            image += "" if c.inliers is None else f" ({_score(c.score)}, {c.inliers} inl)"
        rows.append((str(c.rank), c.name, _score(c.text_score), image, view, size_text(c), path))
    if len(rows) == 1:
        lines.append("no models matched")
    else:
        widths = [max(len(row[i]) for row in rows) for i in range(6)]
        for row in rows:
            cells = [row[0].rjust(widths[0]), row[1].ljust(widths[1])]
            cells += [row[i].rjust(widths[i]) for i in (2, 3, 4, 5)]
            lines.append("  ".join(cells + [row[6]]))
        lines += units_warnings(r.candidates)
    t = r.timings
    if t:
        parts = [f"{k.removesuffix('_ms').replace('_', ' ')} {v:.0f} ms" for k, v in t.items()]
        lines.append("timings: " + ", ".join(parts))
    return "\n".join(lines)
