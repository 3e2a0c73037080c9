"""Tests of lidar_quality_core.time_sync."""
from __future__ import annotations

import itertools
import random
import threading

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lidar_quality_core.time_sync import (
    NS_PER_SEC,
    StampSynchronizer,
    SyncedSet,
    ns_to_stamp,
    stamp_to_ns,
)

S = NS_PER_SEC


def feed(sync, events):
    """Feed ``(index, stamp, msg)`` events; return all emitted sets."""
    out = []
    for i, t, m in events:
        out.extend(sync.add(i, t, m))
    return out


def assert_conserved(sync):
    s = sync.stats()
    for i in range(sync.n_inputs):
        assert s.received[i] == (
            s.matched + s.dropped_overflow[i] + s.dropped_unmatched[i] + s.dropped_reset[i]
            + s.late[i] + s.queued[i]
        ), (i, s)
        assert s.dropped[i] == s.dropped_overflow[i] + s.dropped_unmatched[i] + s.dropped_reset[i]


# -- stamps -------------------------------------------------------------------------


def test_stamp_to_ns_roundtrip():
    assert stamp_to_ns(3, 5) == 3 * S + 5
    assert stamp_to_ns(0, S - 1) == S - 1
    assert ns_to_stamp(stamp_to_ns(1_700_000_000, 123_456_789)) == (1_700_000_000, 123_456_789)
    with pytest.raises(ValueError):
        stamp_to_ns(1, S)
    with pytest.raises(ValueError):
        stamp_to_ns(1, -1)
    with pytest.raises(TypeError):
        stamp_to_ns(1.5, 0)


def test_constructor_validation():
    with pytest.raises(ValueError):
        StampSynchronizer(0)
    with pytest.raises(ValueError):
        StampSynchronizer(2, mode="exact", slop_ns=5)
    with pytest.raises(ValueError):
        StampSynchronizer(2, mode="fuzzy")
    with pytest.raises(ValueError):
        StampSynchronizer(2, queue_size=0)
    sync = StampSynchronizer(2)
    with pytest.raises(IndexError):
        sync.add(2, 0, "x")
    with pytest.raises(TypeError):
        sync.add(0, 1.0, "x")


# -- exact --------------------------------------------------------------------------


@pytest.mark.parametrize("order_seed", range(5))
def test_exact_interleaved_orders(order_seed):
    stamps = [10, 20, 30, 40]
    rng = random.Random(order_seed)
    per_input = [[(i, t, f"{i}@{t}") for t in stamps] for i in range(3)]
    # Random merge that preserves the per-input order.
    events = []
    while any(per_input):
        i = rng.choice([k for k in range(3) if per_input[k]])
        events.append(per_input[i].pop(0))
    sync = StampSynchronizer(3, mode="exact", queue_size=10)
    out = feed(sync, events)
    assert [s.stamp_ns for s in out] == stamps
    for s in out:
        assert s.messages == tuple(f"{i}@{s.stamp_ns}" for i in range(3))
        assert s.stamps == (s.stamp_ns,) * 3
    assert [s.seq for s in out] == list(range(4))
    assert sync.stats().matched == 4
    assert_conserved(sync)


def test_exact_messages_in_input_order_regardless_of_arrival():
    sync = StampSynchronizer(3)
    assert sync.add(2, 5, "c") == []
    assert sync.add(0, 5, "a") == []
    (s,) = sync.add(1, 5, "b")
    assert isinstance(s, SyncedSet)
    assert s.messages == ("a", "b", "c")
    assert s.stamp_ns == 5


def test_exact_discards_older_unmatched():
    sync = StampSynchronizer(2)
    feed(sync, [(0, 1, "a1"), (0, 2, "a2"), (0, 3, "a3"), (1, 2, "b2")])
    s = sync.stats()
    assert s.matched == 1
    assert s.dropped_unmatched == [1, 0]  # a1 superseded
    assert s.queued == [1, 0]  # a3 waits
    (out,) = sync.add(1, 3, "b3")
    assert out.messages == ("a3", "b3")
    assert_conserved(sync)


def test_exact_no_match_when_stamps_differ_by_one_ns():
    sync = StampSynchronizer(2)
    assert feed(sync, [(0, 100, "a"), (1, 101, "b")]) == []


