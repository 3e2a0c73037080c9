"""XGBoost tree ensembles evaluated by one compiled walk (numba), for the small batches of
the online nodes: a frame's ~50 boxes or merged detections.

Why: ``xgboost``'s own predict costs ~0.25 ms for 50 rows when called back to back, but
~1.0 ms once per frame in a node, because its code and its tree objects (300 trees, each
a handful of separately allocated vectors) have left the caches after ~20 ms idle. Here
the trees are packed as complete binary trees in two contiguous arrays (46 kB for 300
trees of depth 4: a tree's conditions and leaves in one row, its features and NaN
directions in one row of 16-bit codes) and walked by one compiled function: ~0.11 ms back
to back, ~0.2 ms in a node. For thousands of rows xgboost's blocked predictor is faster (2000 rows: 3.0
against 4.3 ms), so :mod:`model_store` takes this walk only up to ``MAX_ROWS``.

What it evaluates exactly as xgboost does: the gbtree booster, numerical splits (a row
goes left when ``float32(x) < split_condition``, a missing value (NaN) the way the node's
``default_left`` says), the margin summed in float32 from the base margin in tree order,
then the objective's link (``binary:logistic`` and ``reg:logistic``: sigmoid,
``reg:squarederror``: identity).
Anything else (other objectives, categorical splits, several targets or classes, a
``missing`` value other than NaN, an early-stopping best iteration, trees deeper than
``MAX_DEPTH``, more than ``MAX_FEATURES`` features) is not packed: :func:`pack` says why
and the caller keeps xgboost.
Results agree with xgboost's to float32 rounding: within 1e-6 (relative, or absolute for
probabilities), often to the bit (tested on the shipped models and on trained ones).

The kernel is compiled once and cached next to this module (numba's ``cache=True``; where
that directory is not writable, numba's user cache); a process loads it at import.
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = ["MAX_DEPTH", "MAX_FEATURES", "MAX_ROWS", "TreeEnsemble", "pack", "predict_pair"]

#: deeper trees are left to xgboost (a complete tree of depth 10 has 2047 slots)
MAX_DEPTH = 10
#: larger batches are left to xgboost: its blocked walk is faster there (measured on the
#: shipped 300-tree models: equal at ~300 rows back to back, ~1500 rows once per frame)
MAX_ROWS = 512
#: a node's code: its feature index in the low 15 bits, 1 in the top bit where a missing
#: value goes right (models of more features are left to xgboost)
_FEATURE, _NAN_SHIFT = 0x7FFF, 15
MAX_FEATURES = _FEATURE + 1
_LINKS = {"binary:logistic": "logistic", "reg:logistic": "logistic",
          "reg:squarederror": "identity"}


@njit(inline="always")
def _step(X, r, i, nodes, codes):
    # v >= threshold: right; NaN compares false: right only if the node's NaN bit is set
    c = codes[i]
    v = X[r, c & _FEATURE]
    return 2 * i + 1 + np.int64(v >= nodes[i]) + np.int64(v != v) * np.int64(c >> _NAN_SHIFT)


@njit("void(float32[:, ::1], float32[:, ::1], uint16[:, ::1], int64, float32, float32[::1])",
      cache=True, nogil=True)
def _margins(X, nodes, codes, depth, base, out):
    # eight rows at a time (then four, then one), each tree walked for all of them
    # together: their walks are independent chains of loads the CPU overlaps, kept in
    # registers (eight against four: 15 % faster on the shipped models; a block of rows
    # walked level by level through an index array was 1.2x slower, one row at a time
    # 2x); each row still sums its leaves in tree order. A walk ends on slot i in
    # [inner, 2 inner]: the leaf's value is nodes[t, i].
    n, n_trees = X.shape[0], nodes.shape[0]
    r = 0
    while r + 8 <= n:
        a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = base
        for t in range(n_trees):
            nd, cd = nodes[t], codes[t]
            i0 = i1 = i2 = i3 = i4 = i5 = i6 = i7 = 0
            for _ in range(depth):
                i0 = _step(X, r, i0, nd, cd)
                i1 = _step(X, r + 1, i1, nd, cd)
                i2 = _step(X, r + 2, i2, nd, cd)
                i3 = _step(X, r + 3, i3, nd, cd)
                i4 = _step(X, r + 4, i4, nd, cd)
                i5 = _step(X, r + 5, i5, nd, cd)
                i6 = _step(X, r + 6, i6, nd, cd)
                i7 = _step(X, r + 7, i7, nd, cd)
            a0 += nd[i0]
            a1 += nd[i1]
            a2 += nd[i2]
            a3 += nd[i3]
            a4 += nd[i4]
            a5 += nd[i5]
            a6 += nd[i6]
            a7 += nd[i7]
        out[r], out[r + 1], out[r + 2], out[r + 3] = a0, a1, a2, a3
        out[r + 4], out[r + 5], out[r + 6], out[r + 7] = a4, a5, a6, a7
        r += 8
    while r + 4 <= n:
        a0 = a1 = a2 = a3 = base
        for t in range(n_trees):
            nd, cd = nodes[t], codes[t]
            i0 = i1 = i2 = i3 = 0
            for _ in range(depth):
                i0 = _step(X, r, i0, nd, cd)
                i1 = _step(X, r + 1, i1, nd, cd)
                i2 = _step(X, r + 2, i2, nd, cd)
                i3 = _step(X, r + 3, i3, nd, cd)
            a0 += nd[i0]
            a1 += nd[i1]
            a2 += nd[i2]
            a3 += nd[i3]
        out[r], out[r + 1], out[r + 2], out[r + 3] = a0, a1, a2, a3
        r += 4
    for r in range(r, n):
        a = base
        for t in range(n_trees):
            nd, cd = nodes[t], codes[t]
            i = 0
            for _ in range(depth):
                i = _step(X, r, i, nd, cd)
            a += nd[i]
        out[r] = a


@dataclass(frozen=True)
class TreeEnsemble:
    """Trees of one xgboost model as complete binary trees (heap order: node ``i`` has
    children ``2i + 1``, ``2i + 2``; a leaf above the full depth is repeated over the
    slots below it), each tree one row of two arrays: ``nodes`` (trees, 2 inner + 1)
    float32, the inner nodes' split conditions then the leaves' values, and ``codes``
    (trees, inner) uint16, each inner node's feature index and NaN direction (``inner`` =
    ``2**depth - 1``). One row of ``nodes`` and one of ``codes`` is all a tree's walk
    reads: on the shipped models 0.30 -> 0.22 ms for both of MIMO's models and a frame's
    55 rows, against four arrays (features int32, conditions, NaN directions int8,
    leaves) read before. ``feature``, ``threshold``, ``nan_right`` and ``leaf`` give them
    apart."""

    nodes: np.ndarray
    codes: np.ndarray
    depth: int
    base_margin: np.float32
    link: str
    n_features: int

    @property
    def feature(self) -> np.ndarray:
        """Split feature of each inner node, ``(trees, inner)``."""
        return (self.codes & _FEATURE).astype(np.int64)

    @property
    def threshold(self) -> np.ndarray:
        """Split condition of each inner node (inf on the padding below a leaf)."""
        return self.nodes[:, :self.codes.shape[1]]

    @property
    def nan_right(self) -> np.ndarray:
        """1 where a missing value goes right, ``(trees, inner)``."""
        return (self.codes >> _NAN_SHIFT).astype(np.int8)

    @property
    def leaf(self) -> np.ndarray:
        """Leaf values in slot order, ``(trees, inner + 1)``."""
        return self.nodes[:, self.codes.shape[1]:]

    def margin(self, X) -> np.ndarray:
        """Summed tree outputs plus the base margin, float32 ``(n,)``."""
        X = np.require(X, np.float32, "CW")  # the kernel's signature: writable, C order
        if X.ndim != 2 or X.shape[1] != self.n_features:
            raise ValueError(f"X must be (n, {self.n_features}), got {X.shape}")
        out = np.empty(len(X), dtype=np.float32)
        _margins(X, self.nodes, self.codes, self.depth, self.base_margin, out)
        return out

    def predict(self, X) -> np.ndarray:
        """What xgboost's predict returns for ``X`` (probability of the positive class or
        the regression value), float64 ``(n,)``."""
        return self.linked(self.margin(X))

    def linked(self, m: np.ndarray) -> np.ndarray:
        """The objective's link of float32 margins ``m``, float64 (NaN stays NaN)."""
        if self.link == "logistic":
            # xgboost's sigmoid is float32; rounded once from float64 here (the exp
            # implementations differ in the last bit anyway)
            m = (1.0 / (1.0 + np.exp(-m.astype(np.float64)))).astype(np.float32)
        return m.astype(np.float64)


