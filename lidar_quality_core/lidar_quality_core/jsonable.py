"""Report values as plain JSON: the one conversion used by every summary and manifest."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["jsonable"]


def jsonable(o: Any, *, drop_private: bool = False) -> Any:
    """``o`` with numpy scalars / arrays as Python numbers / lists, paths as strings, dict
    keys as strings and non-finite floats as ``None`` (JSON has no NaN). ``drop_private``:
    leave out dict keys starting with ``_`` (in-memory extras such as prediction arrays)."""
    if isinstance(o, dict):
        return {str(k): jsonable(v, drop_private=drop_private) for k, v in o.items()
                if not (drop_private and str(k).startswith("_"))}
    if isinstance(o, (list, tuple)):
        return [jsonable(v, drop_private=drop_private) for v in o]
    if isinstance(o, np.ndarray):
        return jsonable(o.tolist(), drop_private=drop_private)
    if isinstance(o, (bool, np.bool_)):
        return bool(o)
    if isinstance(o, (np.integer, int)):
        return int(o)
    if isinstance(o, (np.floating, float)):
        return float(o) if math.isfinite(o) else None
    if isinstance(o, Path):
        return str(o)
    return o
