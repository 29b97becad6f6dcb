"""Shared fixtures: a real render server on an ephemeral loopback port."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import pytest

from server.commands.serve import ServerThread
from server.settings import ServerSettings


class LiveServer(ServerThread):
    """The real server on 127.0.0.1 with URLs and tokens for tests."""

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/ws/sim"

    @property
    def view_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}/ws/view"

    @property
    def token(self) -> str | None:
        return self.settings.token

    @property
    def viewer_token(self) -> str | None:
        return self.settings.viewer_token

    def restart(self) -> LiveServer:
        """Stop and start a fresh server on the same port and state directory."""
        self.stop()
        return start_server(self.settings, port=self.port)


def start_server(settings: ServerSettings, port: int = 0) -> LiveServer:
    return LiveServer(replace(settings, port=port))


def make_settings(tmp_path: Path, **overrides: object) -> ServerSettings:
    base = ServerSettings(
        host="127.0.0.1",
        port=0,
        device="cpu",
        token="test-token",
        viewer_token="viewer-token",
        state_dir=tmp_path / "state",
        default_size=(64, 48),
        stats_interval_s=0.5,
        batch_engine="local",  # the Ray tests ask for Ray (tests/server/pipeline/test_ray.py)
        # the suite's many servers start nothing ahead of their first session (each would
        # cost the 2-core machine about a second); tests/server/web/test_warm_start.py
        # starts them as `scalesteer serve` does
        warm_up_render=0,
        selection_prestart=0,
    )
    return replace(base, **overrides)  # type: ignore[arg-type]


@pytest.fixture
def live_server(tmp_path: Path) -> Iterator[LiveServer]:
    server = start_server(make_settings(tmp_path))
    yield server
    server.stop()
