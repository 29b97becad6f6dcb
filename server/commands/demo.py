"""`scalesteer demo`: the render server and a live OpenMM villin simulation, wired together.

The villin headpiece (the structure shipped in the openmm package, water removed, implicit
solvent, Langevin dynamics) runs on CUDA when present, else on the CPU; the server renders on
the GPU when warp finds one, else on warp's CPU device at a lower default resolution.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import socket
import sys
import time
import webbrowser
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from protocol import RenderParams
from server.commands.serve import ServerThread, dashboard_urls
from server.settings import ServerSettings, persistent_tokens

if TYPE_CHECKING:
    from simulation_adapters.openmm_reporter import SteeringReporter


def _has_cuda() -> bool:
    from server.render.device import cuda_count

    return cuda_count() > 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="scalesteer demo", description=__doc__)
    ap.add_argument("--host", default="127.0.0.1")
    ap.add_argument(
        "--port",
        type=int,
        default=8000,
        help="0 picks a free port (with make: make demo PORT=8001)",
    )
    ap.add_argument("--device", default="auto", help="render device: auto | cpu | cuda:N")
    ap.add_argument(
        "--platform", default=None, help="OpenMM platform (default: CUDA if present, else CPU)"
    )
    ap.add_argument(
        "--token",
        default=None,
        help="server token (default: a random one kept in the state directory, printed)",
    )
    ap.add_argument("--interval", type=int, default=50, help="MD steps between frames (2 fs steps)")
    ap.add_argument(
        "--duration",
        type=float,
        default=0.0,
        help="stop after this many seconds (0: run until Ctrl-C)",
    )
    ap.add_argument("--no-browser", action="store_true", help="do not try to open the dashboard")
    ap.add_argument("--state-dir", type=Path, default=Path(".scalesteer"))
    return ap


def port_taken(host: str, port: int) -> bool:
    """Whether something listens on `host:port` already (the server would not start there);
    port 0 is never taken."""
    if port == 0:
        return False
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as uvicorn binds
        try:
            probe.bind((host, port))
        except OSError:
            return True
    return False


def _stop_on_term(signum: int, frame: object) -> None:
    """SIGTERM (`docker stop`, a process manager) stops the demo as Ctrl-C does."""
    raise KeyboardInterrupt


def _announce(simulation: Any, settings: ServerSettings) -> str:
    """Print where the dashboard is and what runs; returns the steering link."""
    steer, view = dashboard_urls(settings)
    platform = simulation.context.getPlatform().getName()
    print(f"\n  scalesteer dashboard:  {steer}")
    if view:
        print(f"  read-only viewer link: {view}")
    n_atoms = simulation.topology.getNumAtoms()
    print(f"  simulation: villin headpiece, {n_atoms} atoms, OpenMM {platform}")
    print("  try: raise the temperature to 450-600 K and watch the motion grow; 300 K calms it")
    print("  Ctrl-C stops the demo\n", flush=True)
    return steer


@dataclass
class _Running:
    """What the demo has started so far: closed, last started first, however it stops."""

    server: ServerThread | None = None
    reporter: SteeringReporter | None = None

    def close(self) -> None:
        if self.reporter is not None:
            self.reporter.close()
        if self.server is not None:
            self.server.stop()


def _run(args: argparse.Namespace, running: _Running) -> None:
    """Build the system, start the server and its reporter (kept in `running` as soon as
    each exists), and run until the deadline, the dashboard's stop or an interrupt."""
    logging.basicConfig(level="WARNING", format="%(asctime)s %(name)s %(levelname)s %(message)s")
    from simulation_adapters.openmm_reporter import SteeringReporter, run_steered
    from simulation_adapters.openmm_systems import build_villin_simulation

    gpu = args.device.startswith("cuda") or (args.device == "auto" and _has_cuda())
    settings = ServerSettings(
        host=args.host,
        port=args.port,
        device=args.device,
        state_dir=args.state_dir,
        default_size=(800, 600) if gpu else (400, 300),
        render_defaults=RenderParams(sigma_A=1.5, quality=1.0 if gpu else 0.45),
    )
    token, viewer_token = persistent_tokens(args.state_dir)
    settings = replace(settings, token=args.token or token, viewer_token=viewer_token)
    print("scalesteer demo: preparing the villin headpiece (implicit solvent)...", flush=True)
    simulation = build_villin_simulation(platform=args.platform)
    running.server = ServerThread(settings)
    settings = running.server.settings
    reporter = running.reporter = SteeringReporter(
        f"ws://127.0.0.1:{settings.port}/ws/sim",
        token=settings.token,
        interval=args.interval,
        session="default",
    )
    simulation.reporters.append(reporter)
    steer = _announce(simulation, settings)
    if not args.no_browser:
        with contextlib.suppress(Exception):
            webbrowser.open(steer)
    deadline = time.monotonic() + args.duration if args.duration > 0 else None
    while not reporter.stop_requested and (deadline is None or time.monotonic() < deadline):
        run_steered(simulation, args.interval * 10, reporter=reporter)
    if reporter.stop_requested:
        print("the dashboard stopped the simulation", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if port_taken(args.host, args.port):
        print(
            f"scalesteer demo: port {args.port} on {args.host} is in use (another demo or "
            f"server?); start on another one: make demo PORT={args.port + 1}, or scalesteer "
            f"demo --port {args.port + 1} (--port 0 picks a free one)",
            file=sys.stderr,
        )
        return 2
    running = _Running()
    before = signal.signal(signal.SIGTERM, _stop_on_term)
    # One try from the handler on: a Ctrl-C or SIGTERM at any point of the start-up (the
    # imports, the system's build, the server's start) stops the demo in order too.
    try:
        _run(args, running)
    except KeyboardInterrupt:
        print("\nstopping...", file=sys.stderr)
    finally:
        # a second Ctrl-C or SIGTERM must not cut the closing short (the server's stop is
        # bounded): jobs and recordings close whole
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            running.close()
        finally:
            signal.signal(signal.SIGINT, previous)
            signal.signal(signal.SIGTERM, before)
    return 0
