"""`scalesteer serve`: run the render server under uvicorn and print the dashboard URL."""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from server.settings import ServerSettings, is_loopback, persistent_tokens, ray_cluster_address
from server.threads import name_thread


def build_parser(prog: str = "scalesteer serve") -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=prog, description="Run the scalesteer render server.")
    ap.add_argument("--host", default="127.0.0.1", help="bind address (default: loopback only)")
    ap.add_argument("--port", type=int, default=8000)
    ap.add_argument("--device", default="auto", help="auto | cpu | cuda:N")
    auth = ap.add_mutually_exclusive_group()
    auth.add_argument(
        "--token",
        help="server token (default: a random one, kept in <state-dir>/tokens.json so links "
        "survive restarts; printed)",
    )
    auth.add_argument(
        "--no-token-on-loopback-only",
        action="store_true",
        help="no token needed; only allowed when bound to a loopback address",
    )
    ap.add_argument(
        "--viewer-token",
        help="read-only token (default: a random one kept in the state directory, printed)",
    )
    ap.add_argument(
        "--new-tokens",
        action="store_true",
        help="draw new random tokens (old links stop working)",
    )
    ap.add_argument(
        "--data-dir", type=Path, help="directory of server-side datasets for the REST API"
    )
    ap.add_argument(
        "--state-dir", type=Path, default=Path(".scalesteer"), help="steering logs, job outputs"
    )
    ap.add_argument(
        "--allow-origin", action="append", default=[], help="extra WebSocket Origin to accept"
    )
    ap.add_argument(
        "--trusted-proxy",
        action="append",
        default=[],
        help="address of a reverse proxy whose X-Forwarded-For names the client (repeat for "
        "several; none by default: a client's address is its connection's)",
    )
    ap.add_argument(
        "--encode-workers",
        type=int,
        default=None,
        help="image encoder threads (default: one per core, at most 8)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="any numeric server setting, e.g. --set max_connections=256 (a wrong name is "
        "refused with the list of names; what each limits: docs/server.md, Limits)",
    )
    ap.add_argument(
        "--gpus",
        help="render each session's images across several devices: all | 0,1,... | "
        "cuda:0,cuda:1 | cpu,cpu (two CPU devices, to try it without GPUs) "
        "(sort-first bands, or slabs of space for a system one device does not hold; "
        "docs/rendering.md)",
    )
    ap.add_argument(
        "--device-atoms",
        type=int,
        default=None,
        help="atoms one device's renderer holds (default: the largest system a frame may "
        "carry); with --gpus, a lone session's larger system is split across the devices",
    )
    ap.add_argument(
        "--batch-engine",
        choices=["auto", "ray", "local"],
        default="auto",
        help="where trajectory jobs render: auto: on Ray when a cluster is configured "
        "(--ray-address; jobs of ray_min_frames frames or more), else here; ray: on Ray always "
        "(without --ray-address, a token-authenticated instance of this server's own); local: "
        "here",
    )
    ap.add_argument(
        "--ray-address",
        default=ray_cluster_address(),
        help="a Ray cluster to join, e.g. HOST:6379 (env SCALESTEER_RAY_ADDRESS or RAY_ADDRESS; "
        "RAY_AUTH_TOKEN, when set, authenticates)",
    )
    ap.add_argument("--ray-workers", type=int, help="Ray render actors at most")
    ap.add_argument(
        "--video-codecs",
        default="h264,av1,vp9,h264-baseline",
        help="video codecs streamed to browsers that decode them, best first "
        "(h264, av1, vp9, h264-baseline); 'none': JPEG images only",
    )
    ap.add_argument("--log-level", default="info")
    return ap


def tunable_limits() -> dict[str, type]:
    """The numeric settings `--set` may change: ints and floats of `ServerSettings`."""
    import dataclasses

    kinds = {"int": int, "float": float}
    return {
        f.name: kinds[str(f.type)]
        for f in dataclasses.fields(ServerSettings)
        if str(f.type) in kinds and f.name != "port"
    }


MAY_BE_ZERO = frozenset({"warm_up_render", "selection_prestart"})
"""Settings `--set` may turn off with 0 (every other must be positive)."""


def _overrides(pairs: list[str]) -> dict[str, object]:
    tunable = tunable_limits()
    out: dict[str, object] = {}
    for pair in pairs:
        name, eq, raw = pair.partition("=")
        name = name.strip().replace("-", "_")
        if not eq or name not in tunable:
            raise ValueError(
                f"--set {pair!r}: expected NAME=VALUE with NAME one of {', '.join(sorted(tunable))}"
            )
        try:
            value = tunable[name](raw)
        except ValueError:
            kind = "an integer" if tunable[name] is int else "a number"
            raise ValueError(f"--set {name}: {raw!r} is not {kind}") from None
        if value < 0 or (value == 0 and name not in MAY_BE_ZERO):
            least = "0 or more" if name in MAY_BE_ZERO else "positive"
            raise ValueError(f"--set {name}: must be {least}, got {raw}")
        out[name] = value
    return out


def video_codecs(text: str) -> tuple[str, ...]:
    """`--video-codecs`: a comma-separated list of known codecs, or 'none'."""
    from server.pipeline.video import CANDIDATES

    if text.strip().lower() in ("", "none"):
        return ()
    codecs = tuple(c.strip() for c in text.split(",") if c.strip())
    unknown = [c for c in codecs if c not in CANDIDATES]
    if unknown:
        raise ValueError(
            f"--video-codecs: unknown {', '.join(unknown)}; known: {', '.join(CANDIDATES)}"
        )
    return codecs


def settings_from(args: argparse.Namespace) -> ServerSettings:
    kwargs: dict[str, object] = {
        "host": args.host,
        "port": args.port,
        "device": args.device,
        "open_on_loopback": args.no_token_on_loopback_only,
        "data_dir": args.data_dir,
        "state_dir": args.state_dir,
        "allowed_origins": tuple(args.allow_origin),
        "trusted_proxies": tuple(args.trusted_proxy),
    }
    saved_token, saved_viewer = persistent_tokens(args.state_dir, renew=args.new_tokens)
    kwargs["token"] = args.token or saved_token
    kwargs["viewer_token"] = args.viewer_token or saved_viewer
    if args.no_token_on_loopback_only:
        kwargs["token"] = None
        kwargs["viewer_token"] = None
    if args.encode_workers is not None:
        kwargs["encode_workers"] = args.encode_workers
    kwargs["gpus"] = args.gpus
    if args.device_atoms is not None:
        kwargs["device_atoms"] = args.device_atoms
    kwargs["batch_engine"] = args.batch_engine
    kwargs["ray_address"] = args.ray_address or None
    kwargs["ray_workers"] = args.ray_workers
    kwargs["video_codecs"] = video_codecs(args.video_codecs)
    kwargs.update(_overrides(args.set))
    return ServerSettings(**kwargs)  # type: ignore[arg-type]


def dashboard_urls(settings: ServerSettings, session: str | None = None) -> tuple[str, str | None]:
    host = "127.0.0.1" if settings.host in ("0.0.0.0", "::") else settings.host
    base = f"http://{host}:{settings.port}/"
    query = f"?session={session}" if session else ""
    join = "&" if query else "?"
    steer = base + query + (f"{join}token={settings.token}" if settings.token else "")
    view = (
        base + query + f"{join}role=viewer&token={settings.viewer_token}"
        if settings.viewer_token
        else None
    )
    return steer, view


def _config(settings: ServerSettings, log_level: str, app: Any = None) -> Any:
    import uvicorn

    from server.web import accesslog
    from server.web.app import create_app
    from server.web.transport import MAX_HEAD_BYTES, guarded_http, guarded_protocol

    config = uvicorn.Config(
        app if app is not None else create_app(settings),
        host=settings.host,
        port=settings.port,
        log_level=log_level,
        # h11 (uvicorn's own parser), with a deadline for a request's headers and a size limit
        http=guarded_http(settings.header_timeout_s),
        h11_max_incomplete_event_size=MAX_HEAD_BYTES,
        # websockets' sans-I/O protocol: of uvicorn's WebSocket implementations it takes the
        # least CPU per 12 MB frame (the legacy one is deprecated and no faster; wsproto ~2.5x);
        # its message limit is the viewers' until a simulation's hello is accepted
        ws=guarded_protocol(settings.viewer_limits.max_message_bytes, settings.ws_stall_s),
        ws_max_size=settings.limits.max_message_bytes,
        ws_ping_interval=settings.ws_ping_s,
        ws_ping_timeout=settings.ws_ping_s,
        # frames are raw floats and images are JPEG: deflate costs CPU and saves nothing
        ws_per_message_deflate=False,
        # a client's address is the socket's unless a configured proxy forwards it: rate limits
        # and budgets follow it (uvicorn would believe any loopback client's X-Forwarded-For)
        proxy_headers=bool(settings.trusted_proxies),
        forwarded_allow_ips=",".join(settings.trusted_proxies) or None,
        lifespan="on",
        # a shutdown never waits on a client for more than this (open dashboards included)
        timeout_graceful_shutdown=5,
    )
    accesslog.install((settings.token, settings.viewer_token))  # after uvicorn's logging set-up
    return config


def run(settings: ServerSettings, log_level: str = "info") -> None:
    """Serve until stopped. A render still running on a device once the app has closed
    (recordings, jobs and sessions first) would keep the process alive until it ends, minutes
    for the largest: the process then exits without it."""
    import uvicorn

    from server.web.app import create_app

    app = create_app(settings)
    try:
        # a SIGTERM is raised again once the app has closed, and ends the process there
        uvicorn.Server(_config(settings, log_level, app)).run()
    except KeyboardInterrupt:
        _exit_if_busy(app, 130)
        raise
    _exit_if_busy(app, 0)


def _exit_if_busy(app: Any, code: int) -> None:
    """End the process now when a device's thread is still rendering (left by
    `GpuQueue.close`, or by a stop that failed before it): the interpreter's exit would wait
    for that thread. Exit handlers are skipped: the app has closed what holds data
    (recordings, jobs, the steering log), and a spare file-reading child ends when its socket
    closes."""
    state = getattr(app.state, "scalesteer", None)
    if state is not None and any(r["busy_s"] > 0 for r in state.gpu.busy()):
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


class ServerThread:
    """The server running in a background thread (the demo, tests); port 0 picks a free one."""

    def __init__(self, settings: ServerSettings, log_level: str = "warning") -> None:
        import uvicorn

        from server.web.app import create_app

        self._app = create_app(settings)
        self._server = uvicorn.Server(_config(settings, log_level, self._app))
        self._thread = threading.Thread(target=self._run, name="uvicorn", daemon=True)
        try:
            self._thread.start()
            deadline = time.monotonic() + 60
            while not self._server.started:
                if not self._thread.is_alive() or time.monotonic() > deadline:
                    raise RuntimeError(
                        f"the server did not start on {settings.host}:{settings.port}"
                    )
                time.sleep(0.02)
            self.port: int = self._server.servers[0].sockets[0].getsockname()[1]
            self.settings = replace(settings, port=self.port)
        except BaseException:
            # Interrupted or failed while starting: the half-started server must not outlive
            # us, and its lifespan (jobs, recordings) closes as on a normal stop.
            self._server.should_exit = True
            if self._thread.is_alive():
                self._thread.join(timeout=30)
            raise

    def _run(self) -> None:
        name_thread()
        self._server.run()

    @property
    def app_state(self) -> Any:
        return self._app.state.scalesteer

    def stop(self, timeout: float | None = None) -> None:
        """Stop and wait: by default as long as the server's own stop may take (5 s for open
        requests, `close_wait_s` for the devices, and time to close the rest)."""
        self._server.should_exit = True
        if timeout is None:
            timeout = 5.0 + self.settings.close_wait_s + 15.0
        self._thread.join(timeout=timeout)
        if self._thread.is_alive():
            raise RuntimeError("the server did not stop")

    def exit_if_busy(self, code: int) -> None:
        """After `stop`: end the process now when a device is still rendering, as `run` does
        (the interpreter's exit would wait for that render: minutes for the largest)."""
        _exit_if_busy(self._app, code)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        settings = settings_from(args)
    except ValueError as exc:
        print(f"scalesteer serve: {exc}", file=sys.stderr)
        return 2
    from server.commands.render import device_refusal

    # before the server starts: the reason alone, not under its start-up traceback (`--device
    # gpu7` had served, and failed every render)
    if (refusal := device_refusal(settings.device)) is not None:
        print(f"scalesteer serve: {refusal}", file=sys.stderr)
        return 2
    if settings.gpus:
        from server.render.device import resolve_many
        from server.render.errors import RenderError

        try:
            resolve_many(settings.gpus)
        except RenderError as exc:
            print(f"scalesteer serve: --gpus {settings.gpus}: {exc}", file=sys.stderr)
            return 2
    logging.basicConfig(
        level=args.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s"
    )
    steer, view = dashboard_urls(settings)
    if not is_loopback(settings.host):
        print(
            "warning: listening beyond loopback; anyone with the token can steer", file=sys.stderr
        )
    print(f"\n  scalesteer dashboard:  {steer}")
    if view:
        print(f"  read-only viewer link: {view}")
    print()
    try:
        run(settings, args.log_level)
    except KeyboardInterrupt:  # Ctrl-C: uvicorn has shut down; its re-raised signal ends here
        return 130
    return 0
