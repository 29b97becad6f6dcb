"""The steps of the server's stop (`server.web.app._closing`): each runs even when one before
it failed, and a step waited for until a deadline is left behind there, not waited on."""

from __future__ import annotations

import asyncio
import logging
import time

import pytest

from server.web.app import _closing


def test_a_failed_step_is_logged_and_the_next_still_runs(caplog: pytest.LogCaptureFixture) -> None:
    ran: list[str] = []

    async def failing() -> None:
        raise OSError("disk gone")

    def broken() -> None:
        raise RuntimeError("timers gone")

    async def stop() -> None:
        await _closing("the recordings", failing())
        await _closing("the owners' leases", broken)
        await _closing("the jobs", asyncio.sleep(0, result=ran.append("jobs")))

    with caplog.at_level(logging.ERROR, logger="scalesteer"):
        asyncio.run(stop())
    assert ran == ["jobs"]
    text = caplog.text
    assert "closing the recordings failed" in text and "disk gone" in text
    assert "closing the owners' leases failed" in text and "timers gone" in text


def test_a_step_still_waiting_at_the_deadline_is_cancelled_and_left(
    caplog: pytest.LogCaptureFixture,
) -> None:
    cancelled: list[bool] = []

    async def held() -> None:
        try:
            await asyncio.sleep(60)  # a render holding the device
        except asyncio.CancelledError:
            cancelled.append(True)
            raise

    async def stop() -> float:
        t0 = time.monotonic()
        await _closing("the sessions", held(), time.monotonic() + 0.2)
        took = time.monotonic() - t0
        await asyncio.sleep(0)  # the cancellation reaches the step
        return took

    with caplog.at_level(logging.WARNING, logger="scalesteer"):
        took = asyncio.run(stop())
    assert took < 30  # not the step's 60 s
    assert cancelled == [True]
    assert "the sessions still waited on the devices at the deadline" in caplog.text


def test_a_step_cancelled_before_the_stop_ends_quietly(caplog: pytest.LogCaptureFixture) -> None:
    async def stop() -> None:
        warming = asyncio.ensure_future(asyncio.sleep(60))
        warming.cancel()
        await asyncio.sleep(0)
        await _closing("the warm-up render", warming, time.monotonic() + 5)

    with caplog.at_level(logging.WARNING, logger="scalesteer"):
        asyncio.run(stop())  # no CancelledError out of the stop
    assert "warm-up" not in caplog.text
