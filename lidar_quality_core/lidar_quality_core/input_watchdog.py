"""Why a stamp-synchronised node publishes nothing: a missing input, or stamps that never
match.

A node with several inputs (cloud + detections + proposals, K heads, ...) publishes a
frame only when every input delivered a message of that stamp. When one input is never
published (a remap forgotten), or its stamps sit a few milliseconds from the others',
nothing comes out and no frame is "dropped". :class:`InputWatchdog` sees arrivals and
matches and, once no set matched for ``timeout_s`` while messages arrive, says which:

* some inputs received nothing in that time: they are *missing*;
* every input arrives but nothing matches: the *nearest stamp offset* between the
  inputs (recent stamps), to compare with the synchroniser's tolerance.

No input at all is *idle* (not an error: nothing to do). A verdict needs two arrivals
since the last matched set (on some input for *missing*, on every input for *no match*):
one late message, or a process that was paused, is not a pattern. Pure Python; the node calls
:meth:`check` from a timer and turns the verdict into a log line and a diagnostics level.
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field

OK, WARN, ERROR = 0, 1, 2


@dataclass
class Verdict:
    """``level`` (OK / WARN / ERROR), ``cause`` (``"ok"``, ``"idle"``, ``"missing"``,
    ``"no_match"``), ``silent_s`` (seconds without a matched set while inputs arrive),
    ``missing`` (input indices that received nothing for ``timeout_s``), ``offset_ns``
    (no_match: for each input, the smallest stamp distance of its recent messages to
    input 0's; input 0 itself 0)."""

    level: int = OK
    cause: str = "ok"
    silent_s: float = 0.0
    missing: list[int] = field(default_factory=list)
    offset_ns: list[int] = field(default_factory=list)


class InputWatchdog:
    """Arrivals and matches of ``n_inputs`` synchronised inputs (thread-safe).

    WARN once ``timeout_s`` pass without a matched set while some input arrives, ERROR
    after ``error_s``. Time is the caller's monotonic clock (seconds), so the verdict does
    not depend on message stamps (a bag's, a simulator's)."""

    def __init__(self, n_inputs: int, timeout_s: float = 2.0, error_s: float = 10.0,
                 history: int = 20, start_s: float = 0.0):
        if n_inputs < 1 or not 0 < timeout_s <= error_s:
            raise ValueError(f"need n_inputs >= 1 and 0 < timeout_s <= error_s, got "
                             f"{n_inputs}, {timeout_s}, {error_s}")
        self.n, self.timeout_s, self.error_s = int(n_inputs), float(timeout_s), float(error_s)
        self._lock = threading.Lock()
        self._last_arrival: list[float | None] = [None] * self.n
        self._stamps = [deque(maxlen=history) for _ in range(self.n)]
        self._since_match = [0] * self.n   # arrivals per input since the last matched set
        self._last_match = start_s

    def arrival(self, index: int, stamp_ns: int, now_s: float) -> None:
        with self._lock:
            self._last_arrival[index] = now_s
            self._stamps[index].append(int(stamp_ns))
            self._since_match[index] += 1

    def matched(self, now_s: float) -> None:
        with self._lock:
            self._last_match = now_s
            self._since_match = [0] * self.n

    def check(self, now_s: float) -> Verdict:
        with self._lock:
            last = list(self._last_arrival)
            stamps = [list(d) for d in self._stamps]
            since = self._last_match
            counts = list(self._since_match)
        recent = [t is not None and now_s - t < self.timeout_s for t in last]
        silent = now_s - since
        if silent < self.timeout_s:
            return Verdict()
        if not any(recent):
            return Verdict(cause="idle", silent_s=silent)
        level = ERROR if silent >= self.error_s else WARN
        missing = [i for i in range(self.n) if not recent[i]]
        # evidence, not a moment: a set completes only after every input's message is in,
        # and a paused process sees its clock jump; two unmatched arrivals are a pattern
        if missing:
            if max(counts) < 2:
                return Verdict()
            return Verdict(level, "missing", silent, missing)
        if min(counts) < 2:
            return Verdict()
        return Verdict(level, "no_match", silent, [], nearest_offsets(stamps))


def nearest_offsets(stamps: list[list[int]]) -> list[int]:
    """For each input, the smallest |stamp - stamp of input 0| over the recent stamps."""
    ref = stamps[0]
    return [0] + [min((abs(a - b) for a in s for b in ref), default=0) for s in stamps[1:]]
