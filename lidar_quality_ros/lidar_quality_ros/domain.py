"""Run-specific ROS domain ids, leased with file locks so that concurrent test runs and
tests never share a domain (DDS traffic of ours also stays on loopback: see env.sh).

``scripts/env.sh`` under our scripts (``LQ_ISOLATED=1``) takes its shell-wide domain from the
same lock files, in the same order, with ``flock``: a test never leases the domain of the
run around it, nor of another run."""
from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path

#: Domains 1..101 keep Fast DDS's ports below Linux's ephemeral range; 0 is left to
#: whatever stack runs with the default domain.
DOMAIN_RANGE = range(1, 102)
LOCK_DIR = Path(os.environ.get("LQ_DOMAIN_LOCK_DIR", Path(tempfile.gettempdir()) / "lidar_quality_domains"))


class DomainLease:
    """An exclusive lease of one ROS domain id, held until ``release()`` (or process exit)."""

    def __init__(self, domain_id: int, fd: int):
        self.domain_id = domain_id
        self._fd = fd

    @classmethod
    def acquire(cls, start: int | None = None) -> "DomainLease":
        LOCK_DIR.mkdir(parents=True, exist_ok=True)
        ids = list(DOMAIN_RANGE)
        k = (os.getpid() if start is None else start) % len(ids)
        for domain_id in ids[k:] + ids[:k]:
            try:
                # Read-only is enough for flock and works on a lock file another user made.
                fd = os.open(LOCK_DIR / f"{domain_id}.lock", os.O_CREAT | os.O_RDONLY, 0o666)
            except OSError:
                continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                os.close(fd)
                continue
            return cls(domain_id, fd)
        raise RuntimeError(f"no free ROS domain id in {DOMAIN_RANGE} (locks in {LOCK_DIR})")

    def release(self) -> None:
        if self._fd >= 0:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = -1

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.release()
