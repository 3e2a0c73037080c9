"""Domain profile and drift score: how far live inputs are from a meta model's training data.

A :class:`DomainProfile` summarises the training data of a model quantity by quantity
(each feature column; per-frame input statistics such as points per frame, intensity or
the detector's scores): the quantiles at ``LEVELS`` (0, 5, ..., 100 %) of its finite
values, their count, and the fraction of missing (NaN) values. It is JSON (stored in a
model's manifest) and small: 23 numbers per quantity.

Drift of live values against a quantity: the population stability index (PSI) over the
profile's quantile bins. Training puts mass q_i in bin i (1/B for B bins between
quantiles, ties merged), the live sample p_i; PSI = sum (p_i - q_i) ln(p_i / q_i), both
floored at ``EPS``. A missing-value rate is one more bin. For small samples PSI is biased
upwards (under no shift its expectation is about (B - 1) / n, as a chi-square over n):
:func:`psi` uses fewer bins for few values (about ``VALUES_PER_BIN`` live values a bin)
and subtracts that expectation, so that in-domain windows score near 0 whatever their
size. Conventional reading: < 0.1 no shift, 0.1-0.25 moderate, > 0.25 major.

:class:`DriftMonitor` keeps the last ``window`` frames' values per quantity; after each
frame, ``score`` is the largest PSI beyond the quantity's ``spread`` (a window holds a
scene or two, and one training sequence's values already differ from the mix of all
sequences by that much: positions, sizes) over the quantities with at least ``min_values``
values in the window (a per-frame statistic needs that many frames; a per-box feature a
frame or two), once the window holds ``min_frames`` frames (10, or the window); the
most drifted ones are named in words by :func:`explain`, and ``level`` is OK / WARN /
ERROR from two thresholds. The default thresholds are the conventional PSI
readings; they are to be calibrated on held-out in-domain frames and simulated shifts
(issue 18's domain-shift benchmark).

There is only the window's score, reported after every frame: no score of a frame alone.
A frame holds one value of each per-frame statistic and (LMD, MIMO) typically 5-30 boxes,
fewer than the ``min_values`` (30) a quantity needs before its PSI's noise is below the
thresholds; one frame's values (LMS: its segments, however many) are one scene's, whose
difference from the training mix is the ``spread`` a window is allowed; and the
thresholds hold for windows. The nodes put the window's verdict in their quality messages
(:meth:`DomainVerdict.message_fields`: level, score, frames, quantities, passthrough;
``lidar_quality_msgs`` version 1).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field
from collections.abc import Iterable, Mapping

import numpy as np
from numba import njit

from .parameters import param

__all__ = ["LEVELS", "EPS", "VALUES_PER_BIN", "QuantityProfile", "DomainProfile", "psi",
           "fine_counts", "psi_counts",
           "DriftMonitor", "DriftReport", "explain", "ACTIONS", "DriftParameters",
           "DomainCheck", "DomainVerdict", "STATE_CONSTANTS"]

LEVELS = tuple(np.linspace(0.0, 1.0, 21).round(4).tolist())   # 0, 5, ..., 100 %
EPS = 1e-4
VALUES_PER_BIN = 5
OK, WARN, ERROR = 0, 1, 2
LEVEL_NAMES = ("OK", "WARN", "ERROR")
#: what an out-of-domain frame (drift at the ERROR level) gets
ACTIONS = ("flag", "passthrough")
#: what a drifted quantity most likely means (quantity name -> hint), for the log line
HINTS = {"intensity": "intensity scale?", "reflectance": "intensity scale?",
         "score": "another detector?", "points": "another sensor or cropping?",
         "range": "another sensor or scene?", "class": "another detector or scene?"}


@dataclass(frozen=True)
class QuantityProfile:
    """Quantiles at ``LEVELS`` of a quantity's finite training values, their count, the
    fraction of values that were missing (NaN) and ``spread``: the largest PSI of one
    training sequence against the whole (how far one scene's values already are from the
    mix of all; 0 without sequences)."""

    quantiles: tuple
    count: int
    missing: float = 0.0
    spread: float = 0.0

    @classmethod
    def of(cls, values, groups=None, *, min_values: int = 30) -> "QuantityProfile":
        """The profile of ``values``; ``groups`` (one label per value, e.g. the sequence)
        give the ``spread`` over the groups with at least ``min_values`` values."""
        v = np.asarray(values, np.float64).reshape(-1)
        finite = v[np.isfinite(v)]
        missing = 1.0 - len(finite) / len(v) if len(v) else 0.0
        q = np.quantile(finite, LEVELS) if len(finite) else np.full(len(LEVELS), np.nan)
        prof = cls(tuple(float(x) for x in q), int(len(finite)), float(missing))
        if groups is None or not len(finite):
            return prof
        g = np.asarray(groups).reshape(-1)
        if len(g) != len(v):
            raise ValueError(f"{len(g)} group labels for {len(v)} values")
        spread = [psi(prof, v[g == k]) for k in np.unique(g) if (g == k).sum() >= min_values]
        spread = [x for x in spread if np.isfinite(x)]
        return cls(prof.quantiles, prof.count, prof.missing,
                   float(max(spread)) if spread else 0.0)

    @property
    def median(self) -> float:
        return self.quantiles[len(LEVELS) // 2]

    def to_json(self) -> dict:
        return {"quantiles": list(self.quantiles), "count": self.count,
                "missing": self.missing, "spread": self.spread}

    @classmethod
    def from_json(cls, d: Mapping) -> "QuantityProfile":
        q = tuple(float(x) if x is not None else math.nan for x in d["quantiles"])
        if len(q) != len(LEVELS):
            raise ValueError(f"a profile has {len(LEVELS)} quantiles, got {len(q)}")
        return cls(q, int(d["count"]), float(d.get("missing", 0.0)),
                   float(d.get("spread") or 0.0))


@dataclass(frozen=True)
class DomainProfile:
    """Quantity name -> :class:`QuantityProfile` (module docstring)."""

    quantities: dict = field(default_factory=dict)

    @classmethod
    def of(cls, columns: Mapping[str, Iterable],
           groups: Mapping[str, Iterable] | None = None) -> "DomainProfile":
        """The profile of ``{name: training values}``; ``groups``: ``{name: a sequence
        label per value}`` for the quantities whose ``spread`` is to be measured."""
        groups = groups or {}
        return cls({name: QuantityProfile.of(v, groups.get(name))
                    for name, v in columns.items()})

    def to_json(self) -> dict:
        return {"version": 1, "levels": list(LEVELS),
                "quantities": {k: q.to_json() for k, q in self.quantities.items()}}

    @classmethod
    def from_json(cls, d: Mapping) -> "DomainProfile":
        if d.get("version") != 1:
            raise ValueError(f"unknown domain profile version {d.get('version')!r}")
        return cls({k: QuantityProfile.from_json(q) for k, q in d["quantities"].items()})


N_FINE = len(LEVELS) - 1      # the profile's bins: 5 % of the training values each


def fine_counts(profile: QuantityProfile, values) -> np.ndarray:
    """(``N_FINE`` + 1,) counts of ``values`` in the profile's quantile bins (``x`` in bin
    ``j`` when ``q[j] <= x < q[j+1]``, ties staying in the bin that starts at them), then
    the missing (NaN) values."""
    v = np.asarray(values, np.float64).reshape(-1)
    finite = v[np.isfinite(v)]
    edges = np.asarray(profile.quantiles[1:-1])
    c = np.bincount(np.searchsorted(edges, finite, side="right"), minlength=N_FINE)
    return np.r_[c, len(v) - len(finite)].astype(np.float64)


def _fine_mass(profile: QuantityProfile) -> np.ndarray:
    """The training mass of each bin of :func:`fine_counts` (a tie's point mass in the bin
    that starts at it: P(X < u) is the first level whose quantile reaches u)."""
    q = np.asarray(profile.quantiles)
    below = np.asarray(LEVELS)[np.searchsorted(q, q[1:-1], side="left")]
    mass = np.diff(np.r_[0.0, below, 1.0]) * (1.0 - profile.missing)
    return np.r_[mass, profile.missing]


def psi_counts(profile: QuantityProfile, counts, mass=None) -> float:
    """:func:`psi` of values given by their :func:`fine_counts` (summed over frames):
    about ``VALUES_PER_BIN`` values a bin, adjacent bins merged."""
    counts = np.asarray(counts, np.float64)
    n = float(counts.sum())
    if n <= 0 or profile.count == 0:
        return math.nan
    mass = _fine_mass(profile) if mass is None else mass
    n_bins = int(np.clip(n // VALUES_PER_BIN, 2, N_FINE))
    starts = np.round(np.linspace(0, N_FINE, n_bins + 1)).astype(int)[:-1]
    c = np.r_[np.add.reduceat(counts[:N_FINE], starts), counts[N_FINE]]
    q = np.r_[np.add.reduceat(mass[:N_FINE], starts), mass[N_FINE]]
    used = (c > 0) | (q > 0)
    c, q = c[used], np.maximum(q[used], EPS)
    # half a value added to every bin (Jeffreys): an empty bin of a small sample is not
    # read as a vanished part of the distribution
    p = (c + 0.5) / (n + 0.5 * len(c))
    raw = float(np.sum((p - q) * np.log(p / q)))
    expected = (len(p) - 1) * (1.0 / n + 1.0 / max(profile.count, 1))
    return max(raw - expected, 0.0)


def psi(profile: QuantityProfile, values) -> float:
    """Bias-corrected population stability index of ``values`` against ``profile``
    (module docstring); NaN when either side has no value."""
    return psi_counts(profile, fine_counts(profile, values))


@njit("void(float64[:, ::1], int64[::1], float64[:, ::1], boolean[::1], float64[:, ::1])",
      cache=True, nogil=True)
def _add_counts(V, rows, edges, sorted_edges, out):
    """Add :func:`fine_counts` of each column ``j`` of ``V`` (n, k) to ``out[rows[j]]``
    against ``edges[rows[j]]`` (one compiled pass: a value's bin is the number of edges at
    or below it; a non-finite value is missing). ``sorted_edges[r]``: the edges of row
    ``r`` are finite and ascending, so that all of them can be compared without a branch
    (half the time of stopping at the first edge above the value, whose exit the CPU
    mispredicts); otherwise the bin is where the first edge above the value is."""
    n, k = V.shape
    n_edges = edges.shape[1]
    for i in range(n):  # V's row order: one contiguous pass
        for j in range(k):
            r = rows[j]
            v = V[i, j]
            if not np.isfinite(v):
                out[r, n_edges + 1] += 1.0
                continue
            b = 0
            if sorted_edges[r]:
                for m in range(n_edges):
                    b += edges[r, m] <= v
            else:
                while b < n_edges and edges[r, b] <= v:
                    b += 1
            out[r, b] += 1.0


@njit("Tuple((int64[::1], int64))(float64[::1], int64)", cache=True, nogil=True)
def _ranked(scores, k):
    """``(the first k of the finite scores' ranking, how many are finite)``: highest
    first, equal scores in index order (numpy's stable argsort of -scores; a numpy chain
    of ~12 calls a frame before)."""
    n = scores.shape[0]
    taken = np.zeros(n, np.bool_)
    finite = 0
    for i in range(n):
        finite += np.isfinite(scores[i])
    out = np.empty(min(k, finite), np.int64)
    for r in range(out.shape[0]):
        best = -1
        for i in range(n):
            if not taken[i] and np.isfinite(scores[i]) and (best < 0 or scores[i] > scores[best]):
                best = i
        taken[best] = True
        out[r] = best
    return out, finite


@njit("void(float64[:, ::1], float64[:, ::1], float64[::1], float64[::1], boolean[::1], "
      "float64, float64[::1])", cache=True, nogil=True)
def _window_scores(total, mass, train_n, spread, empty, min_values, out):
    """Per quantity (row) with at least ``min_values`` values in the window: the
    :func:`psi_counts` of its ``total`` counts minus its ``spread`` (beyond what one
    training sequence already differs from the mix of all); the rest stays NaN. One
    compiled pass (:func:`psi_counts`' arithmetic; sums in bin order)."""
    c = np.empty(N_FINE + 1)
    q = np.empty(N_FINE + 1)
    for r in range(total.shape[0]):
        n = 0.0
        for j in range(N_FINE + 1):
            n += total[r, j]
        if n < min_values or empty[r]:
            continue
        n_bins = int(min(max(n // VALUES_PER_BIN, 2.0), float(N_FINE)))
        step = N_FINE / n_bins
        lo = 0
        for b in range(n_bins):  # bins of np.round(np.linspace(0, N_FINE, n_bins + 1))
            if b + 1 < n_bins:
                x = (b + 1) * step
                f = np.floor(x)
                d = x - f
                hi = int(f + 1.0 if d > 0.5 or (d == 0.5 and f % 2.0 == 1.0) else f)
            else:
                hi = N_FINE
            cs, qs = 0.0, 0.0
            for j in range(lo, hi):
                cs += total[r, j]
                qs += mass[r, j]
            c[b], q[b] = cs, qs
            lo = hi
        c[n_bins], q[n_bins] = total[r, N_FINE], mass[r, N_FINE]
        n_used = 0
        for b in range(n_bins + 1):
            if c[b] > 0 or q[b] > 0:
                n_used += 1
        raw = 0.0
        for b in range(n_bins + 1):
            if c[b] > 0 or q[b] > 0:
                qb = max(q[b], EPS)
                pb = (c[b] + 0.5) / (n + 0.5 * n_used)
                raw += (pb - qb) * np.log(pb / qb)
        expected = (n_used - 1) * (1.0 / n + 1.0 / max(train_n[r], 1.0))
        out[r] = max(raw - expected, 0.0) - spread[r]


@njit("Tuple((int64[::1], int64))(float64[:, ::1], float64[:, ::1], float64[:, ::1], "
      "float64[:, ::1], float64[::1], float64[::1], boolean[::1], float64, boolean, "
      "float64[::1], int64)", cache=True, nogil=True)
def _window_update(total, counts, old, mass, train_n, spread, empty, min_values, score, out,
                   k):
    """A frame's step of the window in one compiled call: its ``counts`` added to
    ``total``, the leaving frame's ``old`` counts (if any rows) taken off, ``out`` the
    :func:`_window_scores` (all NaN unless ``score``) and :func:`_ranked`'s first ``k``.
    Counts are whole numbers: the sums are exact in any order."""
    rows, cols = total.shape
    for r in range(rows):
        for j in range(cols):
            total[r, j] += counts[r, j]
    if old.shape[0]:
        for r in range(rows):
            for j in range(cols):
                total[r, j] -= old[r, j]
    out[:] = np.nan
    if score:
        _window_scores(total, mass, train_n, spread, empty, min_values, out)
    return _ranked(out, k)


def explain(name: str, profile: QuantityProfile, values) -> str:
    """The drift of one quantity in words: live against training median, and a hint."""
    v = np.asarray(values, np.float64).reshape(-1)
    finite = v[np.isfinite(v)]
    parts = [name]
    if len(finite) and np.isfinite(profile.median):
        live, train = float(np.median(finite)), profile.median
        parts.append(f"median {live:.3g}, training median {train:.3g}")
        q = profile.quantiles
        iqr = q[15] - q[5]          # 75 % and 25 %
        # a ratio only for a median clear of 0 (one near 0 makes any ratio huge)
        if (train != 0 and live / train > 0 and abs(train) >= 0.25 * iqr
                and abs(math.log(live / train)) >= math.log(3)):
            parts.append(f"({live / train:.3g}x)")
    miss = 1.0 - len(finite) / len(v) if len(v) else 0.0
    if abs(miss - profile.missing) > 0.1:
        parts.append(f"missing {100 * miss:.0f} % (training {100 * profile.missing:.0f} %)")
    hint = next((h for key, h in HINTS.items() if key in name.lower()), None)
    text = " ".join(parts)
    return f"{text}: {hint}" if hint else text


_NO_COUNTS = np.zeros((0, N_FINE + 1))  # no frame leaves the window (_window_update)


class _GroupValues:
    """One frame's values as the matrices they came in (``[(names, X), ...]``), read by
    quantity with ``get`` like a dict (only :func:`explain` reads them, for the drifted
    quantities)."""

    __slots__ = ("_groups", "_where")

    def __init__(self, groups, where: dict):
        self._groups = groups
        self._where = where  # name -> (group, column): the same for frames of one layout

    @staticmethod
    def where(groups) -> dict:
        return {n: (g, j) for g, (names, _) in enumerate(groups) for j, n in enumerate(names)}

    def get(self, k):
        """Quantity ``k``'s values (a view of its column), or None, as ``dict.get``."""
        at = self._where.get(k)
        return None if at is None else self._groups[at[0]][1][:, at[1]]


@dataclass
class DriftReport:
    """The monitor's state after a frame: window score, level, the most drifted
    quantities (name, PSI) largest first, their description in words, the frames in the
    window and how many quantities had enough values there to be scored."""

    score: float
    level: int
    drifted: list
    text: str
    frames: int
    scored: int = 0


class DriftMonitor:
    """Rolling drift of live frames against a profile (module docstring). ``add(values)``
    takes one frame's ``{quantity: values}`` (per-row values or one per-frame value; or
    the same as matrices, see :meth:`add`) and returns the :class:`DriftReport` over the
    last ``window`` frames."""

    def __init__(self, profile: DomainProfile, *, window: int = 50, warn: float = 0.25,
                 error: float = 0.5, top: int = 3, min_values: int = 30,
                 min_frames: int = 10):
        if window < 1:
            raise ValueError("window must be at least 1 frame")
        if not 0 <= warn <= error:
            raise ValueError(f"need 0 <= warn <= error, got {warn}, {error}")
        self.profile, self.window, self.warn, self.error, self.top = (
            profile, window, warn, error, top)
        self.min_values = min_values
        #: frames before any score: a frame or two of one scene tell little
        self.min_frames = min(min_frames, window)
        self._names = list(profile.quantities)
        qs = [profile.quantities[k] for k in self._names]
        self._index = {k: i for i, k in enumerate(self._names)}
        self._edges = np.array([q.quantiles[1:-1] for q in qs]).reshape(-1, N_FINE - 1)
        self._sorted_edges = (np.isfinite(self._edges).all(axis=1)
                              & (np.diff(self._edges, axis=1) >= 0).all(axis=1))
        self._mass = np.array([_fine_mass(q) for q in qs]).reshape(-1, N_FINE + 1)
        self._train_n = np.array([q.count for q in qs], np.float64)
        self._spread = np.array([q.spread for q in qs], np.float64)
        self._empty = self._train_n == 0
        # per frame: the quantities' bin counts (scoring, summed as frames come and go)
        # and their values (only to put the drifted ones in words)
        self._counts: deque = deque()
        self._values: deque = deque()
        self._total = np.zeros((len(self._names), N_FINE + 1))
        self._layouts: dict = {}  # the column layouts of the frames' values (_GroupValues)

    def add(self, values, *, explain: bool = True) -> DriftReport:
        """``values``: ``{quantity: values}``, ``(names, X)`` for the columns of one
        (rows, quantities) matrix (lms_node's 114 metrics of ~2000 segments: not split
        into columns and stacked again), or a list of such ``(names, X)`` (LMD: the
        boxes' features and scores, and the frame's point count). ``explain`` False:
        the report's ``text`` is left empty (:meth:`words` gives it on demand)."""
        counts = np.zeros_like(self._total)
        if isinstance(values, tuple):
            values = [values]
        if isinstance(values, Mapping):
            frame = {k: np.asarray(v, np.float64).reshape(-1) for k, v in values.items()
                     if k in self._index}
            by_len: dict[int, list[str]] = {}
            for k, v in frame.items():
                by_len.setdefault(len(v), []).append(k)
            # quantities of a frame's rows: one matrix
            groups = [(names, np.stack([frame[k] for k in names], axis=1) if n
                       else np.zeros((0, len(names)))) for n, names in by_len.items()]
            for names, V in groups:
                _add_counts(np.require(V, np.float64, "CW"), self._rows(names),
                            self._edges, self._sorted_edges, counts)
        else:
            # a node's frames share their layout: which columns are profiled, their rows
            # in the profile and the name -> column map are worked out once per layout
            layout = tuple(tuple(names) for names, _ in values)
            known = self._layouts.get(layout)
            if known is None:
                if len(self._layouts) > 8:
                    self._layouts.clear()
                known = self._layouts[layout] = self._layout(layout)
            selections, where = known
            groups = []
            for (names, X), (kept, cols, _) in zip(values, selections):
                X = np.asarray(X, np.float64).reshape(-1, len(names))
                groups.append((kept, X if cols is None else X[:, cols]))
            frame = _GroupValues(groups, where)
            for (_, V), (_, _, rows) in zip(groups, selections):
                _add_counts(np.require(V, np.float64, "CW"), rows, self._edges,
                            self._sorted_edges, counts)
        self._counts.append(counts)
        self._values.append(frame)
        old = _NO_COUNTS
        if len(self._counts) > self.window:
            old = self._counts.popleft()
            self._values.popleft()
        scores = np.empty(len(self._names))
        # only the first few of the ranking are reported (top)
        first, n_scored = _window_update(
            self._total, counts, old, self._mass, self._train_n, self._spread, self._empty,
            float(self.min_values), len(self._counts) >= self.min_frames, scores,
            max(self.top, 1))
        ranked = [(self._names[i], float(scores[i])) for i in first.tolist()]
        score = ranked[0][1] if ranked else 0.0
        level = ERROR if score >= self.error else WARN if score >= self.warn else OK
        drifted = [(k, round(v, 4)) for k, v in ranked[:self.top] if v >= self.warn]
        text = self.words(drifted) if explain else ""
        return DriftReport(float(score), level, drifted, text, len(self._counts), n_scored)

    def _layout(self, layout) -> tuple[list, dict]:
        """Per ``(names, X)`` group of a layout: ``(the profiled names, their columns or
        None for all, their rows in the profile)``, and the name -> column map."""
        selections = []
        for names in layout:
            cols = [j for j, k in enumerate(names) if k in self._index]
            kept = tuple(names[j] for j in cols)
            selections.append((kept, None if len(cols) == len(names) else np.array(cols),
                               self._rows(kept)))
        return selections, _GroupValues.where([(kept, None) for kept, _, _ in selections])

    def _rows(self, names) -> np.ndarray:
        """The profile's rows of the profiled quantities ``names``."""
        return np.array([self._index[k] for k in names], np.int64)

    def words(self, drifted) -> str:
        """The ``drifted`` quantities (``(name, PSI)`` pairs) in words over the current
        window (:func:`explain`: their live medians against training)."""
        # one get a frame, the frames' dicts and _GroupValues alike
        return "; ".join(explain(k, self.profile.quantities[k], np.concatenate(
            [v for f in self._values if (v := f.get(k)) is not None])) for k, _ in drifted)


# ------------------------------------------------------------------ in the nodes
@dataclass(frozen=True)
class DriftParameters:
    """The drift monitor's parameters, common to lmd_node, lms_node and mimo_node (a
    ``parameters.group`` of each node's parameters)."""

    drift_window: int = param(
        50, "Frames in the rolling window the drift score is computed over (the meta "
        "models' training-data profile against the live features and inputs).", min_value=1)
    drift_warn: float = param(
        0.25, "Drift score (bias-corrected PSI of the most drifted quantity) from which "
        "/diagnostics reports WARN and a throttled warning names the quantities.",
        min_value=0.0)
    drift_error: float = param(
        0.5, "Drift score from which /diagnostics reports ERROR: the frame is out of the "
        "models' domain (drift_action).", min_value=0.0)
    drift_action: str = param(
        "flag", "What an out-of-domain frame gets: flag (annotated as always, flagged in "
        "/diagnostics and the quality message's drift_level) or passthrough (the detector's "
        "own score as the confidence and NaN predicted IoU; LMS, without a detector score: "
        "NaN for both; the quality message says passthrough: true).", choices=ACTIONS)

    def validate(self) -> None:
        if self.drift_error < self.drift_warn:
            raise ValueError(f"drift_error = {self.drift_error} is below drift_warn = "
                             f"{self.drift_warn}")


#: a verdict's ``state`` -> the quality messages' drift_level constant (lidar_quality_msgs)
STATE_CONSTANTS = {"off": "DRIFT_OFF", "warming up": "DRIFT_WARMING_UP", "OK": "DRIFT_OK",
                   "WARN": "DRIFT_WARN", "ERROR": "DRIFT_ERROR"}


@dataclass
class DomainVerdict:
    """One frame's drift for a processor's outputs: diagnostics ``values``, the warning
    text (``issue``, None when quiet), ``error`` (level ERROR) and ``passthrough`` (the
    frame's confidences are to be replaced, ``drift_action``); for the quality messages
    ``state`` (``STATE_CONSTANTS``: ``"off"`` without a profile, ``"warming up"`` before
    the window gives a score, else the level's name), the window's ``score`` (NaN unless
    scored), its ``frames`` and the most drifted ``quantities``."""

    values: dict
    issue: str | None = None
    error: bool = False
    passthrough: bool = False
    state: str = "off"
    score: float = math.nan
    frames: int = 0
    quantities: tuple = ()

    def message_fields(self, message_class) -> dict:
        """The version and drift fields of a ``lidar_quality_msgs`` quality array
        (``message_class``: DetectionQualityArray, SegmentQualityArray or
        ClusterUncertaintyArray, whose constants give the level), as keyword arguments.
        The score is rounded to float32 here, as the message carries it: the message
        equals itself after a round trip through its bytes."""
        return {"version": message_class.MESSAGE_VERSION,
                "drift_level": getattr(message_class, STATE_CONSTANTS[self.state]),
                "drift_score": float(np.float32(self.score)),
                "drift_window_frames": int(self.frames),
                "drift_quantities": ", ".join(self.quantities),
                "passthrough": bool(self.passthrough)}


class DomainCheck:
    """A processor's drift monitor over its models' profile (None: the models record no
    profile, and each frame says so in its values).

    The warning's words (the drifted quantities' live medians over the window, the most
    expensive part of a drifted frame's check: medians of up to 50 frames' values) are
    rebuilt when the level or the drifted quantities change, and otherwise every
    ``WORDS_EVERY`` frames; score, level and quantities are every frame's. A node shows
    the words at most once per /diagnostics period and logs them at most once per warning
    period, so an out-of-domain stream no longer pays the medians on every frame."""

    #: frames between two rebuilds of unchanged warning words (1 s at 10 Hz)
    WORDS_EVERY = 10

    def __init__(self, profile: DomainProfile | None, params: DriftParameters | None = None):
        p = params or DriftParameters()
        p.validate()
        self.action = p.drift_action
        self._profile, self._params = profile, p
        self.reset()

    def reset(self) -> None:
        """Forget the window: a new input stream (the next bag of a batch) starts afresh."""
        p = self._params
        self.monitor = None if self._profile is None else DriftMonitor(
            self._profile, window=p.drift_window, warn=p.drift_warn, error=p.drift_error)
        self._words, self._words_of, self._words_age = "", None, 0

    def __call__(self, quantities) -> DomainVerdict:
        if self.monitor is None:
            return DomainVerdict({"drift": "off: the models record no training-data profile "
                                           "(trained before profiles; retrain to monitor)"})
        r = self.monitor.add(quantities, explain=False)
        if r.level >= WARN:
            of = (r.level, tuple(k for k, _ in r.drifted))
            self._words_age += 1
            if of != self._words_of or self._words_age >= self.WORDS_EVERY:
                self._words, self._words_of, self._words_age = (
                    self.monitor.words(r.drifted), of, 0)
            r.text = self._words
        else:
            self._words_of = None
        scored = r.scored > 0       # else: too few frames, or too few values of each quantity
        # as the quality messages say it: no score (not a 0) while the window fills
        values = {"drift.level": LEVEL_NAMES[r.level] if scored else "warming up",
                  "drift.window_frames": r.frames, "drift.scored_quantities": r.scored}
        if scored:
            values["drift.score"] = round(r.score, 3)
        if r.drifted:
            values["drift.quantities"] = ", ".join(k for k, _ in r.drifted)
        issue = None
        if r.level >= WARN:
            issue = (f"inputs unlike the models' training data (drift {r.score:.2f} over "
                     f"{r.frames} frames): {r.text}")
        return DomainVerdict(values, issue, r.level == ERROR,
                             r.level == ERROR and self.action == "passthrough",
                             LEVEL_NAMES[r.level] if scored else "warming up",
                             r.score if scored else math.nan, r.frames,
                             tuple(k for k, _ in r.drifted))
