"""InputWatchdog: idle, a missing input, stamps that never match, WARN then ERROR."""
import pytest
from lidar_quality_core.input_watchdog import ERROR, OK, WARN, InputWatchdog, nearest_offsets

MS = 1_000_000


def test_quiet_start_and_matching_inputs_are_ok():
    wd = InputWatchdog(2, timeout_s=2.0, error_s=10.0, start_s=0.0)
    assert wd.check(1.0).cause == "ok"
    assert wd.check(5.0).cause == "idle" and wd.check(5.0).level == OK  # nothing arrives
    for k in range(50):  # 10 Hz, every set matches
        t = 5.0 + k / 10
        wd.arrival(0, k * 100 * MS, t)
        wd.arrival(1, k * 100 * MS, t)
        wd.matched(t)
    assert wd.check(10.0).cause == "ok"
    assert wd.check(12.0).cause == "idle"  # the bag ended: nothing to say


def test_missing_input_warns_then_errors():
    wd = InputWatchdog(3, timeout_s=2.0, error_s=6.0, start_s=0.0)
    for k in range(80):  # inputs 0 and 2 arrive, 1 never does: nothing matches
        wd.arrival(0, k * 100 * MS, k / 10)
        wd.arrival(2, k * 100 * MS, k / 10)
        if k == 15:
            assert wd.check(k / 10).level == OK  # within the timeout
        if k == 25:
            v = wd.check(k / 10)
            assert (v.level, v.cause, v.missing) == (WARN, "missing", [1])
    v = wd.check(7.9)
    assert (v.level, v.cause, v.missing) == (ERROR, "missing", [1])
    assert v.silent_s == pytest.approx(7.9)


def test_input_that_stops_later_is_missing():
    wd = InputWatchdog(2, timeout_s=1.0, error_s=5.0, start_s=0.0)
    for k in range(10):
        for j in range(2):
            wd.arrival(j, k * 100 * MS, k / 10)
        wd.matched(k / 10)
    for k in range(10, 30):  # input 1 stops at 1 s
        wd.arrival(0, k * 100 * MS, k / 10)
    v = wd.check(2.9)
    assert (v.cause, v.missing, v.level) == ("missing", [1], WARN)


def test_stamps_that_never_match_report_the_nearest_offset():
    wd = InputWatchdog(3, timeout_s=2.0, error_s=10.0, start_s=0.0)
    for k in range(40):  # input 1 stamped 10 ms after the cloud, input 2 equal
        wd.arrival(0, k * 100 * MS, k / 10)
        wd.arrival(1, k * 100 * MS + 10 * MS, k / 10)
        wd.arrival(2, k * 100 * MS, k / 10)
    v = wd.check(3.9)
    assert (v.level, v.cause, v.missing) == (WARN, "no_match", [])
    assert v.offset_ns == [0, 10 * MS, 0]


def test_nearest_offsets_and_arguments():
    assert nearest_offsets([[0, 100], [95, 300], []]) == [0, 5, 0]
    with pytest.raises(ValueError):
        InputWatchdog(2, timeout_s=5.0, error_s=1.0)
    with pytest.raises(ValueError):
        InputWatchdog(0)


def test_one_unmatched_arrival_after_a_pause_is_not_a_verdict():
    # a paused process: its clock jumps, one message is in, its set not yet complete
    wd = InputWatchdog(1, timeout_s=2.0, error_s=10.0, start_s=0.0)
    wd.arrival(0, 0, 0.0)
    wd.matched(0.0)
    wd.arrival(0, 100 * MS, 2.5)
    assert wd.check(2.5).cause == "ok"
    wd2 = InputWatchdog(2, timeout_s=2.0, error_s=10.0, start_s=0.0)
    wd2.arrival(0, 0, 2.5)
    assert wd2.check(2.5).cause == "ok"  # one message of one input: not yet "missing"
    wd2.arrival(0, 100 * MS, 2.6)
    assert wd2.check(2.6).cause == "missing"
