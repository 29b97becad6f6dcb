"""The order a device's thread takes its work in (`server.pipeline.turns`): live sessions
first, one-off renders and jobs after, work that waited a share of a device live work fills."""

from __future__ import annotations

import threading
from concurrent.futures import CancelledError, Future

import pytest

from server.pipeline.turns import JOB, LIVE, ONE_OFF, TurnExecutor, rank_of


class Clock:
    """The executor's clock, advanced by the work it runs (each piece takes its seconds)."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def held(pool: TurnExecutor) -> tuple[threading.Event, Future[None]]:
    """The worker kept busy until the event is set (work queued meanwhile waits)."""
    started, release = threading.Event(), threading.Event()

    def block() -> None:
        started.set()
        release.wait(10)

    future: Future[None] = pool.submit(block)
    assert started.wait(10)
    return release, future


def run_in_turns(
    pool: TurnExecutor, clock: Clock, work: list[tuple[int, str, float]], busy_s: float = 0.0
) -> list[str]:
    """Queue `work` (rank, label, seconds it takes) behind a worker busy for `busy_s`, let it
    go and return the order the labels ran in."""
    order: list[str] = []

    def run(label: str, seconds: float) -> None:
        order.append(label)
        clock.now += seconds

    release, first = held(pool)
    clock.now += busy_s
    futures = [pool.submit_ranked(rank, run, label, s) for rank, label, s in work]
    release.set()
    for f in [first, *futures]:
        f.result(10)
    return order


def test_slots_have_ranks() -> None:
    assert rank_of("session:default") == rank_of("warm-up") == rank_of(None) == LIVE
    assert rank_of("rest:4f2a") == ONE_OFF
    assert rank_of("job:17") == JOB


def test_a_live_render_goes_before_one_off_renders_and_jobs_queued_earlier() -> None:
    clock = Clock()
    pool = TurnExecutor(age_s=60.0, clock=clock)
    try:
        work = [(JOB, "job", 0.0), (ONE_OFF, "rest 1", 0.0), (ONE_OFF, "rest 2", 0.0),
                (LIVE, "live", 0.0)]  # fmt: skip
        assert run_in_turns(pool, clock, work) == ["live", "rest 1", "rest 2", "job"]
    finally:
        pool.shutdown()


def test_a_live_render_waits_for_no_more_than_the_render_under_way() -> None:
    """On the CPU device a one-off render takes seconds: a live image that needs two live
    renders in a row must not wait for a second one-off render between them."""
    clock = Clock()
    pool = TurnExecutor(age_s=0.5, clock=clock)
    try:
        work = [(ONE_OFF, "rest 2", 7.0), (ONE_OFF, "rest 3", 7.0), (LIVE, "live 1", 0.2),
                (LIVE, "live 2", 0.2)]  # fmt: skip
        order = run_in_turns(pool, clock, work, busy_s=7.0)  # the one-off render under way
        assert order == ["live 1", "live 2", "rest 2", "rest 3"]
    finally:
        pool.shutdown()


def test_work_that_waited_gets_a_share_of_a_device_that_live_work_fills() -> None:
    clock = Clock()
    pool = TurnExecutor(age_s=0.5, share=0.8, clock=clock)
    try:
        work = [(ONE_OFF, "rest", 0.1)] * 10 + [(LIVE, "live", 0.1)] * 100
        order = run_in_turns(pool, clock, work)
        # none before 0.5 s of live work; then about a fifth of the device's time
        assert order[:5] == ["live"] * 5 and order[5] == "rest", order
        last = len(order) - order[::-1].index("rest")
        assert 0.15 <= order[:last].count("rest") / last <= 0.25, order
    finally:
        pool.shutdown()


def test_failures_reach_their_caller_and_the_worker_goes_on() -> None:
    pool = TurnExecutor()
    try:
        with pytest.raises(ZeroDivisionError):
            pool.submit_ranked(ONE_OFF, lambda: 1 / 0).result(10)
        assert pool.submit_ranked(JOB, lambda: 42).result(10) == 42
    finally:
        pool.shutdown()


def test_shutdown_cancels_what_waits_and_lets_the_running_work_end() -> None:
    pool = TurnExecutor()
    release, running = held(pool)
    waiting = pool.submit_ranked(JOB, lambda: "never")
    pool.shutdown(wait=False, cancel_futures=True)
    with pytest.raises(CancelledError):
        waiting.result(1)
    with pytest.raises(RuntimeError, match="after shutdown"):
        pool.submit(lambda: None)
    release.set()
    running.result(10)
    pool.shutdown(wait=True)