# -- approximate --------------------------------------------------------------------


def test_approximate_within_and_outside_slop():
    sync = StampSynchronizer(2, mode="approximate", slop_ns=10)
    (s,) = feed(sync, [(0, 100, "a"), (1, 110, "b")])  # spread == slop: accepted
    assert s.messages == ("a", "b")
    assert s.stamps == (100, 110)
    assert s.stamp_ns == 110  # reference = newest stamp of the set
    assert feed(sync, [(0, 200, "a2"), (1, 211, "b2")]) == []  # 11 > slop


def test_approximate_prefers_tightest_set():
    sync = StampSynchronizer(3, mode="approximate", slop_ns=50)
    # {92, 100, 108} spreads 16, {100, 105, 108} spreads 8.
    assert feed(sync, [(1, 92, "b92"), (1, 105, "b105"), (2, 108, "c108")]) == []
    (s,) = sync.add(0, 100, "a100")
    assert s.messages == ("a100", "b105", "c108")
    # Where closest-in-time is not tightest: 98 is closer to 100 than 104 is,
    # but {98,100,106} spreads 8 and {100,104,106} spreads 6.
    sync = StampSynchronizer(3, mode="approximate", slop_ns=50)
    feed(sync, [(1, 98, "b98"), (1, 104, "b104"), (2, 106, "c106")])
    (s,) = sync.add(0, 100, "a100")
    assert s.stamps == (100, 104, 106)
    assert sync.stats().dropped_unmatched == [0, 1, 0]  # b98 superseded


def test_approximate_tie_prefers_older_window():
    sync = StampSynchronizer(2, mode="approximate", slop_ns=10)
    feed(sync, [(1, 95, "b95"), (1, 105, "b105")])
    (s,) = sync.add(0, 100, "a")
    assert s.stamps == (100, 95)
    assert sync.stats().queued == [0, 1]  # b105 kept for a later set


def test_approximate_keeps_newer_messages_and_stays_monotone():
    sync = StampSynchronizer(2, mode="approximate", slop_ns=5)
    out = feed(sync, [(0, 100, "a100"), (0, 103, "a103"), (1, 104, "b104"), (1, 106, "b106")])
    # Pivot b104 -> tightest {103, 104}; then a100 is superseded and b106 has no partner.
    assert [s.stamps for s in out] == [(103, 104)]
    out = feed(sync, [(0, 107, "a107")])
    assert [s.stamps for s in out] == [(107, 106)]
    # A message at or before its input's last emitted stamp can never match.
    assert sync.add(1, 105, "b105") == []
    assert sync.stats().late == [0, 1]
    assert_conserved(sync)


@settings(max_examples=200, deadline=None)
@given(
    others=st.lists(st.lists(st.integers(0, 30), min_size=1, max_size=5), min_size=1, max_size=3),
    pivot=st.integers(0, 30),
    slop=st.integers(0, 10),
)
def test_approximate_choice_matches_brute_force(others, pivot, slop):
    # Inputs 1.. are filled first (nothing can match while input 0 is empty); then the
    # pivot on input 0 must pick the tightest set, ties -> oldest window -> earliest.
    n = len(others) + 1
    sync = StampSynchronizer(n, mode="approximate", slop_ns=slop, queue_size=10)
    for j, stamps in enumerate(others, start=1):
        for k, t in enumerate(stamps):
            assert sync.add(j, t, (j, k)) == []
    out = sync.add(0, pivot, (0, 0))
    # Candidates per input sorted by (stamp, arrival).
    queues = [sorted((t, k) for k, t in enumerate(stamps)) for stamps in others]
    best = min(
        itertools.product(*queues),
        key=lambda c: (max(pivot, *(t for t, _ in c)) - min(pivot, *(t for t, _ in c)),
                       min(pivot, *(t for t, _ in c)), c),
    )
    stamps = (pivot,) + tuple(t for t, _ in best)
    if max(stamps) - min(stamps) > slop:
        assert out == []
    else:
        (s,) = out
        assert s.stamps == stamps
        assert s.messages == ((0, 0),) + tuple((j, k) for j, (_, k) in enumerate(best, start=1))


