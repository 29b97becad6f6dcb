"""`scalesteer demo`: the render server and a live OpenMM villin simulation, wired together.

The villin headpiece (the structure shipped in the openmm package, water removed, implicit
solvent, Langevin dynamics) runs on CUDA when present, else on the CPU, in a process of its own
(`server.commands.villin`, started under the server's supervisor so that it ends with the
demo); the server renders on the GPU when warp finds one, else on warp's CPU device at a lower
default resolution.

On the CPU, the simulation leaves the renderer and the browser room (`server.commands.villin`
says how), and images go as JPEG, not video: they are small (what the frame budget affords),
and a video stream encodes each at the whole canvas's size.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import socket
import sys
import time
import traceback
import webbrowser
from dataclasses import dataclass, replace
from pathlib import Path

from protocol import RenderParams
from server.commands.serve import ServerThread, dashboard_urls
from server.session.session import Session
from server.settings import ServerSettings, persistent_tokens
from server.supervisor import Supervised

CPU_FRAME_BUDGET_MS = 60.0
"""The live image's render time on the CPU: a steer waits for the render under way, then its
own, so a shorter one answers sooner and shows more images a second, a little less sharp."""
READY_S = 300.0
"""How long the simulation may take to build its system and join the server."""


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
    ap.add_argument(
        "--interval",
        type=int,
        default=None,
        help="MD steps between frames, 2 fs each (default 50 on a GPU, 10 on the CPU)",
    )
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


def _announce(engine: str, n_atoms: int, settings: ServerSettings) -> str:
    """Print where the dashboard is and what runs; returns the steering link."""
    steer, view = dashboard_urls(settings)
    print(f"\n  scalesteer dashboard:  {steer}")
    if view:
        print(f"  read-only viewer link: {view}")
    print(f"  simulation: villin headpiece, {n_atoms} atoms, {engine}")
    print("  try: raise the temperature to 450-600 K and watch the motion grow; 300 K calms it")
    print("  Ctrl-C stops the demo\n", flush=True)
    return steer


@dataclass
class _Running:
    """What the demo has started so far: closed, last started first, however it stops."""

    server: ServerThread | None = None
    simulation: Supervised | None = None

    def close(self) -> None:
        if self.simulation is not None:
            self.simulation.stop()
        if self.server is not None:
            self.server.stop()


def _simulation_command(args: argparse.Namespace, settings: ServerSettings) -> list[str]:
    command = [sys.executable, "-m", "server.commands.villin", "--session", "default",
               "--url", f"ws://127.0.0.1:{settings.port}/ws/sim"]  # fmt: skip
    if settings.token:
        command += [f"--token={settings.token}"]  # a token may begin with "-"
    if args.platform:
        command += ["--platform", args.platform]
    if args.interval:
        command += ["--interval", str(args.interval)]
    return command


def _joined(running: _Running) -> int:
    """Wait for the simulation to join the server's default session; its atom count
    (RuntimeError when it ends first)."""
    assert running.server is not None and running.simulation is not None
    session: Session = running.server.app_state.sessions.get("default")
    deadline = time.monotonic() + READY_S
    while session.engine is None or session.topology is None:
        code = running.simulation.poll()
        if code is not None:
            raise RuntimeError(f"the simulation ended before it joined the server (exit {code})")
        if time.monotonic() > deadline:
            raise RuntimeError(f"the simulation did not join the server within {READY_S:g} s")
        time.sleep(0.1)
    return session.topology.n_atoms


def _run(args: argparse.Namespace, running: _Running) -> None:
    """Start the server, then the simulation in its own process (kept in `running` as soon
    as each exists), and run until the deadline, the dashboard's stop or an interrupt."""
    logging.basicConfig(level="WARNING", format="%(asctime)s %(name)s %(levelname)s %(message)s")
    gpu = args.device.startswith("cuda") or (args.device == "auto" and _has_cuda())
    settings = ServerSettings(
        host=args.host,
        port=args.port,
        device=args.device,
        state_dir=args.state_dir,
        default_size=(800, 600) if gpu else (400, 300),
        render_defaults=RenderParams(sigma_A=1.5, quality=1.0 if gpu else 0.45),
        # on the CPU the live images are small (the frame budget's): JPEG costs less than a
        # video stream encoded at the whole canvas's size, and answers a steer sooner
        video_codecs=ServerSettings.video_codecs if gpu else (),
        frame_budget_ms=ServerSettings.frame_budget_ms if gpu else CPU_FRAME_BUDGET_MS,
    )
    token, viewer_token = persistent_tokens(args.state_dir)
    settings = replace(settings, token=args.token or token, viewer_token=viewer_token)
    running.server = ServerThread(settings)
    settings = running.server.settings
    print("scalesteer demo: preparing the villin headpiece (implicit solvent)...", flush=True)
    # its warnings and errors reach this terminal; it ends with the demo, kill -9 included
    running.simulation = Supervised(_simulation_command(args, settings), output=None)
    n_atoms = _joined(running)
    from simulation_adapters.openmm_systems import choose_platform

    steer = _announce(f"OpenMM {choose_platform(args.platform).getName()}", n_atoms, settings)
    if not args.no_browser:
        with contextlib.suppress(Exception):
            webbrowser.open(steer)
    deadline = time.monotonic() + args.duration if args.duration > 0 else None
    while (code := running.simulation.poll()) is None:
        if deadline is not None and time.monotonic() >= deadline:
            return
        time.sleep(0.2)
    if code == 0:
        print("the dashboard stopped the simulation", file=sys.stderr)
    else:
        print(f"the simulation ended (exit {code}); stopping", file=sys.stderr)


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
    code = 0
    before = signal.signal(signal.SIGTERM, _stop_on_term)
    # One try from the handler on: a Ctrl-C or SIGTERM at any point of the start-up (the
    # imports, the system's build, the server's start) stops the demo in order too.
    try:
        _run(args, running)
    except KeyboardInterrupt:
        print("\nstopping...", file=sys.stderr)
    except RuntimeError as exc:
        print(f"scalesteer demo: {exc}", file=sys.stderr)
        code = 1
    except Exception:  # said here: the exit below may end the process before Python would
        traceback.print_exc()
        code = 1
    finally:
        # a second Ctrl-C or SIGTERM must not cut the closing short (the server's stop is
        # bounded): jobs and recordings close whole
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            running.close()
        except Exception:
            traceback.print_exc()
            code = 1
        finally:
            signal.signal(signal.SIGINT, previous)
            signal.signal(signal.SIGTERM, before)
        if running.server is not None:  # closed: a render still running is not waited for
            running.server.exit_if_busy(code)
    return code
