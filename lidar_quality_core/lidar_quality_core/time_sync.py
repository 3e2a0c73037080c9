"""Synchronise N message streams by header stamp (replacement for ``message_filters``).

Pure Python / numpy: the ROS node converts ``builtin_interfaces/Time`` with
:func:`stamp_to_ns` and feeds :meth:`StampSynchronizer.add` from its subscriptions.

Matching rule (both modes share it; ``exact`` is ``approximate`` with ``slop_ns=0``):

* Every arriving message is the *pivot*. Among the sets made of the pivot plus one queued
  message from each other input, the one with the smallest spread (newest - oldest
  stamp) is chosen; ties go to the set whose oldest stamp is smallest, then to the
  earliest-arrived message among equal stamps. The set is emitted at once if its spread
  is ``<= slop_ns``. Emission is eager (lowest latency): a message arriving later could
  have formed a tighter set, but sets are never held back waiting for one.
* Because every arrival is tried immediately, no emittable set ever waits in the
  queues, so one ``add`` emits at most one set (a loop restart, below, may emit more).
* After an emission each queue discards its emitted message and everything at or
  older than it on that queue (the older ones count as ``dropped_unmatched``). Newer
  messages stay, so per input the emitted stamps are strictly increasing.
* A message whose stamp is at or before the last stamp emitted *from its own input* can
  never be part of a later set: it is counted ``late`` and not queued. In exact mode
  that stamp equals the set's reference stamp.
* A message older than the last emitted reference stamp by more than
  ``reset_on_backwards_ns`` (a bag replayed in a loop, a sim clock reset) clears all
  queues (``resets`` += 1, cleared messages counted ``dropped_reset``) and is then
  accepted normally. A shorter jump back is a loop too once *every* input has sent a
  message older than its last emitted one since the last emission (a bag shorter than
  ``reset_on_backwards_ns`` replayed in a loop): the queues are cleared the same way and
  those messages (first counted ``late``) are queued again, so the looped frames match
  instead of all counting late. A straggler on some inputs only stays ``late``.
* Queues hold at most ``queue_size`` messages after ``add`` returns; overflow drops the
  earliest *arrived* message (``dropped_overflow``). Arrival order rather than stamp
  order so that stale stamps from before an unnoticed clock jump cannot pin the queue.

Conservation, per input ``i`` (checked by the tests)::

    received[i] == matched + dropped_overflow[i] + dropped_unmatched[i]
                   + dropped_reset[i] + late[i] + queued[i]

Threading: an internal ``threading.Lock`` guards only the bookkeeping inside ``add``;
user code is never called under it. ``add`` returns the emitted sets and the caller
runs its callback afterwards (or uses :meth:`StampSynchronizer.add_and_dispatch`).
With several threads, callbacks of different sets may run concurrently or out of order:
``SyncedSet.seq`` is the emission order if the consumer needs it.
"""
from __future__ import annotations

import bisect
import operator
import struct
import threading
from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

__all__ = [
    "NS_PER_SEC",
    "stamp_to_ns",
    "ns_to_stamp",
    "stamp_of_bytes",
    "SyncedSet",
    "SyncStats",
    "StampSynchronizer",
]

NS_PER_SEC = 1_000_000_000


def stamp_to_ns(sec: int, nanosec: int) -> int:
    """Integer nanoseconds of a ``(sec, nanosec)`` stamp; ``0 <= nanosec < 1e9``."""
    sec = operator.index(sec)
    nanosec = operator.index(nanosec)
    if not 0 <= nanosec < NS_PER_SEC:
        raise ValueError(f"nanosec must be in [0, 1e9), got {nanosec}")
    return sec * NS_PER_SEC + nanosec


def ns_to_stamp(stamp_ns: int) -> tuple[int, int]:
    """Inverse of :func:`stamp_to_ns`: ``(sec, nanosec)`` with ``0 <= nanosec < 1e9``."""
    return divmod(operator.index(stamp_ns), NS_PER_SEC)


