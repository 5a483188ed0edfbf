"""Short stable hashes of configuration, the keys of incremental work and of caches."""

from __future__ import annotations

import hashlib
import json


def fingerprint(obj: object) -> str:
    """Short stable hash of a JSON-serialisable object."""
    blob = json.dumps(obj, sort_keys=True, default=str).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
