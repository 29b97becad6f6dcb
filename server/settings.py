"""Server configuration: one frozen object built by `scalesteer serve` or by tests."""

from __future__ import annotations

import ipaddress
import os
import secrets
from dataclasses import dataclass, field
from pathlib import Path

from protocol import DEFAULT_LIMITS, Limits, RenderParams

VIEWER_LIMITS = Limits(max_message_bytes=256 * 1024)
"""Browsers and scripts send only small control messages."""


def default_encode_workers() -> int:
    """One encoder thread per core, at most 8: a 1080p JPEG keeps one core busy for 10-30 ms,
    so a few encodes in flight keep up with a GPU that renders a frame in about 10 ms."""
    return max(1, min(8, os.cpu_count() or 1))


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class ServerSettings:
    """What the server needs to know at start; see `scalesteer serve --help`."""

    host: str = "127.0.0.1"
    port: int = 8000
    device: str = "auto"
    token: str | None = field(default_factory=lambda: secrets.token_urlsafe(18))
    viewer_token: str | None = field(default_factory=lambda: secrets.token_urlsafe(18))
    open_on_loopback: bool = False
    data_dir: Path | None = None
    state_dir: Path = Path(".scalesteer")
    allowed_origins: tuple[str, ...] = ()
    limits: Limits = DEFAULT_LIMITS
    viewer_limits: Limits = VIEWER_LIMITS
    max_upload_bytes: int = 512 * 1024 * 1024
    max_sessions: int = 64
    job_retention_s: float = 24 * 3600.0
    """How long a finished job's output stays downloadable."""
    job_max_bytes: int = 2 << 30
    """Disk the outputs of finished jobs may take together; the oldest go first beyond it."""
    session_idle_s: float = 600.0
    interactive_idle_s: float = 0.15
    interactive_scale: float = 0.5
    interactive_jpeg_quality: int = 60
    frame_wait_s: float = 0.25
    """Longest a simulation's next big frame (over 1 MiB) waits to be read until a render took
    the last one."""
    default_size: tuple[int, int] = (640, 480)
    encode_workers: int = field(default_factory=default_encode_workers)
    """Threads that encode images; also how many encodes the renderer keeps in flight."""
    render_defaults: RenderParams = field(default_factory=RenderParams)
    stats_interval_s: float = 1.0
    state_interval_s: float = 0.1
    hello_timeout_s: float = 10.0
    client_dir: Path = Path(__file__).resolve().parents[1] / "client_web"

    def __post_init__(self) -> None:
        if self.open_on_loopback and not is_loopback(self.host):
            raise ValueError("--no-token-on-loopback-only needs a loopback --host")
        if self.token is None and not self.open_on_loopback:
            raise ValueError("a token is required unless the server is open on loopback only")
        if self.encode_workers < 1:
            raise ValueError("--encode-workers must be at least 1")
        if self.data_dir is not None and not self.data_dir.is_dir():
            raise ValueError(f"--data-dir {self.data_dir} is not a directory")
