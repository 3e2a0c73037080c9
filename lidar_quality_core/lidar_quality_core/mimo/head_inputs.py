"""One head's detections as the merge reads them (mimo_ros.pipeline.head_detections): the
class probabilities with a background column, which boxes are usable, their predicted
variances.

Compiled passes over a head's ~25 boxes: the numpy chains they replace were ~12 calls a
head for the probabilities and ~20 for the variances, each far dearer than its arithmetic
once a node's caches have gone cold between frames (0.17 ms a head, measured in the e2e
run, against 0.03 here).
"""
from __future__ import annotations

import numpy as np
from numba import njit, types

from lidar_quality_core.kernel_types import array_in, array_out

__all__ = ["class_probabilities", "ordered_variances"]

_F2A = array_in(types.float64, 2, "A")


@njit(types.Tuple((array_out(types.float64, 2), array_out(types.boolean),
                   array_out(types.boolean), array_out(types.boolean)))(
    _F2A, array_in(types.boolean, 1, "A")), cache=True, nogil=True)
def class_probabilities(fg, valid):
    """From the heads' foreground class scores ``fg`` (n, C) (NaN: no hypothesis of that
    class): ``(probs (n, 1 + C), usable, known, in_range)``. ``probs``:
    background column 0 = clip(1 - sum of the known scores, 0, 1), absent classes 0, the
    rows of unusable boxes NaN; ``known``: some class of the list is scored; ``in_range``:
    every known score in [0, 1]; ``usable``: ``valid & known & in_range``."""
    n, n_cls = fg.shape
    probs = np.empty((n, n_cls + 1))
    usable = np.empty(n, np.bool_)
    known = np.empty(n, np.bool_)
    in_range = np.empty(n, np.bool_)
    for i in range(n):
        total = 0.0
        have = False
        ok = True
        for c in range(n_cls):
            v = fg[i, c]
            if v == v:
                have = True
                ok &= (v >= 0.0) & (v <= 1.0)
            else:
                v = 0.0
            probs[i, c + 1] = v
            total += v
        bg = 1.0 - total
        probs[i, 0] = 0.0 if bg < 0.0 else 1.0 if bg > 1.0 else bg   # NaN stays (np.clip)
        known[i], in_range[i] = have, ok
        usable[i] = valid[i] and have and ok
        if not usable[i]:
            probs[i, :] = np.nan
    return probs, usable, known, in_range


@njit(types.Tuple((array_out(types.float64, 2), types.int64, types.boolean))(
    _F2A, array_in(types.int64, 1, "A")), cache=True, nogil=True)
def ordered_variances(values, index):
    """``(variances (n, 7), entries ignored, in order)`` of a variance message whose
    entry ``k`` names detection ``index[k]``: when every entry is in order (``index[k] ==
    k``), the values with NaN where one is negative or not finite (an entry with such a
    value counted); otherwise ``in order`` False and the caller matches the entries."""
    n = values.shape[0]
    out = np.empty((n, 7))
    for k in range(n):
        if index[k] != k:
            return out, 0, False
    bad = 0
    for k in range(n):
        ok = True
        for j in range(7):
            v = values[k, j]
            good = v >= 0.0 and v - v == 0.0   # finite and not negative
            out[k, j] = v if good else np.nan
            ok &= good
        bad += not ok
    return out, bad, True