def test_approximate_zero_slop_equals_exact():
    rng = random.Random(3)
    events = [(rng.randrange(3), rng.randrange(0, 60, 3), k) for k in range(300)]
    events.sort(key=lambda e: e[1])  # per-input non-decreasing stamps
    a = StampSynchronizer(3, mode="exact", queue_size=5)
    b = StampSynchronizer(3, mode="approximate", slop_ns=0, queue_size=5)
    assert feed(a, events) == feed(b, events)
    assert a.stats() == b.stats()
    # equal stamps take a bisection path; a slop below the stamps' step (3 ns) makes the
    # general search match the same sets
    c = StampSynchronizer(3, mode="approximate", slop_ns=1, queue_size=5)
    a = StampSynchronizer(3, mode="exact", queue_size=5)
    assert feed(a, events) == feed(c, events)
    assert a.stats() == c.stats()


# -- queues, late, reset --------------------------------------------------------------


def test_overflow_drops_oldest_and_counts():
    sync = StampSynchronizer(2, queue_size=3)
    feed(sync, [(0, t, f"a{t}") for t in range(1, 6)])
    s = sync.stats()
    assert s.dropped_overflow == [2, 0]
    assert s.queued == [3, 0]
    assert sync.add(1, 1, "b1") == []  # a1 was evicted
    (out,) = sync.add(1, 3, "b3")
    assert out.messages == ("a3", "b3")
    assert_conserved(sync)


def test_overflow_evicts_by_arrival_not_stamp():
    # Stale high stamps from before a clock jump must not pin the queue.
    sync = StampSynchronizer(2, queue_size=2)
    feed(sync, [(0, 50, "old50"), (0, 60, "old60"), (0, 1, "a1"), (0, 2, "a2")])
    assert sync.stats().queued == [2, 0]
    (out,) = sync.add(1, 1, "b1")
    assert out.messages == ("a1", "b1")


def test_late_messages_counted_not_queued():
    sync = StampSynchronizer(2)
    feed(sync, [(0, 10, "a"), (1, 10, "b")])
    assert sync.add(0, 9, "old") == []
    assert sync.add(1, 10, "dup") == []
    s = sync.stats()
    assert s.late == [1, 1]
    assert s.queued == [0, 0]
    assert_conserved(sync)