#: A serialized ROS message starts with the CDR encapsulation (4 bytes); a leading
#: std_msgs/Header then puts stamp.sec (int32) and stamp.nanosec (uint32) at bytes 4..12.
HEADER_STAMP = struct.Struct("<iI")


def stamp_of_bytes(data) -> int:
    """Header stamp [ns] of the little-endian CDR bytes of a message with a leading
    header, read without deserializing it; ``ValueError`` for other bytes."""
    if len(data) < 12 or bytes(data[:2]) != b"\x00\x01":
        raise ValueError("not little-endian CDR of a message with a header")
    return stamp_to_ns(*HEADER_STAMP.unpack_from(data, 4))


class SyncedSet(NamedTuple):
    """One emitted set: ``messages[i]`` / ``stamps[i]`` belong to input ``i``.

    ``stamp_ns`` is the reference stamp: the newest stamp of the set (all equal in exact
    mode). ``seq`` counts emissions from 0 (reset does not restart it).
    """

    stamp_ns: int
    messages: tuple
    stamps: tuple[int, ...]
    seq: int


@dataclass
class SyncStats:
    """Counters of a synchroniser; lists are per input, ``matched`` counts sets."""

    received: list[int]
    late: list[int]
    dropped_overflow: list[int]
    dropped_unmatched: list[int]
    dropped_reset: list[int]
    queued: list[int]
    matched: int = 0
    resets: int = 0

    @classmethod
    def zeros(cls, n: int) -> SyncStats:
        return cls(*([0] * n for _ in range(6)))

    @property
    def dropped(self) -> list[int]:
        """Messages lost without being part of a set (excluding ``late``), per input."""
        return [
            a + b + c
            for a, b, c in zip(self.dropped_overflow, self.dropped_unmatched, self.dropped_reset)
        ]

    def as_dict(self) -> dict[str, Any]:
        """Plain dict (e.g. for a diagnostics message), including ``dropped``."""
        d = {k: (list(v) if isinstance(v, list) else v) for k, v in self.__dict__.items()}
        d["dropped"] = self.dropped
        return d


@dataclass
class _Queue:
    # Parallel lists kept sorted by stamp; ``arrival`` orders overflow eviction.
    stamps: list[int] = field(default_factory=list)
    arrival: list[int] = field(default_factory=list)
    msgs: list[Any] = field(default_factory=list)

    def insert(self, stamp: int, arrival: int, msg: Any) -> int:
        # bisect_right keeps equal stamps in arrival order, so ties pick the earliest.
        pos = bisect.bisect_right(self.stamps, stamp)
        self.stamps.insert(pos, stamp)
        self.arrival.insert(pos, arrival)
        self.msgs.insert(pos, msg)
        return pos

    def pop(self, pos: int) -> None:
        del self.stamps[pos], self.arrival[pos], self.msgs[pos]

    def drop_through(self, pos: int) -> int:
        """Remove entries ``[0, pos]``; returns how many were removed."""
        del self.stamps[: pos + 1], self.arrival[: pos + 1], self.msgs[: pos + 1]
        return pos + 1

    def clear(self) -> int:
        n = len(self.stamps)
        self.stamps.clear()
        self.arrival.clear()
        self.msgs.clear()
        return n

    def __len__(self) -> int:
        return len(self.stamps)