_F8 = "float64[:, ::1]"


@njit(f"void({_F8}, float32[:, ::1], uint16[:, ::1], int64, float32, float32[::1], "
      "float32[:, ::1], uint16[:, ::1], int64, float32, float32[::1], boolean[::1])",
      cache=True, nogil=True)
def _pair(X, nodes_a, codes_a, depth_a, base_a, out_a, nodes_b, codes_b, depth_b, base_b,
          out_b, missing):
    # predict_pair's rows, as float32 with +-inf as missing, walked through both
    # ensembles; ``missing``: the rows of nothing but NaN
    n, m = X.shape
    Xf = np.empty((n, m), np.float32)
    for r in range(n):
        none = m > 0
        for c in range(m):
            v = X[r, c]
            if v == v:
                none = False
                if np.isinf(v):
                    v = np.nan
            Xf[r, c] = np.float32(v)
        missing[r] = none
    _margins(Xf, nodes_a, codes_a, depth_a, base_a, out_a)
    _margins(Xf, nodes_b, codes_b, depth_b, base_b, out_b)


def predict_pair(a: TreeEnsemble, b: TreeEnsemble, X) -> tuple[np.ndarray, np.ndarray]:
    """``(a.predict(X'), b.predict(X'))`` of a node's two models on the same rows in one
    compiled pass, where ``X'`` is ``X`` with +-inf as missing (a split value otherwise);
    a row with every feature NaN gets NaN from both (an input the feature code flagged,
    never a score). Bit for bit the two ``predict`` calls on the other rows: ~60 Python
    calls fewer a frame (the row checks, the conversion, two walks' wrappers)."""
    X = np.ascontiguousarray(X, np.float64)
    if X.ndim != 2 or X.shape[1] != a.n_features or b.n_features != a.n_features:
        raise ValueError(f"X must be (n, {a.n_features}) for both models, got {X.shape}")
    out_a = np.empty(len(X), np.float32)
    out_b = np.empty(len(X), np.float32)
    missing = np.empty(len(X), np.bool_)
    _pair(X, a.nodes, a.codes, a.depth, a.base_margin, out_a, b.nodes, b.codes, b.depth,
          b.base_margin, out_b, missing)
    pa, pb = a.linked(out_a), b.linked(out_b)
    if missing.any():  # NaN as np.full writes it (the link can flip a NaN's sign bit)
        pa[missing] = np.nan
        pb[missing] = np.nan
    return pa, pb


