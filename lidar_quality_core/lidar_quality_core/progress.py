"""A one-line progress bar on stderr for the long offline steps (datasets, CV, training)."""
from __future__ import annotations

import sys
import time

__all__ = ["Progress"]


class Progress:
    """``Progress(label, total)``: ``update(n)`` counts on, ``bar(done, total)`` sets the
    count (the ``progress(done, total)`` callback of ``meta_model``), ``close()`` ends the
    line. ``enabled=False``: silent. The line ends by itself when ``done`` reaches ``total``."""

    def __init__(self, label: str, total: int | None = None, enabled: bool = True):
        self.label, self.total, self.enabled = label, total, enabled
        self.done, self.t0, self._open = 0, time.monotonic(), False

    def update(self, n: int = 1, note: str = "") -> None:
        self(self.done + n, None, note)

    def __call__(self, done: int, total: int | None = None, note: str = "") -> None:
        self.done = int(done)
        if total is not None:
            self.total = int(total)
        if not self.enabled:
            return
        rate = self.done / max(time.monotonic() - self.t0, 1e-9)
        if self.total:
            fill = int(30 * min(self.done / self.total, 1.0))
            bar = f"[{'#' * fill}{'.' * (30 - fill)}] {self.done}/{self.total}"
        else:
            bar = f"{self.done}"
        sys.stderr.write(f"\r{self.label} {bar} ({rate:.1f}/s) {note}"[:160])
        self._open = True
        if self.total and self.done >= self.total:
            self.close()
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled and self._open:
            sys.stderr.write("\n")
            sys.stderr.flush()
        self._open = False
