"""Open-set answers: is the best candidate the object, or does the library not hold it?

Every ranking returns a best model, also for an object the library lacks. This module turns the scores of
one answer into ``confidence``, a calibrated probability that the top-1 model is the right one, and
``accepted = confidence >= accept_threshold``. It runs on plain numbers (no model, no store):

* :func:`answer_features` reads the answer's features: the top-1 ranking score (fused with verification
  when verified), its margin to the next model, the top-1's verification inliers, its stage-1 text score
  and how far that is behind the best text score of the candidates, whether stage 1 had to fall back
  (nothing reached tau), and ``cohort_z``: how many standard deviations the top-1's image score stands
  above the query's image scores over the library (a cohort of up to 1024 meshes; score normalisation
  as in speaker verification: an absent object's best match rarely stands out of the crowd); and, when the
  learned view encoder is fused, ``learned`` (the top-1's raw learned-encoder cosine, an absolute measure
  of how alike the ROI and the model's closest view look) and ``learned_z`` (the same cohort score of it);
  ``score_z`` / ``margin_z``: the top-1's ranking key and its lead over the second in standard deviations
  of the keys of every candidate ranked (``None`` with fewer than 3).
* A :class:`Calibration` holds one logistic model per ranking variant (mode, verified or not), fitted by
  ``python -m pipeline.evaluate openset`` on a split where the right mesh is absent
  (:mod:`pipeline.evaluate.openset`), and its default operating point. Each profile's calibration ships
  as JSON beside this module (``pipeline/query/calibration/<profile>.json``); ``QuerySettings.accept_model``
  names another file.

A calibration is only valid for the models it was fitted with (it records their keys): with other models,
or a variant it has no model for, the answer says so and carries ``accepted = confidence = None``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from pipeline.query.patches import LEAD_FEATURES, PATCH_FEATURES, UNION_FEATURES

#: every feature an answer offers; a variant's model uses a subset (stored in the calibration)
FEATURES = (
    "score",
    "margin",
    "inliers",
    "text_score",
    "text_gap",
    "fallback",
    "cohort_z",
    "learned",
    "learned_z",
    "score_z",
    "margin_z",
    "image_lead",
    "learned_lead",
    *PATCH_FEATURES,
    *LEAD_FEATURES,
    *UNION_FEATURES,
)
#: meshes whose image scores make the cohort of ``cohort_z`` (all of them in smaller libraries)
COHORT_SIZE = 1024
#: features that are z-scores over a sample of the answer's own scores: the ranked candidates' keys
#: (``score_z``, ``margin_z``) or the library's cohort (``cohort_z``, ``learned_z``)
Z_FEATURES = {"score_z": "candidates", "margin_z": "candidates", "cohort_z": "cohort", "learned_z": "cohort"}
#: how a verdict's note names each sample of :data:`Z_FEATURES`
Z_SAMPLE_NAMES = {"candidates": "ranked models", "cohort": "library models"}
#: the fewest scores a z-score feature is read from before a verdict that uses it is given: over a handful
#: of models the best one cannot stand out (at most sqrt(n - 1) standard deviations), so a right answer in a
#: 4-model library looked like an absent object's
MIN_Z_SAMPLE = 20
#: margins are clipped here (a lone candidate has no next model and gets the cap)
MARGIN_CAP = 0.25
#: the roles whose model identity decides whether a calibration applies
CALIBRATED_ROLES = ("captioner", "text_encoder", "view_encoder", "clip_image_encoder")
#: options of the learned view encoder that do not move its scores (left out of its identity)
UNSCORED_OPTIONS = ("precision", "batch_size", "device")
FORMAT = 1


def learned_identity(spec) -> str:
    """The learned view encoder as a calibration sees it: its id and the options that move its cosines
    (input size, pooling, flip, ROI framing)."""
    opts = {k: v for k, v in sorted(spec.options.items()) if k not in UNSCORED_OPTIONS}
    if "roi_margin" in opts and not opts["roi_margin"]:  # no framing: as when the option is not given
        del opts["roi_margin"]
    return f"{spec.key()} {json.dumps(opts, sort_keys=True)}"


def model_identities(profile, onboarding, fused: bool, settings=None) -> dict[str, str | None]:
    """What a calibration is tied to: the store's models of :data:`CALIBRATED_ROLES`, and the learned view
    encoder as the query fuses it, with the fusion weights (``settings``' ``fuse_*``), since the fused
    score's distribution depends on both. ``fused``: whether the ranking context fuses it
    (``RankContext.learned``: the role kept and the store holding its embeddings); ``None`` when it does
    not. A calibration written before the weights were recorded has no ``fusion`` entry and is not checked
    on it."""
    from pipeline.query.fusion import fusion_identity

    out = {r: onboarding.models.get(r) for r in CALIBRATED_ROLES}
    out["learned_encoder"] = learned_identity(profile.learned_encoder) if fused else None
    out["fusion"] = fusion_identity(settings) if fused and settings is not None else None
    return out


class CalibrationError(ValueError):
    """A calibration file that cannot be read or is malformed (one line)."""


def variant_of(mode: str, verified: bool) -> str:
    """The calibration variant of a ranking: its mode, plus ``+verify`` when local features re-ranked it."""
    return f"{mode}+verify" if verified and mode != "text-only" else mode


def answer_features(
    keys: list[float],
    inliers: int | None,
    text_score: float | None,
    used_fallback: bool,
    best_text: float | None = None,
    image: float | None = None,
    cohort: tuple[float, float] | None = None,
    learned: float | None = None,
    learned_cohort: tuple[float, float] | None = None,
    key_stats: tuple[float, float] | None = None,
) -> dict[str, float | None]:
    """Features of one answer. ``keys``: the ranking key (fused score when verified, else the image score;
    text score in text-only mode) of the best candidates in rank order, at least the top two when there
    are two; ``inliers`` / ``text_score``: the top-1's (``None`` when not verified / no stage 1);
    ``best_text``: the best stage-1 score of any candidate (``text_gap`` = how far the top-1 is behind it);
    ``image`` / ``cohort``: the top-1's image score and the (mean, std) of the query's image scores over
    the library's cohort (``cohort_z`` = how far the top-1 stands out of the library, in stds);
    ``learned`` / ``learned_cohort``: the same for the learned encoder's cosine (``None`` when not fused);
    ``key_stats``: (mean, std) of the ranking keys of every candidate (``score_z``, ``margin_z``)."""
    if not keys:
        return dict.fromkeys(FEATURES)
    s1 = float(keys[0])
    margin = max(
        MARGIN_CAP if len(keys) < 2 or not math.isfinite(keys[1]) else min(s1 - float(keys[1]), MARGIN_CAP),
        0.0,
    )
    return {
        "score": s1 if math.isfinite(s1) else None,
        "margin": margin,
        "inliers": None if inliers is None or inliers < 0 else math.log1p(int(inliers)),
        "text_score": None if text_score is None or not math.isfinite(text_score) else float(text_score),
        "text_gap": None
        if text_score is None or best_text is None or not math.isfinite(best_text - text_score)
        else max(float(best_text) - float(text_score), 0.0),
        "fallback": 1.0 if used_fallback else 0.0,
        "cohort_z": _z(image, cohort),
        "learned": None if learned is None or not math.isfinite(learned) else float(learned),
        "learned_z": _z(learned, learned_cohort),
        "score_z": _z(s1, key_stats),
        "margin_z": None if key_stats is None or not key_stats[1] > 0 else margin / key_stats[1],
        "image_lead": None,
        "learned_lead": None,
    }


def _z(value: float | None, cohort: tuple[float, float] | None) -> float | None:
    """How many of the cohort's stds ``value`` lies above its mean (``None`` without both)."""
    if value is None or cohort is None or not math.isfinite(value) or not cohort[1] > 0:
        return None
    return (float(value) - cohort[0]) / cohort[1]


@dataclass(frozen=True)
class AcceptModel:
    """A logistic model of P(top-1 right | features) for one ranking variant, and its operating point."""

    features: tuple[str, ...]
    mean: tuple[float, ...]
    scale: tuple[float, ...]
    coef: tuple[float, ...]
    intercept: float
    threshold: float  # default accept_threshold (the operating point chosen by cross-validation)

    def __post_init__(self) -> None:
        n = len(self.features)
        if not n or any(len(v) != n for v in (self.mean, self.scale, self.coef)):
            raise CalibrationError("calibration model: features, mean, scale and coef differ in length")
        unknown = set(self.features) - set(FEATURES)
        if unknown:
            raise CalibrationError(f"calibration model: unknown features {sorted(unknown)}")
        if not 0.0 <= self.threshold <= 1.0:
            raise CalibrationError(f"calibration threshold must be within [0, 1], got {self.threshold}")

    def confidence(self, feats: dict[str, float | None]) -> float | None:
        """P(top-1 right) for ``feats`` (``None`` when a feature the model needs is missing)."""
        x = [feats.get(f) for f in self.features]
        if any(v is None for v in x):
            return None
        return float(self.predict(np.asarray([x], np.float64))[0])

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Confidences of the rows of ``x`` (columns in ``features`` order)."""
        z = (np.asarray(x, np.float64) - np.asarray(self.mean)) / np.asarray(self.scale)
        logit = z @ np.asarray(self.coef) + self.intercept
        return 1.0 / (1.0 + np.exp(-np.clip(logit, -50, 50)))

    def to_json(self) -> dict:
        return {
            "features": list(self.features),
            "mean": list(self.mean),
            "scale": list(self.scale),
            "coef": list(self.coef),
            "intercept": self.intercept,
            "threshold": self.threshold,
        }

    @classmethod
    def from_json(cls, d: dict) -> AcceptModel:
        try:
            return cls(
                features=tuple(d["features"]),
                mean=tuple(float(v) for v in d["mean"]),
                scale=tuple(float(v) for v in d["scale"]),
                coef=tuple(float(v) for v in d["coef"]),
                intercept=float(d["intercept"]),
                threshold=float(d["threshold"]),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"calibration model: {type(exc).__name__}: {exc}") from None


@dataclass(frozen=True)
class Calibration:
    """One profile's acceptance models by variant, the model keys they were fitted with, how (``fit``)."""

    profile: str
    models: dict[str, str | None]  # role -> "backend:model_id" at fitting time
    variants: dict[str, AcceptModel]
    fit: dict = field(default_factory=dict)  # command, data, cross-validated rates (provenance only)
    source: str = ""  # the file it was read from

    def mismatch(self, models: dict[str, str | None]) -> str | None:
        """Why this calibration does not apply to a store onboarded with ``models`` (``None``: it applies)."""
        for role in (*CALIBRATED_ROLES, "learned_encoder", "fusion"):  # a calibration older than the
            if role in self.models and self.models.get(role) != models.get(role):  # learned encoder or
                return (  # the recorded fusion weights has no entry for them
                    f"acceptance calibrated for {role} {self.models.get(role)}, this store and query use "
                    f"{models.get(role)}: re-calibrate with `python -m pipeline.evaluate openset` (docs/query.md)"
                )
        return None

    def to_json(self) -> dict:
        return {
            "format": FORMAT,
            "profile": self.profile,
            "models": self.models,
            "variants": {k: v.to_json() for k, v in sorted(self.variants.items())},
            "fit": self.fit,
        }

    @classmethod
    def from_json(cls, d: dict, source: str = "") -> Calibration:
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise CalibrationError(
                f"{source or 'calibration'}: not an acceptance calibration of format {FORMAT}"
            )
        try:
            variants = {str(k): AcceptModel.from_json(v) for k, v in d["variants"].items()}
            return cls(str(d["profile"]), dict(d["models"]), variants, dict(d.get("fit") or {}), source)
        except (KeyError, TypeError, AttributeError) as exc:
            raise CalibrationError(f"{source or 'calibration'}: {type(exc).__name__}: {exc}") from None

    def write(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1) + "\n", encoding="utf-8")
        tmp.replace(path)
        return path


