import subprocess
import sys

from lidar_quality_ros.domain import DOMAIN_RANGE, DomainLease


def test_leases_are_exclusive_in_process():
    leases = [DomainLease.acquire(start=0) for _ in range(5)]
    try:
        ids = [le.domain_id for le in leases]
        assert len(set(ids)) == 5 and all(i in DOMAIN_RANGE for i in ids)
        assert 0 not in ids
    finally:
        for le in leases:
            le.release()


def test_lease_excludes_other_processes():
    with DomainLease.acquire(start=7) as lease:
        code = ("from lidar_quality_ros.domain import DomainLease;"
                f"print(DomainLease.acquire(start={lease.domain_id - 1}).domain_id)")
        other = int(subprocess.check_output([sys.executable, "-c", code], text=True))
        assert other != lease.domain_id
    again = DomainLease.acquire(start=lease.domain_id - 1)
    assert again.domain_id == lease.domain_id  # released: free again
    again.release()


def test_unopenable_lock_file_is_skipped(tmp_path, monkeypatch):
    # e.g. a lock file of another user, or a stale link: that domain is passed over
    import lidar_quality_ros.domain as domain
    monkeypatch.setattr(domain, "LOCK_DIR", tmp_path)
    (tmp_path / "5.lock").symlink_to(tmp_path / "missing_dir" / "5.lock")
    with DomainLease.acquire(start=4) as lease:
        assert lease.domain_id == 6
