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


def test_work_that_waited_long_takes_every_other_turn() -> None:
    clock = Clock()
    pool = TurnExecutor(age_s=0.5, clock=clock)
    try:
        work = [(ONE_OFF, "rest 1"), (ONE_OFF, "rest 2"), (LIVE, "live 1"), (LIVE, "live 2")]
        # all of it waited past the age: the oldest and the live work take turns
        assert run_in_turns(pool, work, clock, age=1.0) == ["rest 1", "live 1", "rest 2", "live 2"]
        # none of it did: by rank
        assert run_in_turns(pool, work, clock, age=0.0) == ["live 1", "live 2", "rest 1", "rest 2"]
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