def shipped_path(profile: str) -> Path:
    """Where the package keeps ``profile``'s calibration (it may not exist)."""
    return Path(str(resources.files("pipeline.query").joinpath("calibration", f"{profile}.json")))


def load_calibration(profile: str, path: str | Path | None = None) -> Calibration | None:
    """``path``'s calibration, or the one shipped for ``profile`` (``None`` when the package has none)."""
    if path is not None:
        return _read(str(path))
    p = shipped_path(profile)
    return _read(str(p)) if p.is_file() else None


@lru_cache(maxsize=16)
def _read_cached(path: str, mtime: float) -> Calibration:
    try:
        d = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CalibrationError(f"acceptance calibration not found: {path}") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CalibrationError(f"cannot read acceptance calibration {path}: {exc}") from None
    return Calibration.from_json(d, path)


def _read(path: str) -> Calibration:
    try:
        mtime = Path(path).stat().st_mtime
    except OSError:
        raise CalibrationError(f"acceptance calibration not found: {path}") from None
    return _read_cached(path, mtime)


@dataclass(frozen=True)
class Verdict:
    """The open-set decision of one answer."""

    accepted: bool | None  # None: not judged (no calibration applies; see note)
    confidence: float | None
    threshold: float | None
    variant: str
    features: dict[str, float | None]
    note: str | None = None

    def to_dict(self) -> dict:
        return {
            "variant": self.variant,
            "features": {k: (None if v is None else round(v, 6)) for k, v in self.features.items()},
            "note": self.note,
        }


