"""Cache keys of the dataset builders: a change to the code that computes the rows invalidates them."""
from __future__ import annotations

import hashlib
from pathlib import Path


def source_hash(*modules) -> str:
    """Short SHA-256 over the source files of ``modules`` (module objects or paths), in order."""
    h = hashlib.sha256()
    for m in modules:
        p = Path(getattr(m, "__file__", m))
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]
