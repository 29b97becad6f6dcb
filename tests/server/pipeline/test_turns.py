"""The order a device's thread takes its work in (`server.pipeline.turns`): live sessions
first, one-off renders and jobs after, work that waited long every other turn."""

from __future__ import annotations

import threading
from concurrent.futures import CancelledError, Future

import pytest

from server.pipeline.turns import JOB, LIVE, ONE_OFF, TurnExecutor, rank_of


class Clock:
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
    pool: TurnExecutor, work: list[tuple[int, str]], clock: Clock | None = None, age: float = 0
) -> list[str]:
    """Queue `work` (rank, label) behind a busy worker, advance the clock by `age`, let it go
    and return the order the labels ran in."""
    order: list[str] = []
    release, first = held(pool)
    futures = [pool.submit_ranked(rank, order.append, label) for rank, label in work]
    if clock is not None:
        clock.now += age
    release.set()
    for f in [first, *futures]:
        f.result(10)
    return order


def test_slots_have_ranks() -> None:
    assert rank_of("session:default") == rank_of("warm-up") == rank_of(None) == LIVE
    assert rank_of("rest:4f2a") == ONE_OFF
    assert rank_of("job:17") == JOB


def test_a_live_render_goes_before_one_off_renders_and_jobs_queued_earlier() -> None:
    pool = TurnExecutor(age_s=60.0)
    try:
        work = [(JOB, "job"), (ONE_OFF, "rest 1"), (ONE_OFF, "rest 2"), (LIVE, "live")]
        assert run_in_turns(pool, work) == ["live", "rest 1", "rest 2", "job"]
    finally:
        pool.shutdown()


def test_a_live_render_waits_for_no_more_than_the_render_under_way() -> None:
    """On the CPU device a one-off render takes seconds: a live image that needs two live
    renders in a row must not wait for a second one-off render between them."""
    clock = Clock()
    pool = TurnExecutor(age_s=0.5, clock=clock)
    order: list[str] = []

    def work(label: str, seconds: float) -> None:
        order.append(label)
        clock.now += seconds

    try:
        release, first = held(pool)
        clock.now += 7.0  # the one-off render under way
        queued = [pool.submit_ranked(ONE_OFF, work, f"rest {i}", 7.0) for i in (2, 3)]
        queued += [pool.submit_ranked(LIVE, work, f"live {i}", 0.2) for i in (1, 2)]
        release.set()
        for f in [first, *queued]:
            f.result(10)
        assert order == ["live 1", "live 2", "rest 2", "rest 3"]
    finally:
        pool.shutdown()


def test_work_that_waited_gets_a_share_of_a_device_that_live_work_fills() -> None:
    clock = Clock()
    pool = TurnExecutor(age_s=0.5, share=0.8, clock=clock)
    order: list[str] = []

    def work(label: str, seconds: float) -> None:
        order.append(label)
        clock.now += seconds

    try:
        release, first = held(pool)
        queued = [pool.submit_ranked(ONE_OFF, work, "rest", 0.1) for _ in range(10)]
        queued += [pool.submit_ranked(LIVE, work, "live", 0.1) for _ in range(100)]
        release.set()
        for f in [first, *queued]:
            f.result(10)
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
