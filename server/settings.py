"""Server configuration: one frozen object built by `scalesteer serve` or by tests."""

from __future__ import annotations

import ipaddress
import os
import secrets
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal

from protocol import DEFAULT_LIMITS, Limits, RenderParams
from structures.isolated import ReadLimits
from structures.selection_cost import SelectionLimits
from structures.selection_pool import PoolLimits

VIEWER_LIMITS = Limits(max_message_bytes=256 * 1024)
"""Browsers and scripts send only small control messages."""


def default_encode_workers() -> int:
    """One encoder thread per core, at most 8: a 1080p JPEG keeps one core busy for 10-30 ms,
    so a few encodes in flight keep up with a GPU that renders a frame in about 10 ms."""
    return max(1, min(8, os.cpu_count() or 1))


def persistent_tokens(state_dir: Path, renew: bool = False) -> tuple[str, str]:
    """The server and viewer tokens kept in `<state_dir>/tokens.json` (created, readable by the
    owner only, on first use; `renew` draws new ones), so links copied from the dashboard keep
    working across restarts."""
    import json

    path = state_dir / "tokens.json"
    if not renew:
        try:
            saved = json.loads(path.read_text(encoding="utf-8"))
            token, viewer = str(saved["token"]), str(saved["viewer_token"])
            if token and viewer:
                return token, viewer
        except (OSError, ValueError, KeyError, TypeError):
            pass
    token, viewer = secrets.token_urlsafe(18), secrets.token_urlsafe(18)
    state_dir.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as fh:
        json.dump({"token": token, "viewer_token": viewer}, fh)
    os.replace(tmp, path)
    return token, viewer


