"""LidarMetaDetect (LMD) box-wise features (paper section III; numpy and numba, no rclpy).

One row per post-NMS box, columns named by :func:`feature_names` (the model store's
feature list). Schemas:

* ``"exact"`` / ``"threshold"`` (90 features, the paper's set), in this order:

  1. 17 own-box quantities ``x, y, z, l, w, h, theta, score, class, volume (V = lwh),
     surface (A = 2(lw + lh + wh)), size_ratio (F = V / A), points (P, points in the box),
     points_frac (Phi = P / |X|), refl_max, refl_mean, refl_std`` (reflectance = the
     cloud's intensity of the in-box points);
  2. ``prop_<q>_<min|max|mean|std>`` over the proposal set Prop(b) for the 16 quantities
     ``q`` other than ``class`` (64);
  3. ``iou_3d_<stat>`` and ``iou_bev_<stat>`` between the box and its proposals (8);
  4. ``n_proposals`` = N = |Prop(b)| (1).
* ``"none"`` (17 features): post-NMS boxes only, for detectors that publish no
  proposals (train the model on this schema).
* Optional extra features, only when asked for (``extra_class_scores`` /
  ``class_scores``): the detector's per-class scores of the box, ``class_score_<name>``,
  appended after the base schema (absent hypotheses, NaN, count as 0).

Decisions (``../shared/notes/method-details.md``, "LMD", from the authors' code
MetaDetect3D; "ours" where the notes leave the choice to us):

* Proposal set. Prop(b) always contains b itself, so N >= 1 (notes: "the output box
  itself included, so N >= 1"). The other members are

  - ``"exact"``: the NMS pre-image given by the caller (``preimage``): the proposals that
    b's NMS survivor suppressed (notes, ours (a)). ``ProposalSets.from_nms`` builds it from
    ``lidar_quality_core.nms.rotated_nms``; the survivor's own index may be in the set or
    not, the result is the same (see "self copy").
  - ``"threshold"``: every proposal whose rotated BEV IoU with b is strictly above
    ``iou_threshold`` (``>``, as in the authors' code and in ``rotated_nms``, where IoU
    equal to the threshold does not suppress), class not checked (authors; ``class_aware``
    restricts to equal labels), default t = 0.5 (notes). Proposals with a score not above
    ``proposal_score_threshold`` (authors: ``score > score_thr``) are ignored.
  - Self copy (ours): a proposal that *is* b, i.e. has b's geometry (IoU_3D >= 1 - 1e-6)
    and b's score (within 1e-6, times max(1, |score|); both tolerances for float32 round
    trips), is not counted twice: b enters the set once, with its own quantities. So a
    detector that includes its survivors in the proposal list and one that does not give
    the same features. Of several such proposals exactly one is b (the closest in score,
    then in IoU_3D, then the lowest score and box values), never "the first one listed".
    A proposal with b's geometry but another score is another proposal (another anchor's
    or class head's) and a member like any other, as in the authors' set, where the
    survivor is one of the proposals above t and every other one counts too. If no
    proposal matches, nothing is dropped. (The authors zero the highest IoU, which is
    the survivor in their data.)
  - Order: the features do not depend on the order of the proposals, to the last bit:
    each set is summed in a canonical order (by score, then box values).
* Set statistics: population std (``np.std``, as the authors). ``theta`` of a proposal
  is taken as ``theta_b + wrap(theta_p - theta_b)`` (ours): near +-pi a set of almost
  equal headings would otherwise get a spurious std of ~pi; a flipped heading still shows
  as a deviation of ~pi. Own ``theta`` is wrapped to [-pi, pi) (ours: detectors differ in
  yaw range).
* IoU statistics (ours): over Prop(b) without b itself. The authors (method notes) keep
  b's match with itself in each list as a 0 ("the self match is set to 0"); with one
  candidate or none the four statistics are 0, as ours with no other member. With m >= 1
  other members theirs differ: min is always 0, and mean (m / (m + 1) times ours) and
  std mix the members' IoUs with that placeholder, a count effect that n_proposals
  already carries; max is the same. Reasons to keep ours: the statistics then describe
  the other proposals only, and the shipped models (models/lmd) were trained on it
  (their trees split iou_bev_min and iou_3d_min at 0.1 .. 0.9; under the authors' rule
  both are constantly 0): following the authors changes every box with another member
  and needs the models retrained. BEV statistics over all other members.
  IoU_3D statistics: ``"threshold"``: over the other members with IoU_3D > t (the authors'
  separate candidate set {IoU_3D > t}; it lies inside the BEV set since IoU_3D <= IoU_BEV);
  ``"exact"``: over all other members of the pre-image.
* In-box points: boundary inclusive, box centre convention (vision_msgs; mmdet3d uses the
  bottom centre), ``box_geometry.points_in_boxes``. A point is used only if x, y, z and
  intensity are finite (NaN points are ignored everywhere, also in |X|). Empty box (or
  |X| = 0): P = 0, Phi = 0 and the reflectance statistics are 0 (authors: statistics of
  [0]). Intensity is used as given (no rescaling): train and run on the same sensor scale.
* ``class``: the class id as a number; string labels are mapped through ``class_names``
  (unknown names -> -1).
* Invalid post-NMS box (non-finite value or score, size <= 0): its row is all NaN, so it
  can never be scored silently; the caller drops or flags it. Invalid proposals (same
  rule) belong to no set.

IoU_3D of a member pair is derived from its exact BEV IoU (intersection area
``I = iou (a1 + a2) / (1 + iou)`` times the z overlap), which saves a second polygon
clipping per pair.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from numba import njit, types

from lidar_quality_core.box_geometry import _pair_stats, as_boxes, as_cloud, inbox_point_stats
from lidar_quality_core.conventions import wrap_angle as _wrap
from lidar_quality_core.iou import iou_bev_pairs, sparse_iou
from lidar_quality_core.kernel_types import F1 as _F1, F2 as _F2, I1 as _I1, array_in, array_out

from .proposal_sets import ProposalSets

__all__ = ["MODES", "OWN_QUANTITIES", "SET_QUANTITIES", "STATS", "DEFAULT_IOU_THRESHOLD",
           "SELF_IOU", "SELF_SCORE_TOL", "ProposalSets", "feature_names", "compute_features"]

MODES = ("exact", "threshold", "none")
OWN_QUANTITIES = ("x", "y", "z", "l", "w", "h", "theta", "score", "class", "volume",
                  "surface", "size_ratio", "points", "points_frac", "refl_max", "refl_mean",
                  "refl_std")
SET_QUANTITIES = tuple(q for q in OWN_QUANTITIES if q != "class")
STATS = ("min", "max", "mean", "std")
DEFAULT_IOU_THRESHOLD = 0.5
#: A proposal with IoU_3D >= SELF_IOU to the box and a score within SELF_SCORE_TOL of
#: its score (times max(1, |score|)) is the box itself (float32 round trips).
SELF_IOU = 1.0 - 1e-6
SELF_SCORE_TOL = 1e-6

_CLASS_COL = OWN_QUANTITIES.index("class")
_THETA_COL = SET_QUANTITIES.index("theta")


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")


def _extra_names(extra) -> tuple[str, ...]:
    if extra is None:
        return ()
    if isinstance(extra, (int, np.integer)):
        if extra < 0:
            raise ValueError(f"extra_class_scores must be >= 0, got {extra}")
        return tuple(f"class_score_{c}" for c in range(int(extra)))
    return tuple(f"class_score_{c}" for c in extra)


def feature_names(mode: str = "exact", extra_class_scores=None) -> tuple[str, ...]:
    """Ordered feature names of ``mode`` (90 for ``"exact"`` / ``"threshold"``, 17 for
    ``"none"``), plus ``class_score_<c>`` per class when ``extra_class_scores`` is a class
    count or a sequence of class names."""
    _check_mode(mode)
    names = list(OWN_QUANTITIES)
    if mode != "none":
        names += [f"prop_{q}_{s}" for q in SET_QUANTITIES for s in STATS]
        names += [f"iou_3d_{s}" for s in STATS] + [f"iou_bev_{s}" for s in STATS]
        names.append("n_proposals")
    return tuple(names) + _extra_names(extra_class_scores)


# ------------------------------------------------------------------ helpers
def _class_ids(labels, n: int, class_names) -> np.ndarray:
    """Labels (ids or names) -> float class ids; unknown names -> -1."""
    if labels is None:
        return np.full(n, -1.0)
    lab = np.asarray(labels).reshape(-1)
    if len(lab) != n:
        raise ValueError(f"labels has {len(lab)} entries for {n} boxes")
    if lab.dtype.kind in "iubf":
        return lab.astype(np.float64)
    if class_names is not None:
        lut = {str(c): float(k) for k, c in enumerate(class_names)}
        return np.array([lut.get(str(s), -1.0) for s in lab.tolist()], dtype=np.float64)
    try:
        return lab.astype(np.int64).astype(np.float64)
    except ValueError:
        raise ValueError("string labels need class_names (or integer strings)") from None


@njit(array_out(types.boolean)(_F2, _F1), cache=True, nogil=True)
def _valid_rows(b, scores):
    # boxes with every value and the score finite and l, w, h > 0
    out = np.empty(len(b), np.bool_)
    for k in range(len(b)):
        ok = np.isfinite(scores[k])
        for c in range(b.shape[1]):
            ok &= np.isfinite(b[k, c])
        out[k] = ok and b[k, 3] > 0.0 and b[k, 4] > 0.0 and b[k, 5] > 0.0
    return out


def _box_ok(b: np.ndarray, scores: np.ndarray) -> np.ndarray:
    return _valid_rows(np.ascontiguousarray(b, np.float64),
                       np.ascontiguousarray(scores, np.float64))


@njit(types.void(_F2, _F1, _F1, _I1, _F1, _F1, _F1, types.int64, array_out(types.float64, 2)),
      cache=True, nogil=True, error_model="numpy")
def _quantity_rows(b, scores, theta, count, mx, mean, std, n_points, q):
    # SET_QUANTITIES row by row, each value's arithmetic in numpy's order (same bits; a
    # division by 0 gives inf / NaN as in numpy)
    for k in range(len(b)):
        for c in range(6):
            q[k, c] = b[k, c]
        q[k, 6], q[k, 7] = theta[k], scores[k]
        l, w, h = b[k, 3], b[k, 4], b[k, 5]
        q[k, 8] = l * w * h
        q[k, 9] = 2.0 * (l * w + l * h + w * h)
        q[k, 10] = q[k, 8] / q[k, 9]
        q[k, 11] = count[k]
        q[k, 12] = count[k] / n_points if n_points else 0.0
        q[k, 13], q[k, 14], q[k, 15] = mx[k], mean[k], std[k]


def _quantities(b, scores, st, n_points: int) -> np.ndarray:
    """(n, 16) SET_QUANTITIES of boxes ``b`` with in-box point statistics ``st``."""
    q = np.empty((len(b), len(SET_QUANTITIES)))
    f8 = np.float64
    with np.errstate(invalid="ignore"):  # an inf yaw: an invalid box, its row NaN anyway
        theta = np.ascontiguousarray(_wrap(b[:, 6]), f8)
    _quantity_rows(np.ascontiguousarray(b, f8), np.ascontiguousarray(scores, f8), theta,
                   st.count, st.max, st.mean, st.std, int(n_points), q)
    return q


@njit(array_out(types.float64)(_F2, _F2, _I1, _I1, _F1), cache=True, nogil=True,
      error_model="numpy")
def _derived_3d(a, b, d, p, iou_bev):
    # IoU_3D of the pairs (a[d], b[p]) from their exact BEV IoU, numpy's operations in
    # its order (np.maximum / np.minimum's NaN rules); a NaN result is 0, clipped to [0, 1]
    out = np.empty(len(d))
    for k in range(len(d)):
        i, j, v = d[k], p[k], iou_bev[k]
        aa, ab = a[i, 3] * a[i, 4], b[j, 3] * b[j, 4]
        inter = v * (aa + ab) / (1.0 + v)
        t1, t2 = a[i, 2] + a[i, 5] / 2, b[j, 2] + b[j, 5] / 2
        top = t1 if t1 <= t2 or np.isnan(t1) else t2
        b1, b2 = a[i, 2] - a[i, 5] / 2, b[j, 2] - b[j, 5] / 2
        bot = b1 if b1 >= b2 or np.isnan(b1) else b2
        z = top - bot
        inter *= z if z >= 0.0 or np.isnan(z) else 0.0
        union = aa * a[i, 5] + ab * b[j, 5] - inter
        r = inter / union if union > 0 else 0.0
        out[k] = 0.0 if np.isnan(r) else min(max(r, 0.0), 1.0)
    return out


def _derived_iou_3d(a, b, d, p, iou_bev):
    """IoU_3D of the pairs ``(a[d], b[p])`` from their exact BEV IoU (module docstring)."""
    f8 = np.float64
    return _derived_3d(np.ascontiguousarray(a, f8), np.ascontiguousarray(b, f8),
                       np.ascontiguousarray(d, np.int64), np.ascontiguousarray(p, np.int64),
                       np.ascontiguousarray(iou_bev, f8))


@njit(cache=True, nogil=True)
def _put_stats(out, at, values, box):
    # IoU statistics over a box's other members (``box_geometry._pair_stats``, pair order)
    _, lo, hi, mean, std = _pair_stats(values, np.arange(len(values)), box, out.shape[0],
                                       False)
    for k in range(out.shape[0]):
        out[k, at], out[k, at + 1], out[k, at + 2], out[k, at + 3] = lo[k], hi[k], mean[k], std[k]


@njit(types.float64(array_in(types.float64), types.int64, types.int64), cache=True,
      nogil=True)
def _pairwise_sum(a, lo, n):
    # numpy's pairwise summation of a[lo:lo + n] (its add.reduce and reduceat on a
    # contiguous run): 8 accumulators, halves above 128 values; the same bits as numpy
    if n < 8:
        r = -0.0
        for i in range(lo, lo + n):
            r += a[i]
        return r
    if n <= 128:
        acc = a[lo:lo + 8].copy()
        i = 8
        while i < n - n % 8:
            for j in range(8):
                acc[j] += a[lo + i + j]
            i += 8
        r = ((acc[0] + acc[1]) + (acc[2] + acc[3])) + ((acc[4] + acc[5]) + (acc[6] + acc[7]))
        for i in range(i, n):
            r += a[lo + i]
        return r
    h = n // 2
    h -= h % 8
    return _pairwise_sum(a, lo, h) + _pairwise_sum(a, lo + h, n - h)


@njit(types.void(_F2, _I1, _I1, _F1, _F1, _F1, types.float64, types.boolean,
                 array_out(types.float64, 2)), cache=True, nogil=True)
def _set_columns(q, d, prow, theta, v_bev, v_3d, t, all_3d, out):
    # The proposal-set columns of the n = len(out) boxes in one call (as numpy, a chain of
    # ~250 calls a frame), after the own quantities: the set statistics over each box's
    # rows (its own q[k] first, then its members q[n + prow] in pair order, heading
    # ``theta`` relative to the box's), the IoU statistics and N. Pairs ``d`` are sorted
    # by box. A set's sums are its first row plus numpy's pairwise sum of the others, as
    # np.add.reduceat adds a run of rows: the same bits as the numpy chain (a gather, a
    # sort, four reduceat, a repeat) this replaces.
    n, nq = out.shape[0], q.shape[1]
    first = np.zeros(n + 1, np.int64)
    for j in range(len(d)):
        first[d[j] + 1] += 1
    for k in range(n):
        first[k + 1] += first[k]
    col = nq + 1
    run = np.empty(np.diff(first).max() + 1 if n else 1)  # one set's values of a column
    for k in range(n):
        a, e = first[k], first[k + 1]
        m = e - a + 1
        cnt = np.float64(m)
        for c in range(nq):
            run[0] = q[k, c] + 0.0 if c == _THETA_COL else q[k, c]
            for j in range(a, e):
                run[j - a + 1] = theta[j] if c == _THETA_COL else q[n + prow[j], c]
            lo = hi = run[0]
            for i in range(1, m):
                v = run[i]
                if not np.isnan(lo) and (v < lo or np.isnan(v)):  # NaN sticks (np.minimum)
                    lo = v
                if not np.isnan(hi) and (v > hi or np.isnan(v)):
                    hi = v
            mean = (run[0] + _pairwise_sum(run, 1, m - 1) if m > 1 else run[0]) / cnt
            for i in range(m):
                run[i] = (run[i] - mean) * (run[i] - mean)
            dev = run[0] + _pairwise_sum(run, 1, m - 1) if m > 1 else run[0]
            o = col + 4 * c
            out[k, o], out[k, o + 1], out[k, o + 2], out[k, o + 3] = (
                lo, hi, mean, np.sqrt(dev / cnt))
        out[k, col + 4 * nq + 8] = cnt
    sel = np.empty(len(d), np.bool_)
    for j in range(len(d)):
        sel[j] = all_3d or v_3d[j] > t
    _put_stats(out, col + 4 * nq, v_3d[sel], d[sel])
    _put_stats(out, col + 4 * nq + 4, v_bev, d)


# ------------------------------------------------------------------ features
def compute_features(points_xyz, intensity, boxes, scores, labels=None, *, proposals=None,
                     mode: str = "exact", preimage=None,
                     iou_threshold: float = DEFAULT_IOU_THRESHOLD, class_scores=None,
                     class_names: Sequence[str] | None = None, class_aware: bool = False,
                     proposal_score_threshold: float | None = None,
                     n_usable: int | None = None) -> np.ndarray:
    """LMD features of the post-NMS ``boxes`` of one frame: (n_boxes, n_features) float64,
    columns as ``feature_names(mode, class_scores.shape[1] if class_scores else None)``.

    ``points_xyz`` (M, 3) and ``intensity`` (M,): the cloud. ``boxes`` (N, 7) ``x, y, z,
    l, w, h, yaw``; ``scores`` (N,); ``labels`` class ids or names (with ``class_names``).
    ``proposals``: ``(boxes, scores[, labels])`` pre-NMS, or None (= no proposals).
    ``preimage`` (mode ``"exact"``): a :class:`ProposalSets`, or one index sequence per box.
    ``iou_threshold``, ``class_aware``, ``proposal_score_threshold``: mode ``"threshold"``.
    ``class_scores`` (N, C): appended as extra features, columns in the order of the class
    names given to ``feature_names``. See the module docstring for every definition.
    ``n_usable``: the cloud's usable points when the caller counted them
    (``box_geometry.inbox_point_stats``).
    """
    _check_mode(mode)
    if not 0.0 <= float(iou_threshold) < 1.0:
        raise ValueError(f"iou_threshold must be in [0, 1), got {iou_threshold}")
    b = as_boxes(boxes)
    n = len(b)
    sc = np.asarray(scores, dtype=np.float64).reshape(-1)
    if len(sc) != n:
        raise ValueError(f"scores has {len(sc)} entries for {n} boxes")
    cls = _class_ids(labels, n, class_names)
    extra = None
    if class_scores is not None:
        extra = np.asarray(class_scores, dtype=np.float64)
        if extra.ndim != 2 or len(extra) != n:
            raise ValueError(f"class_scores must have shape ({n}, C), got {extra.shape}")
        extra = np.nan_to_num(extra, nan=0.0)
    pts, inten = as_cloud(points_xyz, intensity)
    n_feat = len(feature_names(mode, None if extra is None else extra.shape[1]))
    if n == 0:
        return np.zeros((0, n_feat))
    ok = _box_ok(b, sc)

    # --- proposal sets (mode != "none"): member pairs (box d, proposal p) ---------------
    if mode != "none":
        pb, ps, plab = _unpack_proposals(proposals)
        pok = _box_ok(pb, ps)
        d, p, v_bev, v_3d = _member_pairs(mode, b, ok, cls, pb, ps, pok, plab, preimage,
                                          float(iou_threshold), class_aware,
                                          proposal_score_threshold, class_names)
        d, p, v_bev, v_3d, need, prow = _without_self_copies(sc, d, p, v_bev, v_3d, pb, ps)
        allb = np.concatenate([b, pb[need]])
    else:
        allb = b

    # --- in-box points and per-box quantities -------------------------------------------
    st, n_pts = inbox_point_stats(pts, inten, allb, n_usable)
    allsc = sc if mode == "none" else np.concatenate([sc, ps[need]])
    q = _quantities(allb, allsc, st, n_pts)

    out = np.empty((n, n_feat))
    own = len(OWN_QUANTITIES)
    out[:, :_CLASS_COL] = q[:n, :_CLASS_COL]
    out[:, _CLASS_COL] = cls
    out[:, _CLASS_COL + 1:own] = q[:n, _CLASS_COL:]
    if mode != "none":
        th = q[:n, _THETA_COL][d]
        theta = th + _wrap(q[n:, _THETA_COL][prow] - th)  # headings relative to the box's
        _set_columns(q, d, prow, theta, v_bev, v_3d, float(iou_threshold),
                     mode != "threshold", out)
    if extra is not None:
        out[:, n_feat - extra.shape[1]:] = extra
    out[~ok] = np.nan
    return out


def _without_self_copies(sc, d, p, v_bev, v_3d, pb, ps):
    """The member pairs in canonical order, without each box's self copy, and the
    proposals they use: ``(d, p, v_bev, v_3d, need, prow)``, ``need`` the sorted distinct
    ``p`` and ``prow`` each pair's row in it (``np.unique(p, return_inverse=True)``).

    Self copy of box k: a member with k's geometry (IoU_3D >= SELF_IOU) and score
    (within SELF_SCORE_TOL); of several, the closest in score, then in IoU_3D, then the
    lowest (score, box values), so the choice never depends on the proposal order. The
    rest are sorted by (box, score, box values): sums over a set then run in the same
    order whatever order the proposals came in (bit-identical features)."""
    f8, i8 = np.float64, np.int64
    c = np.ascontiguousarray
    return _canonical_sets(c(sc, f8), c(d, i8), c(p, i8), c(v_bev, f8), c(v_3d, f8),
                           c(pb, f8), c(ps, f8), SELF_SCORE_TOL, SELF_IOU)


@njit(types.boolean(_F2, _F1, _I1, types.int64, types.int64), cache=True, nogil=True)
def _before(pb, ps, p, i, j):
    # member p[i] strictly before p[j]: lower score, then lower box values in column order
    if ps[p[i]] != ps[p[j]]:
        return ps[p[i]] < ps[p[j]]
    for c in range(pb.shape[1]):
        if pb[p[i], c] != pb[p[j], c]:
            return pb[p[i], c] < pb[p[j], c]
    return False


@njit(types.Tuple((array_out(types.int64), array_out(types.int64), array_out(types.float64),
                   array_out(types.float64), array_out(types.int64),
                   array_out(types.int64)))(_F1, _I1, _I1, _F1, _F1, _F2, _F1, types.float64,
                                            types.float64), cache=True, nogil=True)
def _canonical_sets(sc, d, p, v_bev, v_3d, pb, ps, tol, self_iou):
    # :func:`_without_self_copies` in one pass over the boxes' runs: each run sorted by
    # score (a stable merge sort; a run with equal scores, rare, by an insertion sort on
    # (score, box values), stable too: numpy's lexsort order), its self copy dropped, then
    # the distinct proposals by a mark table
    m = len(d)
    by_box = np.argsort(d, kind="mergesort")  # the pairs come grouped; kept stable if not
    order = np.empty(m, np.int64)
    keep = np.ones(m, np.bool_)
    a = 0
    while a < m:
        k = d[by_box[a]]
        e = a + 1
        while e < m and d[by_box[e]] == k:
            e += 1
        run = by_box[a:e]
        scores = np.empty(e - a)
        for i in range(e - a):
            scores[i] = ps[p[run[i]]]
        o = run[np.argsort(scores, kind="mergesort")]
        tie = False
        for i in range(1, e - a):
            tie |= ps[p[o[i]]] == ps[p[o[i - 1]]]
        if tie:
            o = run.copy()
            for i in range(1, e - a):
                x = o[i]
                j = i
                while j > 0 and _before(pb, ps, p, x, o[j - 1]):
                    o[j] = o[j - 1]
                    j -= 1
                o[j] = x
        order[a:e] = o
        # the self copy: the closest score, then the highest IoU_3D, then the first
        lim = tol * max(1.0, abs(sc[k]))
        best = -1
        for i in range(a, e):
            q = order[i]
            gap = abs(ps[p[q]] - sc[k])
            if v_3d[q] >= self_iou and gap <= lim:
                if best < 0:
                    best = i
                else:
                    bq = order[best]
                    bgap = abs(ps[p[bq]] - sc[k])
                    if gap < bgap or (gap == bgap and v_3d[q] > v_3d[bq]):
                        best = i
        if best >= 0:
            keep[best] = False
        a = e
    n_out = 0
    for i in range(m):
        n_out += keep[i]
    od, op = np.empty(n_out, np.int64), np.empty(n_out, np.int64)
    ob, o3 = np.empty(n_out), np.empty(n_out)
    used = np.zeros(len(ps), np.int64)
    t = 0
    for i in range(m):
        if keep[i]:
            q = order[i]
            od[t], op[t], ob[t], o3[t] = d[q], p[q], v_bev[q], v_3d[q]
            used[p[q]] = 1
            t += 1
    n_need = 0
    for j in range(len(ps)):
        if used[j]:
            used[j] = n_need
            n_need += 1
        else:
            used[j] = -1
    need = np.empty(n_need, np.int64)
    for j in range(len(ps)):
        if used[j] >= 0:
            need[used[j]] = j
    prow = np.empty(n_out, np.int64)
    for i in range(n_out):
        prow[i] = used[op[i]]
    return od, op, ob, o3, need, prow


def _unpack_proposals(proposals):
    if proposals is None:
        return np.zeros((0, 7)), np.zeros(0), None
    if len(proposals) not in (2, 3):
        raise ValueError("proposals must be (boxes, scores) or (boxes, scores, labels)")
    pb = as_boxes(proposals[0])
    ps = np.asarray(proposals[1], dtype=np.float64).reshape(-1)
    if len(ps) != len(pb):
        raise ValueError(f"proposal scores has {len(ps)} entries for {len(pb)} proposals")
    plab = proposals[2] if len(proposals) == 3 else None
    return pb, ps, plab


def _member_pairs(mode, b, ok, cls, pb, ps, pok, plab, preimage, t, class_aware,
                  score_thr, class_names):
    """(box, proposal, IoU_BEV, IoU_3D) of every member of every set, grouped by box."""
    n = len(b)
    if mode == "exact":
        if preimage is None:
            if len(pb):
                raise ValueError('mode "exact" needs preimage (the NMS pre-image per box)')
            preimage = ProposalSets(np.zeros(n + 1, np.int64), np.zeros(0, np.int64))
        if not isinstance(preimage, ProposalSets):
            preimage = ProposalSets.from_lists(preimage)
        if len(preimage.offsets) != n + 1:
            raise ValueError(f"preimage has {len(preimage.offsets) - 1} sets for {n} boxes")
        d, p = preimage.pairs()
        if len(p) and (p.min() < 0 or p.max() >= len(pb)):
            raise ValueError(f"preimage refers to proposals outside 0..{len(pb) - 1}")
        keep = pok[p] & ok[d]
        d, p = d[keep], p[keep]
        v = iou_bev_pairs(b[d], pb[p])
    else:
        use = pok.copy()
        if score_thr is not None:
            with np.errstate(invalid="ignore"):
                use &= ps > score_thr
        sel = np.flatnonzero(use)
        d, j, v = sparse_iou(b, pb[sel], "bev")
        p = sel[j]
        m = (v > t) & ok[d]
        if class_aware:
            pcls = _class_ids(plab, len(pb), class_names)
            m &= cls[d] == pcls[p]
        d, p, v = d[m], p[m], v[m]
    return d, p, v, _derived_iou_3d(b, pb, d, p, v)