def test_loop_replay_resets_and_matches_again():
    sync = StampSynchronizer(2, reset_on_backwards_ns=S)
    events = []
    for _ in range(2):
        for k in range(1, 11):
            events += [(0, k * S, ("a", k)), (1, k * S, ("b", k))]
    out = feed(sync, events)
    assert [s.stamp_ns // S for s in out] == list(range(1, 11)) * 2
    s = sync.stats()
    assert s.resets == 1
    assert s.late == [0, 0]
    assert s.matched == 20
    assert_conserved(sync)


def test_backwards_reset_discards_queued_as_dropped():
    sync = StampSynchronizer(2, reset_on_backwards_ns=S)
    feed(sync, [(0, 10 * S, "a"), (1, 10 * S, "b"), (0, 11 * S, "a11"), (1, 12 * S, "b12")])
    assert sync.stats().queued == [1, 1]
    # Small backwards step (<= threshold) is late, not a reset.
    assert sync.add(0, 9 * S, "x") == []
    assert sync.stats().resets == 0
    assert sync.stats().late == [1, 0]
    sync.add(0, 2 * S, "new")
    s = sync.stats()
    assert s.resets == 1
    assert s.dropped_reset == [1, 1]
    assert s.queued == [1, 0]  # the triggering message is accepted
    (out,) = sync.add(1, 2 * S, "bnew")
    assert out.messages == ("new", "bnew")
    assert_conserved(sync)


def test_explicit_reset():
    sync = StampSynchronizer(2)
    feed(sync, [(0, 10, "a"), (1, 10, "b"), (0, 20, "a")])
    sync.reset()
    s = sync.stats()
    assert (s.resets, s.dropped_reset, s.queued) == (1, [1, 0], [0, 0])
    assert sync.last_stamp_ns is None
    # After reset, older stamps are no longer late.
    feed(sync, [(0, 5, "a"), (1, 5, "b")])
    assert sync.stats().matched == 2
    assert_conserved(sync)


def test_single_input_passes_through():
    sync = StampSynchronizer(1)
    for t in [3, 7, 8, 100]:
        (s,) = sync.add(0, t, t)
        assert s.messages == (t,) and s.stamp_ns == t
    assert sync.add(0, 100, "dup") == []  # duplicate stamp is late
    s = sync.stats()
    assert (s.matched, s.late, s.queued) == (4, [1], [0])
    assert_conserved(sync)


def test_stats_as_dict():
    sync = StampSynchronizer(2)
    feed(sync, [(0, 1, "a")])
    d = sync.stats().as_dict()
    assert d["received"] == [1, 0] and d["dropped"] == [0, 0] and d["queued"] == [1, 0]


@settings(max_examples=60, deadline=None)
@given(
    n=st.integers(1, 4),
    qsize=st.integers(1, 4),
    slop=st.integers(0, 6),
    events=st.lists(st.tuples(st.integers(0, 3), st.integers(0, 40)), max_size=80),
)
def test_conservation_random_streams(n, qsize, slop, events):
    sync = StampSynchronizer(n, mode="approximate", slop_ns=slop, queue_size=qsize,
                             reset_on_backwards_ns=15)
    out = feed(sync, [(i % n, t, (i % n, t)) for i, t in events])
    assert_conserved(sync)
    s = sync.stats()
    assert max(s.queued, default=0) <= qsize
    for ss in out:
        assert max(ss.stamps) - min(ss.stamps) <= slop
        assert ss.stamp_ns == max(ss.stamps)
        assert all(m == (i, t) for i, (m, t) in enumerate(zip(ss.messages, ss.stamps)))


# -- property: exact matching --------------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(1, 4),
    stamps=st.sets(st.integers(0, 10**6), min_size=1, max_size=25),
    seed=st.integers(0, 2**32 - 1),
)
def test_exact_every_stamp_matched_once(n, stamps, seed):
    ordered = sorted(stamps)
    rng = random.Random(seed)
    pending = [list(ordered) for _ in range(n)]
    sync = StampSynchronizer(n, mode="exact", queue_size=len(ordered) + 1)
    out = []
    while any(pending):
        i = rng.choice([k for k in range(n) if pending[k]])
        t = pending[i].pop(0)
        out.extend(sync.add(i, t, (i, t)))
    assert sorted(s.stamp_ns for s in out) == ordered
    for s in out:
        assert s.messages == tuple((i, s.stamp_ns) for i in range(n))
    st_ = sync.stats()
    assert st_.dropped == [0] * n and st_.late == [0] * n and st_.queued == [0] * n


# -- threading ------------------------------------------------------------------------


def _run_threads(targets, timeout=30.0):
    threads = [threading.Thread(target=t, daemon=True) for t in targets]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout)
    # A live thread here means a deadlock (generous bound; not a timing assertion).
    assert not any(th.is_alive() for th in threads), "deadlock in synchroniser"


def test_concurrent_add_from_threads():
    n, n_stamps = 4, 500
    sync = StampSynchronizer(n, queue_size=n_stamps)
    results = []
    res_lock = threading.Lock()
    barrier = threading.Barrier(n)

    def producer(i):
        def run():
            barrier.wait()
            for t in range(n_stamps):
                for s in sync.add(i, t, (i, t)):
                    with res_lock:
                        results.append(s)
        return run

    _run_threads([producer(i) for i in range(n)])
    assert sorted(s.stamp_ns for s in results) == list(range(n_stamps))
    assert sorted(s.seq for s in results) == list(range(n_stamps))
    assert_conserved(sync)


def test_reentrant_callback_from_threads_does_not_deadlock():
    # The callback re-enters add() and stats(); run under the internal
    # (non-reentrant) lock it would deadlock.
    n, n_stamps = 3, 300
    sync = StampSynchronizer(n, queue_size=n_stamps)
    seen = []
    seen_lock = threading.Lock()

    def on_set(s):
        with seen_lock:
            seen.append(s.stamp_ns)
        # Input 0 already emitted this stamp, so the echo is deterministically late.
        assert sync.add_and_dispatch(0, s.stamp_ns, "echo", callback=on_set) == []
        sync.stats()

    def producer(i):
        def run():
            for t in range(n_stamps):
                sync.add_and_dispatch(i, t, (i, t), callback=on_set)
        return run

    _run_threads([producer(i) for i in range(n)])
    assert sorted(seen) == list(range(n_stamps))
    s = sync.stats()
    assert s.matched == n_stamps
    assert s.late == [n_stamps, 0, 0]
    assert_conserved(sync)