def judge(
    calibration: Calibration | None,
    feats: dict[str, float | None],
    variant: str,
    threshold: float | None = None,
    mismatch: str | None = None,
    samples: dict[str, int] | None = None,
) -> Verdict:
    """Confidence and acceptance of one answer; ``threshold`` overrides the calibration's operating point.
    ``samples``: how many scores the z-score features were read from (``{"candidates": n, "cohort": m}``);
    a model using one read from fewer than :data:`MIN_Z_SAMPLE` does not judge (``accepted`` ``None``)."""
    if threshold is not None and not 0.0 <= float(threshold) <= 1.0:
        raise ValueError(f"accept threshold must be within [0, 1], got {threshold}")
    if feats.get("score") is None and all(v is None for v in feats.values()):
        t = None if threshold is None else float(threshold)
        return Verdict(False, 0.0, t, variant, feats, "no candidate: the library holds no model to match")
    if calibration is None or mismatch:
        note = mismatch or "no acceptance calibration for this profile: answers are not judged"
        return Verdict(None, None, threshold, variant, feats, note)
    model = calibration.variants.get(variant)
    if model is None:
        return Verdict(None, None, threshold, variant, feats, f"no acceptance calibration for {variant}")
    t = model.threshold if threshold is None else float(threshold)
    small = [
        f
        for f in model.features
        if f in Z_FEATURES and (samples or {}).get(Z_FEATURES[f], MIN_Z_SAMPLE) < MIN_Z_SAMPLE
    ]
    if small:
        over = [f"{f} over {samples[Z_FEATURES[f]]} {Z_SAMPLE_NAMES[Z_FEATURES[f]]}" for f in small]
        note = (f"the acceptance model reads z-scores, which need at least {MIN_Z_SAMPLE} scores: "
                f"{', '.join(over)}")  # fmt: skip
        return Verdict(None, None, t, variant, feats, note)
    conf = model.confidence(feats)
    if conf is None:
        need = [f for f in model.features if feats.get(f) is None]
        return Verdict(None, None, t, variant, feats, f"missing features for acceptance: {', '.join(need)}")
    return Verdict(bool(conf >= t), round(conf, 6), t, variant, feats)