class StampSynchronizer:
    """Match messages of ``n_inputs`` streams by stamp (see module docstring for rules).

    ``mode="exact"`` requires equal stamps (``slop_ns`` must be 0); ``"approximate"``
    accepts sets with ``max - min <= slop_ns``. ``callback`` is only used by
    :meth:`add_and_dispatch`.
    """

    def __init__(
        self,
        n_inputs: int,
        *,
        mode: str = "exact",
        slop_ns: int = 0,
        queue_size: int = 10,
        reset_on_backwards_ns: int = NS_PER_SEC,
        callback: Callable[[SyncedSet], Any] | None = None,
    ) -> None:
        n_inputs = operator.index(n_inputs)
        slop_ns = operator.index(slop_ns)
        queue_size = operator.index(queue_size)
        reset_on_backwards_ns = operator.index(reset_on_backwards_ns)
        if n_inputs < 1:
            raise ValueError(f"n_inputs must be >= 1, got {n_inputs}")
        if mode not in ("exact", "approximate"):
            raise ValueError(f"mode must be 'exact' or 'approximate', got {mode!r}")
        if slop_ns < 0:
            raise ValueError(f"slop_ns must be >= 0, got {slop_ns}")
        if mode == "exact" and slop_ns != 0:
            raise ValueError("slop_ns must be 0 in exact mode (use mode='approximate')")
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        if reset_on_backwards_ns < 0:
            raise ValueError(f"reset_on_backwards_ns must be >= 0, got {reset_on_backwards_ns}")
        self.n_inputs = n_inputs
        self.mode = mode
        self.slop_ns = slop_ns
        self.queue_size = queue_size
        self.reset_on_backwards_ns = reset_on_backwards_ns
        self.callback = callback
        self._lock = threading.Lock()
        self._queues = [_Queue() for _ in range(n_inputs)]
        self._stats = SyncStats.zeros(n_inputs)
        self._arrivals = 0
        self._seq = 0
        self._last_ref: int | None = None
        self._last_emitted: list[int | None] = [None] * n_inputs
        # newest message per input stamped before its last emitted one, since the last
        # emission: when every input has one, the stream went back in time (a loop)
        self._backward: list[tuple[int, Any] | None] = [None] * n_inputs

    # -- public API ---------------------------------------------------------------

    def add(self, index: int, stamp_ns: int, msg: Any) -> list[SyncedSet]:
        """Queue ``msg`` of input ``index``; return the sets this completes (0 or 1)."""
        index = operator.index(index)
        stamp_ns = operator.index(stamp_ns)
        if not 0 <= index < self.n_inputs:
            raise IndexError(f"input index {index} out of range [0, {self.n_inputs})")
        with self._lock:
            return self._add_locked(index, stamp_ns, msg)

    def add_and_dispatch(
        self,
        index: int,
        stamp_ns: int,
        msg: Any,
        callback: Callable[[SyncedSet], Any] | None = None,
    ) -> list[SyncedSet]:
        """:meth:`add`, then call ``callback`` (or ``self.callback``) on each set, unlocked."""
        cb = callback if callback is not None else self.callback
        if cb is None:
            raise ValueError("no callback given and none set on the synchroniser")
        sets = self.add(index, stamp_ns, msg)
        for s in sets:
            cb(s)
        return sets

    def reset(self) -> None:
        """Clear all queues and the emission history (counts one reset)."""
        with self._lock:
            self._reset_locked()

    def stats(self) -> SyncStats:
        """Consistent snapshot of the counters."""
        with self._lock:
            s = self._stats
            return SyncStats(
                received=list(s.received),
                late=list(s.late),
                dropped_overflow=list(s.dropped_overflow),
                dropped_unmatched=list(s.dropped_unmatched),
                dropped_reset=list(s.dropped_reset),
                queued=[len(q) for q in self._queues],
                matched=s.matched,
                resets=s.resets,
            )

    @property
    def last_stamp_ns(self) -> int | None:
        """Reference stamp of the last emitted set (None before any / after reset)."""
        with self._lock:
            return self._last_ref

    # -- internals (called with the lock held) -------------------------------------

    def _reset_locked(self) -> None:
        for i, q in enumerate(self._queues):
            self._stats.dropped_reset[i] += q.clear()
        self._stats.resets += 1
        self._last_ref = None
        self._last_emitted = [None] * self.n_inputs
        self._backward = [None] * self.n_inputs

    def _add_locked(self, i: int, t: int, msg: Any) -> list[SyncedSet]:
        st = self._stats
        st.received[i] += 1
        if self._last_ref is not None and t < self._last_ref - self.reset_on_backwards_ns:
            self._reset_locked()
        last_i = self._last_emitted[i]
        if last_i is not None and t <= last_i:
            st.late[i] += 1
            if t < last_i:
                self._backward[i] = (t, msg)
                if all(b is not None for b in self._backward):
                    return self._restart_after_loop()
            return []
        return self._accept(i, t, msg)

    def _restart_after_loop(self) -> list[SyncedSet]:
        backward = self._backward
        self._reset_locked()
        out: list[SyncedSet] = []
        for j, (t, msg) in enumerate(backward):
            self._stats.late[j] -= 1
            out += self._accept(j, t, msg)
        return out

    def _accept(self, i: int, t: int, msg: Any) -> list[SyncedSet]:
        st = self._stats
        self._arrivals += 1
        pivot_pos = self._queues[i].insert(t, self._arrivals, msg)
        chosen = self._find_set(i, t, pivot_pos)
        if chosen is None:
            q = self._queues[i]
            if len(q) > self.queue_size:
                q.pop(q.arrival.index(min(q.arrival)))
                st.dropped_overflow[i] += 1
            return []
        return [self._emit(chosen)]

    def _find_set(self, i: int, t: int, pivot_pos: int) -> list[int] | None:
        """Queue positions of the tightest set containing the pivot, or None."""
        n = self.n_inputs
        others = [j for j in range(n) if j != i]
        if any(len(self._queues[j]) == 0 for j in others):
            return None
        if self.slop_ns == 0:
            # equal stamps only: the set below reduces to each other input's first
            # (earliest-arrived) message at t; found by bisection instead of the ~15
            # numpy calls below (a node's set-completing arrival, every frame)
            chosen = [0] * n
            chosen[i] = pivot_pos
            for j in others:
                stamps = self._queues[j].stamps
                pos = bisect.bisect_left(stamps, t)
                if pos == len(stamps) or stamps[pos] != t:
                    return None
                chosen[j] = pos
            return chosen
        arrays = [np.asarray(self._queues[j].stamps, dtype=np.int64) for j in others]
        # The tightest set's oldest stamp is the pivot or a queued stamp in
        # [t - slop, t]; for each such lower bound every other input takes its
        # first stamp >= bound, which cannot widen the window. Where no stamp is
        # >= bound the newest one is taken: still a real set, scored by its real spread.
        lo_bounds = np.unique(
            np.concatenate([[t]] + [a[(a <= t) & (a >= t - self.slop_ns)] for a in arrays])
        )
        hi = np.full(lo_bounds.size, t, dtype=np.int64)
        lo = hi.copy()
        positions = []
        for a in arrays:
            pos = np.minimum(np.searchsorted(a, lo_bounds, side="left"), a.size - 1)
            vals = a[pos]
            np.maximum(hi, vals, out=hi)
            np.minimum(lo, vals, out=lo)
            positions.append(pos)
        spread = hi - lo
        k = int(np.lexsort((lo, spread))[0])
        if spread[k] > self.slop_ns:
            return None
        chosen = [0] * n
        chosen[i] = pivot_pos
        for j, pos in zip(others, positions):
            chosen[j] = int(pos[k])
        return chosen

    def _emit(self, chosen: Sequence[int]) -> SyncedSet:
        st = self._stats
        msgs = []
        stamps = []
        for j, pos in enumerate(chosen):
            q = self._queues[j]
            msgs.append(q.msgs[pos])
            stamps.append(q.stamps[pos])
            # Older messages on this queue can no longer be emitted (stamps per input
            # are emitted in increasing order).
            st.dropped_unmatched[j] += q.drop_through(pos) - 1
            self._last_emitted[j] = stamps[-1]
        ref = max(stamps)
        self._last_ref = ref
        self._backward = [None] * self.n_inputs
        st.matched += 1
        out = SyncedSet(ref, tuple(msgs), tuple(stamps), self._seq)
        self._seq += 1
        return out