def test_reentrant_callback_can_complete_nested_sets():
    sync = StampSynchronizer(2)
    seen = []

    def on_set(s):
        seen.append(s.stamp_ns)
        if s.stamp_ns % 2 == 0:
            # Feeding the next stamp from inside the callback emits a nested set.
            sync.add_and_dispatch(0, s.stamp_ns + 1, "a", callback=on_set)
            sync.add_and_dispatch(1, s.stamp_ns + 1, "b", callback=on_set)

    for t in range(0, 20, 2):
        sync.add_and_dispatch(0, t, "a", callback=on_set)
        sync.add_and_dispatch(1, t, "b", callback=on_set)
    assert seen == list(range(20))
    assert_conserved(sync)


def test_add_and_dispatch_uses_registered_callback_outside_lock():
    got = []
    sync = StampSynchronizer(1)

    def cb(s):
        # Lock must be free while user code runs.
        assert sync._lock.acquire(blocking=False)
        sync._lock.release()
        got.append(s.messages)

    sync.callback = cb
    sync.add_and_dispatch(0, 1, "m")
    assert got == [("m",)]
    with pytest.raises(ValueError):
        StampSynchronizer(1).add_and_dispatch(0, 1, "m")


def test_stamp_of_bytes_reads_the_header_stamp_and_refuses_other_bytes():
    import pytest
    from lidar_quality_core.time_sync import HEADER_STAMP, stamp_of_bytes

    raw = bytearray(b"\x00\x01\x00\x00" + bytes(12))
    HEADER_STAMP.pack_into(raw, 4, 1234, 5)
    assert stamp_of_bytes(raw) == stamp_of_bytes(bytes(raw)) == 1234 * 10**9 + 5
    for bad in (bytes(raw[:11]), b"\x01\x00" + bytes(raw[2:]), b""):
        with pytest.raises(ValueError):
            stamp_of_bytes(bad)


def test_loop_of_a_bag_shorter_than_the_reset_threshold_restarts():
    # 5 frames 0.1 s apart replayed three times: each jump back (0.4 s) is below the
    # 1 s reset threshold; every looped frame must match, none count late.
    sync = StampSynchronizer(2, reset_on_backwards_ns=S)
    events = []
    for _ in range(3):
        for k in range(1, 6):
            events += [(0, k * S // 10, ("a", k)), (1, k * S // 10, ("b", k))]
    out = feed(sync, events)
    assert [s.stamp_ns * 10 // S for s in out] == list(range(1, 6)) * 3
    s = sync.stats()
    assert s.resets == 2 and s.late == [0, 0] and s.matched == 15
    assert_conserved(sync)


def test_single_input_loop_restarts_duplicate_stays_late():
    sync = StampSynchronizer(1)
    for t in (10, 20, 30):
        assert len(sync.add(0, t, t)) == 1
    assert sync.add(0, 30, "dup") == []
    (s,) = sync.add(0, 10, "again")
    assert s.messages == ("again",)
    st = sync.stats()
    assert st.late == [1] and st.resets == 1 and st.matched == 4
    assert_conserved(sync)


def test_straggler_on_one_input_is_late_not_a_loop():
    sync = StampSynchronizer(3)
    feed(sync, [(j, t, (j, t)) for t in (10, 20) for j in range(3)])
    assert sync.add(0, 15, "old") == [] and sync.add(1, 15, "old") == []
    st = sync.stats()
    assert st.resets == 0 and st.late == [1, 1, 0]
    (s,) = feed(sync, [(j, 30, (j, 30)) for j in range(3)])
    assert s.stamp_ns == 30
    # the stragglers' slots are cleared by the emission: a later lone one is late again
    assert sync.add(2, 15, "old") == [] and sync.stats().resets == 0
    assert_conserved(sync)
