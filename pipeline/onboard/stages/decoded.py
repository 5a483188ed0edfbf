"""Views decoded once per batch: the caption, image-embedding and local-feature stages of one batch read the
same rendered PNGs, and each used to decode them again (four decodes of every view in the offline profile).

Inside :func:`batch_scope` (the engines' ``commit_batch`` opens one per batch) :func:`decoded_view` keeps the
images it decoded, keyed by a digest of the PNG bytes (never by mesh id or fingerprint, so a re-rendered view
is never served stale), and drops them all when the scope ends. A batch holds ``batch_size`` (16) meshes of
13 views, 208 images of 0.75 MiB at 512 px; :data:`CAPACITY` bounds a larger batch. Outside a scope (a Ray
actor of a single step, which sees each view once; an actor of several steps opens one per batch) every
call decodes. Consumers treat the images as
read-only (no onboarding stage draws on its input).

Why hand-written rather than :func:`functools.lru_cache`: that would key on the whole bytes object (holding
every PNG as a key), could not be scoped to a batch, and would cache in the Ray actors too.
"""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager

CAPACITY = 256

_cache: OrderedDict[bytes, object] = OrderedDict()
_memo: OrderedDict[tuple[str, bytes], object] = OrderedDict()
_lock = threading.Lock()
_depth = 0


@contextmanager
def batch_scope() -> Iterator[None]:
    """Share decoded views between the stages run inside; forget them on exit."""
    global _depth
    with _lock:
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0:
                _cache.clear()
                _memo.clear()


def decoded_view(data: bytes):
    """The PIL RGB image of a view's PNG bytes; inside :func:`batch_scope`, decoded once per batch."""
    from pipeline.mesh.render import decode_png

    with _lock:
        sharing = _depth > 0
    if not sharing:
        return decode_png(data)
    key = hashlib.blake2b(data, digest_size=16).digest()
    with _lock:
        image = _cache.get(key)
        if image is not None:
            _cache.move_to_end(key)
            return image
    image = decode_png(data)
    with _lock:
        _cache[key] = image
        while len(_cache) > CAPACITY:
            _cache.popitem(last=False)
    return image


def sharing() -> bool:
    """Whether a :func:`batch_scope` is open (what :func:`remember` keeps is then seen by later stages)."""
    with _lock:
        return _depth > 0


def remember(kind: str, data: bytes, value: object) -> None:
    """Keep ``value``, a result of stage work on the view of PNG bytes ``data`` (``kind`` names the work),
    for the later stages of the open batch (:func:`recall`); outside a scope, nothing is kept. The image
    embedding stage keeps the learned encoder's object patch tokens this way, from the forward pass that
    embeds the views, so the ``patches`` stage does not run the encoder again."""
    key = (kind, hashlib.blake2b(data, digest_size=16).digest())
    with _lock:
        if _depth == 0:
            return
        _memo[key] = value
        _memo.move_to_end(key)
        while len(_memo) > CAPACITY:
            _memo.popitem(last=False)


def recall(kind: str, data: bytes) -> object | None:
    """What :func:`remember` kept for ``kind`` and ``data`` in the open batch (``None`` if nothing)."""
    key = (kind, hashlib.blake2b(data, digest_size=16).digest())
    with _lock:
        return _memo.get(key)


def cached() -> int:
    """How many decoded views are held now."""
    with _lock:
        return len(_cache)
