"""Frames staged for upload: each arriving frame is copied into a free buffer on a thread of its
own; a render takes its frame's copy, and a buffer in use is never written until released."""

from __future__ import annotations

import math
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from server.pipeline.staging import FrameStager, State


def plain(n: int) -> tuple[object, np.ndarray]:
    a = np.empty((n, 3), np.float32)
    return a, a


@pytest.fixture
def pool() -> ThreadPoolExecutor:
    with ThreadPoolExecutor(1) as p:
        yield p


def frame(k: float, n: int = 50) -> np.ndarray:
    return np.full((n, 3), k, np.float32)


def test_a_render_takes_the_copy_of_its_own_frame(pool: ThreadPoolExecutor) -> None:
    stager = FrameStager(50, pool, plain)
    assert stager.offer(1, frame(1.0))
    staged = stager.take(1, wait_s=5.0)
    assert staged is not None and np.array_equal(staged, frame(1.0))
    assert stager.take(1, wait_s=0.1) is None  # in use: not handed out twice
    assert stager.take(7, wait_s=0.1) is None  # a frame never offered
    stager.release(staged)
    assert stager.states() == [State.FREE] * 3


def test_a_buffer_in_use_is_never_rewritten(pool: ThreadPoolExecutor) -> None:
    stager = FrameStager(50, pool, plain, count=2)
    stager.offer(1, frame(1.0))
    uploading = stager.take(1, wait_s=5.0)
    assert uploading is not None
    assert stager.offer(2, frame(2.0))
    assert stager.take(2, wait_s=5.0) is not None  # the other buffer
    assert not stager.offer(3, frame(3.0))  # both in use: frame 3 uploads from where it is
    assert np.array_equal(uploading, frame(1.0))
    stager.release(uploading)
    assert stager.offer(4, frame(4.0))
    copy = stager.take(4, wait_s=5.0)
    assert copy is uploading and np.array_equal(copy, frame(4.0))


def test_superseded_frames_give_their_buffers_to_newer_ones(pool: ThreadPoolExecutor) -> None:
    stager = FrameStager(50, pool, plain)
    for k in range(1, 8):  # frames arrive faster than renders take them
        assert stager.offer(k, frame(float(k)))
        while State.WRITING in stager.states():  # each copied before the next arrives
            time.sleep(0.001)
    newest = stager.take(7, wait_s=5.0)
    assert newest is not None and np.array_equal(newest, frame(7.0))
    assert stager.take(1, wait_s=0.1) is None  # its buffer went to a newer frame


def test_a_render_waits_for_a_copy_under_way_but_not_forever() -> None:
    gate = threading.Event()
    with ThreadPoolExecutor(1) as pool:
        pool.submit(gate.wait)  # the stage thread is busy: the copy has not started
        stager = FrameStager(50, pool, plain)
        stager.offer(1, frame(1.0))
        assert stager.take(1, wait_s=0.05) is None  # not done in time: upload the frame itself
        gate.set()
        taken = stager.take(1, wait_s=5.0)
        assert taken is not None and np.array_equal(taken, frame(1.0))


def test_a_frame_of_another_size_is_refused(pool: ThreadPoolExecutor) -> None:
    stager = FrameStager(50, pool, plain)
    with pytest.raises(ValueError, match="shape"):
        stager.offer(1, frame(1.0, n=49))


def counted_slices(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Slices of 1 KB on up to 4 threads; the rows of each copy made, as they are made."""
    from server.pipeline import staging

    monkeypatch.setattr(staging, "SLICE_BYTES", 1 << 10)  # 4,000 atoms: several slices
    monkeypatch.setattr(staging, "COPY_THREADS", 4)
    sliced: list[int] = []
    real = np.copyto

    def counted(dst: np.ndarray, src: np.ndarray, **kw: object) -> None:
        sliced.append(len(src))
        real(dst, src, **kw)

    monkeypatch.setattr(staging.np, "copyto", counted)
    return sliced


def test_a_large_frame_is_copied_in_slices_whole_and_in_order(
    pool: ThreadPoolExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    sliced = counted_slices(monkeypatch)
    n = 4_000
    src = np.arange(n * 3, dtype=np.float32).reshape(n, 3)
    stager = FrameStager(n, pool, plain)
    assert stager.offer(1, src)
    staged = stager.take(1, wait_s=5.0)
    assert staged is not None and np.array_equal(staged, src)
    assert len(sliced) == 4 and sum(sliced) == n  # four slices that cover every row once


def test_a_render_waits_for_a_large_copy_as_long_as_a_pageable_upload_would_take() -> None:
    from server.pipeline.staging import Staging

    policy = Staging()
    assert policy.wait_s(1_000) == policy.min_wait_s  # a small frame: no longer than before
    assert policy.wait_s(100_000_000) > 0.2  # 1.2 GB: the copy under way is worth waiting for
    assert policy.wait_s(200_000_000) == pytest.approx(2 * policy.wait_s(100_000_000))
    before = Staging(copy_threads=1, pageable_bytes_per_s=math.inf)  # the benchmark's control
    assert before.wait_s(100_000_000) == before.min_wait_s


def test_the_policy_names_the_threads_that_copy_a_large_frame(
    pool: ThreadPoolExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    from server.pipeline import staging

    sliced = counted_slices(monkeypatch)
    n = 4_000
    src = np.arange(n * 3, dtype=np.float32).reshape(n, 3)
    stager = FrameStager(n, pool, plain, policy=staging.Staging(copy_threads=1))
    assert stager.offer(1, src)
    staged = stager.take(1, wait_s=5.0)
    assert staged is not None and np.array_equal(staged, src)
    assert sliced == [n]  # one copy on the stage thread: the control's staging


def test_a_failed_slice_is_reported_only_once_every_slice_has_stopped_writing(
    pool: ThreadPoolExecutor, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A buffer is marked free after a failed copy and may take the next frame at once: no
    slice of the failed copy may still be writing into it then."""
    from server.pipeline import staging

    monkeypatch.setattr(staging, "SLICE_BYTES", 1 << 10)
    monkeypatch.setattr(staging, "COPY_THREADS", 4)
    real = np.copyto
    finished: list[int] = []
    first = threading.Event()

    def slow_or_failing(dst: np.ndarray, src: np.ndarray, **kw: object) -> None:
        if not first.is_set():
            first.set()
            raise MemoryError("a slice failed")
        time.sleep(0.3)
        real(dst, src, **kw)
        finished.append(len(src))

    monkeypatch.setattr(staging.np, "copyto", slow_or_failing)
    n = 4_000
    with pytest.raises(MemoryError):
        staging.copy_rows(np.empty((n, 3), np.float32), np.ones((n, 3), np.float32))
    assert len(finished) == 3  # the other three slices were done when it raised


def test_a_render_waits_briefly_for_a_copy_that_has_not_begun(pool: ThreadPoolExecutor) -> None:
    """A copy queued behind other work on the stage thread: the render waits `start_wait_s`,
    not the long wait meant for a copy under way, and uploads from where the frame is."""
    stager = FrameStager(50, pool, plain)
    hold = threading.Event()
    pool.submit(hold.wait, 5.0)  # the stage thread is busy elsewhere
    try:
        assert stager.offer(1, frame(1.0))
        t0 = time.monotonic()
        assert stager.take(1, wait_s=3.0, start_wait_s=0.05) is None
        assert time.monotonic() - t0 < 1.0
    finally:
        hold.set()
    staged = stager.take(1, wait_s=5.0, start_wait_s=5.0)  # begun and done now
    assert staged is not None and np.array_equal(staged, frame(1.0))