def ray_cluster_address() -> str | None:
    """The Ray cluster named in the environment: `SCALESTEER_RAY_ADDRESS`, else Ray's own
    `RAY_ADDRESS`."""
    return os.environ.get("SCALESTEER_RAY_ADDRESS") or os.environ.get("RAY_ADDRESS") or None


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
    max_spool_bytes: int = 2 << 30
    """Request bodies being received at once, together (uploads wait in `<state-dir>/spool`
    while they are parsed); a body that would pass it is refused with 503."""
    viewer_spool_bytes: int = 1 << 30
    """The part of `max_spool_bytes` that requests without the server token may hold."""
    body_timeout_s: float = 30.0
    """Longest pause in a request's body (after its headers, or between two of its pieces):
    a body that stalls longer is answered 408 and lets go of its part of the spool."""
    close_wait_s: float = 10.0
    """How long a stopping server waits, in all, on work running on its devices (after 5 s for
    open requests) before it exits without that work (docs/server.md, "Stopping")."""
    max_sessions: int = 64
    max_connections: int = 1024
    """Open WebSockets, all endpoints together (a connection counts from its first byte)."""
    max_connections_per_token: int = 256
    """Connections holding one token (the server token, or the viewer token) at once."""
    max_clients_per_session: int = 64
    """Viewers and steerers of one session at once."""
    steerer_places: int = 4
    """Places of `max_clients_per_session` only steerers take: viewers (whose link is handed out
    widely) cannot fill a session and shut its steerers out."""
    job_retention_s: float = 24 * 3600.0
    """How long a finished job's output stays downloadable."""
    job_max_bytes: int = 2 << 30
    """Disk the outputs of finished jobs may take together; the oldest go first beyond it."""
    recording_max_bytes: int = 2 << 30
    """Size at which a recording's trajectory stops growing (the recording ends `capped`)."""
    recording_queue_bytes: int = 128 << 20
    """Positions a recording holds while they wait for the disk; frames that come while it is
    full are skipped, counted and listed in the recording (`skipped`, `skipped_spans`)."""
    movie_queue_bytes: int = 128 << 20
    """Positions of a live movie's frames waiting to be rendered (a device slower than the
    simulation renders them after the stop); frames that come while it is full are skipped,
    counted and listed by step (`movie.skipped_spans`)."""
    movie_max_s: float = 600.0
    """How long a live movie takes frames unless its request says otherwise (`max_s`)."""
    owner_grace_s: float = 15.0
    """Recordings and movies a dashboard page started (`owner`) end when the page has been
    gone from its session this long (a reconnection within it keeps them going)."""
    gpus: str | None = None
    """Render each session's images across several devices: 'all', '0,1', 'cpu,cpu'."""
    device_atoms: int | None = None
    """Atoms one device's renderer holds (None: `limits.max_atoms`). With `gpus`, a session
    alone on the devices whose system is larger is split across them by space (sort-last)."""
    batch_engine: Literal["auto", "ray", "local"] = "auto"
    """Where trajectory jobs render: in this process, or on Ray when asked (`ray`) or (`auto`)
    when a cluster is configured (`ray_address`) and Ray is installed."""
    ray_address: str | None = None
    """The Ray cluster to join (`ray start --head` prints it); with `batch_engine="ray"`, None
    starts a Ray instance of this server's own (token-authenticated, ended with the server)."""
    ray_workers: int | None = None
    """Ray render actors at most (default: one per GPU of the cluster, else one per CPU)."""
    ray_min_frames: int = 64
    """With `batch_engine="auto"`, jobs of fewer frames render in this process: a small job is
    done before Ray would have shipped it out."""
    max_running_jobs: int = 2
    """Jobs that read and render at once; later ones wait `queued`."""
    max_readers: int = 2
    """Uploaded or named files read at once for `/api/render` and job checks (each in its own
    process); further requests wait their turn."""
    read_memory_bytes: int = 6 << 30
    """Address space of one file-reading process."""
    read_timeout_s: float = 120.0
    """Wall time to open a file (and to read one frame: a quarter of it)."""
    max_file_bytes: int = 2 << 30
    """Largest size of a file once decompressed (`.gz`, `.bz2`)."""
    viewer_max_file_bytes: int = 256 << 20
    """The same for a file a viewer-token holder uploads (500,000 atoms of PDB take 40 MB)."""
    viewer_renders_per_min: float = 30.0
    """`/api/render` calls a viewer-token holder may make per minute (all viewers together)."""
    viewer_max_atoms: int = 500_000
    """Largest structure a viewer-token holder may have the server read (counted before
    parsing), so the read-only link cannot buy minutes of CPU with a small compressed file."""
    viewer_read_timeout_s: float = 20.0
    selection_max_chars: int = 2048
    """Characters of one selection (a layer's, or one typed and counted)."""
    selection_max_depth: int = 32
    """Depth of a selection's parse tree (parentheses, prefixes, chained and/or)."""
    selection_max_pairs: int = 4_000_000
    """Estimated cost of one selection, or of the layers of one render together, in atom
    pair checks (structures/selection_cost.py; about 4 s of one core)."""
    selection_timeout_s: float = 10.0
    """Wall time of one evaluation in a selection worker; past it the worker is killed."""
    selection_seconds_per_min: float = 30.0
    """Selection-worker time one client (its role and address, all its connections) may use in
    any minute for the selections it types and the layers of its REST renders; past it they are
    answered with this limit until the time is earned back."""
    selection_memory_bytes: int = 4 << 30
    """Address space of one selection worker process."""
    selection_workers: int = 2
    """Selection worker processes (each keeps the universes of the topologies it serves)."""
    warm_up_render: int = 1
    """1: the server renders a small molecule once as it starts, so the render kernels are
    loaded before the first session's picture waits for them; 0: not."""
    selection_prestart: int = 1
    """Selection workers started with the server (the others at their first request), so the
    first session's layers and periodic steps do not wait for a worker to start."""
    session_idle_s: float = 600.0
    viewer_views_per_pass: int = 1
    """In a session with a steerer, the views without one (distinct cameras and canvas sizes)
    that one pass renders besides every view a steerer is in; the longest unserved go first,
    the rest in the passes that follow. Viewers each with a camera of their own then share half
    of the session's renders instead of making every frame wait for one render each (40 such
    viewers had taken a steerer from 9.5 to 0.27 images/s). Without a steerer, a pass renders
    every due view from one frame."""
    interactive_idle_s: float = 0.15
    interactive_scale: float = 0.5
    interactive_jpeg_quality: int = 60
    video_codecs: tuple[str, ...] = ("h264", "av1", "vp9", "h264-baseline")
    """Video codecs the server streams to viewers that decode them, best first; empty: JPEG
    only. Each is encoded by NVENC where the GPU has it, else in software (server/pipeline/
    video.py)."""
    max_video_streams: int = 16
    """Video streams (each with an encoder of its own, 12-160 MB) open in the whole server;
    viewers that would need another get JPEG images until one closes."""
    max_video_streams_per_session: int = 8
    """The same for one session, so that one session's viewers cannot take them all."""
    video_kbps_per_mpixel: float = 4500.0
    """A stream's bit rate when the link allows it: per million pixels of canvas at 60 fps
    (1920x1080: 9.3 Mbit/s)."""
    video_min_kbps: float = 350.0
    video_steer_hold_s: float = 1.0
    """While a viewer steers, its video stream encodes at the interactive image's size (the
    browser scales it up, as it does an interactive JPEG image): fewer bits per frame, a
    shorter encode, send and decode. The stream returns to full size, at a keyframe, once
    nobody in its view has interacted for this long; 0 keeps every stream at full size."""
    rest_jpeg_quality: int = 95
    """Quality of the JPEG still that replaces a video viewer's last frame once the view rests
    (nothing changed for `rest_after_s`)."""
    rest_after_s: float = 0.4
    frame_budget_ms: float = 80.0
    """Render time a live image may take: images shrink to what renders in it on this device
    (nothing shrinks on a GPU; on 2 CPU cores villin renders at about 40k pixels); 0 turns
    the budget off."""
    refine_budget_ms: float = 250.0
    """Render time of the refined image that follows once a reduced image stays unchanged."""
    refine_after_s: float = 0.3
    """How long a budget-reduced image must stay unchanged before it is refined."""
    final_after_s: float = 1.5
    """How long a refined image must stay unchanged before the full-size image follows."""
    final_budget_ms: float = 5000.0
    """Render time the full-size image may take: a larger one is shrunk to what renders in it
    (the Screenshot button and REST renders still give the full size). Whatever it cost, a
    final image of the geodesic density at crease rounding 2 held the render for 53 s on two
    CPU cores, and every change waited behind it; 0 turns the budget off."""
    frame_wait_s: float = 0.25
    """Longest a simulation's next big frame (over 1 MiB) waits to be read until a render took
    the last one."""
    default_size: tuple[int, int] = (640, 480)
    cpu_max_live_pixels: int = 960 * 540
    """Largest live image rendered on the CPU device (about half a second there on 2 cores);
    bigger canvases get a smaller image, scaled up by the browser."""
    cpu_max_rest_pixels: int = 1920 * 1080
    """Largest `/api/render` image on the CPU device."""
    one_off_render_seconds: float = 60.0
    """Most device seconds one `/api/render` image may take, judged from its first bands of
    rows (`server.pipeline.bands`); past it the render is refused, naming the estimate."""
    encode_workers: int = field(default_factory=default_encode_workers)
    """Threads that encode images; also how many encodes the renderer keeps in flight."""
    render_defaults: RenderParams = field(default_factory=RenderParams)
    stats_interval_s: float = 1.0
    state_interval_s: float = 0.1
    hello_timeout_s: float = 10.0
    ws_ping_s: float = 20.0
    """WebSocket keep-alive: a ping this often, and a connection whose peer does not answer one
    within as long is closed."""
    ws_stall_s: float = 30.0
    """A WebSocket closed, or unable to write, this long because its peer reads nothing is cut
    (`transport.guarded_protocol`)."""
    header_timeout_s: float = 10.0
    """Time a connection has for a request's headers, from its opening (or its first byte
    after the last response): one that sent part of them is answered 408, one that sent
    nothing is closed."""
    trusted_proxies: tuple[str, ...] = ()
    """Addresses of reverse proxies whose `X-Forwarded-For` names the client; empty: no one's
    is believed, so a client cannot pick the address its rate limits and budgets follow."""
    client_dir: Path = Path(__file__).resolve().parents[1] / "client_web"

    @property
    def spool_dir(self) -> Path:
        """Where uploads wait while they are parsed and compressed files are inflated to be
        read: the server's own, never the system's temporary directory."""
        return self.state_dir / "spool"

    def read_limits(self, role: str = "steerer") -> ReadLimits:
        """What reading one untrusted file may cost, for a holder of `role`'s token."""
        viewer = role == "viewer"
        timeout = self.viewer_read_timeout_s if viewer else self.read_timeout_s
        return ReadLimits(
            max_atoms=min(self.limits.max_atoms, self.viewer_max_atoms)
            if viewer
            else self.limits.max_atoms,
            max_file_bytes=min(self.max_file_bytes, self.viewer_max_file_bytes)
            if viewer
            else self.max_file_bytes,
            memory_bytes=self.read_memory_bytes,
            open_s=timeout,
            frame_s=timeout / 4,
        )

    def spooled_read_limits(self, role: str = "steerer") -> ReadLimits:
        """`read_limits` for the server, whose compressed files inflate into its spool (the
        command-line tools read the user's own files, in the system's temporary directory)."""
        return replace(self.read_limits(role), scratch_dir=str(self.spool_dir))

    def selection_limits(self) -> PoolLimits:
        """What evaluating selections may cost, for everyone alike (viewers and steerers,
        sessions, REST renders and jobs)."""
        return PoolLimits(
            selection=SelectionLimits(
                max_chars=self.selection_max_chars,
                max_depth=self.selection_max_depth,
                max_pairs=self.selection_max_pairs,
            ),
            workers=self.selection_workers,
            timeout_s=self.selection_timeout_s,
            owner_seconds_per_min=self.selection_seconds_per_min,
            memory_bytes=self.selection_memory_bytes,
            max_atoms=self.limits.max_atoms,
        )

    def __post_init__(self) -> None:
        if self.open_on_loopback and not is_loopback(self.host):
            raise ValueError("--no-token-on-loopback-only needs a loopback --host")
        if self.token is None and not self.open_on_loopback:
            raise ValueError("a token is required unless the server is open on loopback only")
        if self.device_atoms is not None and self.device_atoms < 1:
            raise ValueError("--device-atoms must be at least 1")
        if self.encode_workers < 1:
            raise ValueError("--encode-workers must be at least 1")
        if self.max_spool_bytes < self.max_upload_bytes:
            raise ValueError(
                f"max_spool_bytes ({self.max_spool_bytes}) must be at least max_upload_bytes "
                f"({self.max_upload_bytes}): a whole upload must fit in the spool"
            )
        if not self.body_timeout_s > 0:
            raise ValueError("body_timeout_s must be more than 0 seconds")
        if not 0 < self.close_wait_s < float("inf"):
            raise ValueError("close_wait_s must be a finite number of seconds above 0")
        for name in ("ws_ping_s", "ws_stall_s"):
            if not 0 < getattr(self, name) < float("inf"):
                raise ValueError(f"{name} must be a finite number of seconds above 0")
        if self.viewer_views_per_pass < 1:
            raise ValueError("viewer_views_per_pass must be at least 1")
        if not 0 <= self.steerer_places < self.max_clients_per_session:
            raise ValueError(
                "steerer_places must be at least 0 and less than max_clients_per_session"
            )
        if self.selection_workers < 1:
            raise ValueError("selection_workers must be at least 1")
        if self.warm_up_render not in (0, 1):
            raise ValueError("warm_up_render must be 0 or 1")
        if not 0 <= self.selection_prestart <= self.selection_workers:
            raise ValueError("selection_prestart must be between 0 and selection_workers")
        if not self.video_steer_hold_s >= 0:
            raise ValueError("video_steer_hold_s must be 0 or more seconds")
        if self.data_dir is not None and not self.data_dir.is_dir():
            raise ValueError(f"--data-dir {self.data_dir} is not a directory")