def _depth(left, right, node=0) -> int:
    stack, deepest = [(node, 0)], 0
    while stack:
        i, d = stack.pop()
        if left[i] == -1:
            deepest = max(deepest, d)
        else:
            stack += [(left[i], d + 1), (right[i], d + 1)]
    return deepest


def pack(booster, missing=float("nan")) -> tuple[TreeEnsemble | None, str]:
    """``(TreeEnsemble, "")`` of an ``xgboost.Booster``, or ``(None, why not)`` when its
    model is one this walk does not evaluate exactly like xgboost."""
    cfg = json.loads(booster.save_raw("json"))["learner"]
    objective = cfg["objective"]["name"]
    gb = cfg["gradient_booster"]
    mp = cfg["learner_model_param"]
    if objective not in _LINKS:
        return None, f"objective {objective}"
    if gb.get("name") != "gbtree":
        return None, f"booster {gb.get('name')}"
    if int(mp.get("num_class", 0)) > 1 or int(mp.get("num_target", 1)) != 1:
        return None, "several classes or targets"
    if not (isinstance(missing, float) and math.isnan(missing)):
        return None, f"missing value {missing!r} (NaN expected)"
    if booster.attr("best_iteration") is not None:
        return None, "an early-stopping best iteration"
    trees = gb["model"]["trees"]
    if not trees:
        return None, "no trees"
    if any(any(t.get("split_type", ())) or t.get("categories_nodes") for t in trees):
        return None, "categorical splits"
    depth = max(_depth(t["left_children"], t["right_children"]) for t in trees)
    if depth > MAX_DEPTH:
        return None, f"depth {depth} > {MAX_DEPTH}"
    depth = max(depth, 1)
    n_features = int(mp["num_feature"])
    if n_features > MAX_FEATURES:
        return None, f"{n_features} features > {MAX_FEATURES}"
    inner = (1 << depth) - 1
    n = len(trees)
    nodes = np.zeros((n, 2 * inner + 1), dtype=np.float32)
    nodes[:, :inner] = np.inf  # padding: all go left
    codes = np.zeros((n, inner), dtype=np.uint16)
    for k, t in enumerate(trees):
        left, right = t["left_children"], t["right_children"]
        cond, feat, dleft = t["split_conditions"], t["split_indices"], t["default_left"]
        stack = [(0, 0, 0)]  # (node, heap slot, level)
        while stack:
            node, slot, level = stack.pop()
            if left[node] == -1:  # a leaf: its value over every slot below it
                lo = hi = slot
                for _ in range(depth - level):
                    lo, hi = 2 * lo + 1, 2 * hi + 2
                nodes[k, lo:hi + 1] = cond[node]
                continue
            nodes[k, slot] = cond[node]
            codes[k, slot] = feat[node] | (0 if dleft[node] else 1 << _NAN_SHIFT)
            stack += [(left[node], 2 * slot + 1, level + 1),
                      (right[node], 2 * slot + 2, level + 1)]
    base = float(str(mp["base_score"]).strip("[]").split(",")[0])
    link = _LINKS[objective]
    if link == "logistic":
        if not 0.0 < base < 1.0:
            return None, f"base_score {base} outside (0, 1)"
        # xgboost's ProbToMargin in float32, as it computes it (float64 can be 1 ulp off)
        b32 = np.float32(base)
        base = -np.log(np.float32(1.0) / b32 - np.float32(1.0))
    return TreeEnsemble(nodes, codes, depth, np.float32(base), link, n_features), ""