def ranking_features(
    order: np.ndarray,
    keys: np.ndarray,
    inliers: np.ndarray,
    text: np.ndarray | None,
    used_fallback: bool,
    image: np.ndarray | None = None,
    cohort: tuple[float, float] | None = None,
    learned: np.ndarray | None = None,
    learned_cohort: tuple[float, float] | None = None,
) -> dict[str, float | None]:
    """:func:`answer_features` from a ranking's arrays: ``order`` (candidate positions, best first), the
    ranking ``keys``, verification ``inliers`` (-1 = not verified), stage-1 ``text``, stage-2 ``image`` and
    ``learned`` scores by position, and the query's ``cohort`` / ``learned_cohort`` statistics
    (:func:`cohort_stats`); the keys' own statistics over every candidate are taken here."""
    if not len(order):
        return answer_features([], None, None, used_fallback)
    top = int(order[0])
    inl = int(inliers[top]) if inliers is not None and inliers[top] >= 0 else None
    t = None if text is None else float(text[top])
    best = None if text is None else float(np.max(text))
    img = None if image is None else float(image[top])
    lrn = None if learned is None else float(learned[top])
    keys2 = [float(keys[int(j)]) for j in order[:2]]
    out = answer_features(
        keys2, inl, t, used_fallback, best, img, cohort, lrn, learned_cohort, cohort_stats(keys)
    )
    out["image_lead"], out["learned_lead"] = channel_lead(image, top), channel_lead(learned, top)
    return out


def channel_lead(scores: np.ndarray | None, top: int) -> float | None:
    """How far the top-1 (position ``top``) leads every other candidate in one channel's ``scores``
    (negative: another candidate scores higher there; ``None`` without two finite scores). The fused
    ranking can crown a compromise that no single channel puts first, as an absent object's look-alikes
    split the channels; a right model usually leads in each."""
    if scores is None or not 0 <= top < len(scores):
        return None
    s = np.asarray(scores, np.float64)
    own = s[top]
    rest = np.delete(s, top)
    rest = rest[np.isfinite(rest)]
    if not math.isfinite(own) or not len(rest):
        return None
    return float(own - rest.max())


def cohort_indices(n_meshes: int, size: int = COHORT_SIZE) -> np.ndarray:
    """The meshes (positions) whose image scores form the cohort: all of them up to ``size``, else an
    evenly spaced ``size`` (deterministic; the cost per query stays bounded in large libraries)."""
    if n_meshes <= size:
        return np.arange(n_meshes)
    return np.unique(np.linspace(0, n_meshes - 1, size).round().astype(np.int64))


def cohort_stats(scores: np.ndarray) -> tuple[float, float] | None:
    """(mean, std) of a query's finite image scores over the cohort (``None`` with fewer than 3)."""
    s = np.asarray(scores, np.float64)
    s = s[np.isfinite(s)]
    return (float(s.mean()), float(s.std())) if len(s) >= 3 else None
