"""bus/background.py: a node's after-publish work runs below the node's priority, in order, errors surfacing."""

from __future__ import annotations

import os
import threading
import time

import pytest

from followbus.bus.background import BackgroundJob


def test_jobs_run_one_at_a_time_in_order_and_wait_returns_after_the_job() -> None:
    job = BackgroundJob("test")
    done: list[int] = []

    def slow(i: int) -> None:
        time.sleep(0.05)
        done.append(i)

    for i in range(3):
        job.submit(lambda i=i: slow(i))
        assert done == list(range(i))  # submit waited for the previous one, not for this one
    job.wait()
    assert done == [0, 1, 2]


def test_the_job_runs_nicer_than_the_node() -> None:
    job = BackgroundJob("test", nice_increment=7)
    seen: list[tuple[int, int]] = []
    started = threading.Event()

    def look() -> None:
        seen.append((threading.get_native_id(), os.getpriority(os.PRIO_PROCESS, 0)))
        started.set()

    job.submit(look)
    assert started.wait(5.0)  # not job.wait(): a node waiting on its job raises the job to its own priority
    job.wait()
    node_nice = os.getpriority(os.PRIO_PROCESS, 0)
    tid, nice = seen[0]
    assert tid != threading.get_native_id()
    assert nice == min(node_nice + 7, 19)


def test_a_failed_job_raises_in_the_node_at_the_next_wait() -> None:
    job = BackgroundJob("test")

    def fail() -> None:
        raise ValueError("bad sample")

    job.submit(fail)
    with pytest.raises(ValueError, match="bad sample"):
        job.wait()
    job.wait()  # raised once
    job.submit(lambda: None)
    job.wait()


def test_a_job_the_node_waits_on_runs_at_the_nodes_priority_where_permitted() -> None:
    if os.geteuid() != 0:
        pytest.skip("raising a thread back to its process's priority needs root or CAP_SYS_NICE")
    job = BackgroundJob("test", nice_increment=7)
    release = threading.Event()
    seen: list[int] = []

    def held() -> None:
        release.wait(5.0)
        seen.append(os.getpriority(os.PRIO_PROCESS, 0))

    job.submit(held)
    time.sleep(0.1)  # the job is running, at the low priority
    waiter = threading.Thread(target=job.wait)
    waiter.start()
    time.sleep(0.1)  # the node now waits: the job is raised
    release.set()
    waiter.join(5.0)
    assert seen == [os.getpriority(os.PRIO_PROCESS, 0)]
