"""A server starts what a first session would otherwise wait for: the render kernels (a warm-up
render of a small molecule) and a selection worker, before anyone connects."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from server.settings import ServerSettings
from tests.conftest import make_settings, start_server


def test_the_server_warms_up_before_its_first_session(tmp_path: Path) -> None:
    server = start_server(make_settings(tmp_path, warm_up_render=1, selection_prestart=1))
    try:
        state = server._app.state.scalesteer
        deadline = time.monotonic() + 60
        while not (state.gpu.warmed and state.selections.pids()):
            assert time.monotonic() < deadline, "no warm-up render or no selection worker"
            time.sleep(0.1)
        assert len(state.selections.pids()) == 1  # the other worker starts on demand
        assert "warm-up" not in state.gpu._lane_of  # its slot is gone, nothing left placed
    finally:
        server.stop()


def test_a_cold_server_starts_nothing_ahead(tmp_path: Path) -> None:
    server = start_server(make_settings(tmp_path))  # the suite's default: both off
    try:
        time.sleep(1.0)
        state = server._app.state.scalesteer
        assert not state.gpu.warmed and not state.selections.pids()
    finally:
        server.stop()


@pytest.mark.parametrize(
    ("name", "value", "message"),
    [
        ("warm_up_render", 2, "warm_up_render must be 0 or 1"),
        ("selection_prestart", 3, "selection_prestart must be between 0 and selection_workers"),
    ],
)
def test_warm_start_settings_are_checked(name: str, value: int, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        ServerSettings(**{name: value})  # type: ignore[arg-type]
