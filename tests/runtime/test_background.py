"""runtime.background: work beside a loop, collected at a fixed loop time."""
import threading

import pytest

from runtime.background import DelayedResult


def _slow(gate: threading.Event, value):
    gate.wait(10.0)
    return value * 2


def test_a_waiting_clock_takes_the_result_at_its_delay_even_if_the_work_is_slow():
    gate = threading.Event()
    d = DelayedResult("test-bg-wait", delay_s=1.0, clock_waits=True)
    d.submit(5.0, _slow, gate, 21, context="ctx")
    assert d.busy
    assert d.collect(5.5) is None                      # before its delay: nothing, even if done
    threading.Timer(0.2, gate.set).start()             # the work finishes while collect waits
    assert d.collect(6.0) == (42, "ctx")
    assert not d.busy and d.collect(7.0) is None


def test_hardware_never_blocks_on_unfinished_work():
    gate = threading.Event()
    d = DelayedResult("test-bg-nowait", delay_s=1.0, clock_waits=False)
    d.submit(0.0, _slow, gate, 1)
    assert d.collect(3.0) is None and d.busy           # past its delay but not done: the loop goes on
    gate.set()
    d._job[1].result(10.0)
    assert d.collect(3.1) == (2, None)


def test_one_job_at_a_time_and_errors_reach_the_loop():
    d = DelayedResult("test-bg-err", delay_s=0.0, clock_waits=True)
    d.submit(0.0, lambda: 1 / 0)
    with pytest.raises(RuntimeError, match="in flight"):
        d.submit(0.0, lambda: None)
    with pytest.raises(ZeroDivisionError):
        d.collect(0.0)
    assert not d.busy
