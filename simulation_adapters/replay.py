"""`scalesteer replay`: play a trajectory file to a render server as if it were a live run.

    scalesteer replay adk.psf adk.dcd --fps 30 --loop --url ws://127.0.0.1:8000/ws/sim

Files are read with MDAnalysis (PDB and multi-model PDB, PSF/DCD, GRO/XTC/TRR, mmCIF, LAMMPS
data, ...); bonds are guessed when the topology has none. The dashboard steers the playback:
pause/resume, seek, step (while paused), speed, loop, reset (= seek 0) and stop; `frame_interval`
sets the stride. Each frame's `step` is its index in the trajectory. Replay is lossless by default
(a slow server slows the playback instead of skipping frames); `--drop-frames` makes it latest-wins.
"""

from __future__ import annotations

import argparse
import functools
import logging
import os
import re
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from protocol import (
    Control,
    EngineInfo,
    Event,
    Frame,
    Message,
    ParamRange,
    Playback,
    SimParams,
    WireArray,
)
from simulation_adapters.cli_support import add_retry, configure_logging, parse
from simulation_adapters.connection import ConnectionState, SimulationConnection
from structures.errors import StructureError
from structures.reader import Structure, load

log = logging.getLogger("scalesteer.replay")


class ReplayError(RuntimeError):
    """Playback cannot go on (the server refused the connection for good)."""


class TrajectoryReplay:
    """Plays a `Structure`'s frames at `fps` (times `speed`) and obeys the steering.

    `run()` plays in the calling thread until stopped (or, with `exit_at_end`, until the last
    frame has been sent); `start()` plays on a background thread; `close()` stops and joins.
    """

    def __init__(
        self,
        structure: Structure,
        url: str,
        token: str | None = None,
        session: str = "default",
        *,
        fps: float = 30.0,
        loop: bool = False,
        lossless: bool = True,
        start_paused: bool = False,
        exit_at_end: bool = False,
        takeover: bool = False,
        give_up_after: float | None = None,
    ) -> None:
        if not fps > 0:
            raise ValueError("fps must be positive")
        self.structure = structure
        self.n_frames = structure.n_frames
        self.fps = float(fps)
        self.speed = 1.0
        self.loop = loop
        self.stride = 1
        self.paused = start_paused
        self.exit_at_end = exit_at_end
        self.index = 0  # the next frame to send
        self.shown: int | None = None  # the last frame sent
        self.frames_sent = 0
        self.error: Exception | None = None
        self._budget = 1 if start_paused else 0  # a paused start shows its first frame
        self._stopped = False
        self._cond = threading.Condition()
        self._wakeups = 0
        self._thread: threading.Thread | None = None
        self.connection = SimulationConnection(
            url,
            token=token,
            session=session,
            client="scalesteer-replay",
            lossless=lossless,
            on_steer=self._on_steer,
            on_state=self._on_connection,
            takeover=takeover,
            give_up_after=give_up_after,
        )

    # ------------------------------------------------------------------ lifecycle

    def run(self) -> None:
        """Play until stopped (a `stop` control, `close()`, or the end with `exit_at_end`)."""
        self.connection.start()
        self.connection.send_topology(self.structure.topology)
        self.connection.send_engine(self.engine_info())
        if self.paused:
            self.connection.send_event(
                Event(level="info", code="paused", message="the replay starts paused", step=0)
            )
        try:
            self._play()
        finally:
            self.connection.close()

    def start(self, daemon: bool = False) -> TrajectoryReplay:
        """Play on a background thread; an error that ends it is kept in `error`. `daemon`:
        the thread does not keep the process alive (a script that showed a trajectory ends
        when its last line has run)."""

        def target() -> None:
            try:
                self.run()
            except Exception as exc:
                log.error("scalesteer replay stopped: %s", exc)
                self.error = exc

        self._thread = threading.Thread(target=target, name="scalesteer-replay", daemon=daemon)
        self._thread.start()
        return self

    def wait(self, timeout: float | None = None) -> bool:
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    def close(self, timeout: float = 10.0) -> None:
        with self._cond:
            self._stopped = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join(timeout)
        self.connection.close()

    def __enter__(self) -> TrajectoryReplay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ playback

    def _play(self) -> None:
        next_due = time.monotonic()
        while True:
            # the wake-ups are counted before the queue is read: steering that lands after
            # the read (and wakes no one yet) then ends the wait below at once
            with self._cond:
                seen = self._wakeups
            self._apply(self.connection.poll_steering())
            with self._cond:
                if self._stopped:
                    return
                if self.connection.state is ConnectionState.FAILED:
                    raise ReplayError(f"render server: {self.connection.error}")
                at_end = self.index >= self.n_frames
                if at_end and self.loop:
                    self.index, at_end = 0, False
                finished = at_end and self.exit_at_end and not self.paused
                # the last frame shown, not looping: the replay pauses there (a player at its
                # end is not playing), and says so; resume plays it again from the start
                ended = at_end and not finished and not self.paused
                if ended:
                    self.paused, self._budget = True, 0
                waiting = at_end or (self.paused and self._budget == 0)
            if finished:  # outside the lock: closing reports states that take it
                self._flush()
                return
            if ended:
                self.connection.send_event(
                    Event(
                        level="info",
                        code="paused",
                        message="the replay reached its last frame; resume plays it again",
                        step=self.shown if self.shown is not None else self.n_frames - 1,
                    )
                )
            if waiting:
                with self._cond:
                    self._cond.wait_for(functools.partial(self._woken, seen))
                next_due = time.monotonic()
                continue
            delay = next_due - time.monotonic()
            if delay > 0:
                with self._cond:
                    woken = self._cond.wait_for(functools.partial(self._woken, seen), delay)
                if woken:
                    continue  # steering arrived: apply it before sending
            self._send(self.index)
            with self._cond:
                if self.paused and self._budget > 0:
                    self._budget -= 1
                self.index += self.stride
            period = 1.0 / (self.fps * self.speed)
            next_due = max(next_due + period, time.monotonic() - period)

    def _send(self, index: int) -> None:
        ts = self.structure.universe.trajectory[index]
        pos = np.ascontiguousarray(ts.positions, dtype=np.float32)
        box = None
        boxed = ts.dimensions is not None and np.all(np.asarray(ts.dimensions[:3]) > 0)
        if boxed and not self.structure.crystal:  # a crystal's unit cell is no box
            box = WireArray.from_numpy(ts.triclinic_dimensions, "<f4")
        if not np.isfinite(pos).all():
            log.error("frame %d has non-finite coordinates; skipped", index)
            return
        time_ps = _time_ps(ts)
        frame = Frame(
            step=int(index),
            time_ps=time_ps,
            positions=WireArray.from_numpy(pos, "<f4"),
            box=box,
        )
        while not self.connection.send_frame(frame, timeout=0.5):
            with self._cond:
                if self._stopped or self.connection.state is ConnectionState.FAILED:
                    return
        self.shown = index
        self.frames_sent += 1

    def _flush(self) -> None:
        """Let queued lossless frames go out before returning at the end."""
        self.connection.close(timeout=10.0)

    # ------------------------------------------------------------------ steering

    def _woken(self, seen: int) -> bool:
        return self._wakeups != seen or self._stopped

    def _on_connection(self, _state: ConnectionState) -> None:  # connection I/O thread
        with self._cond:  # a failed connection must wake a replay idling at its end
            self._wakeups += 1
            self._cond.notify_all()

    def _on_steer(self, _msg: Message) -> None:  # connection I/O thread
        with self._cond:
            self._wakeups += 1
            self._cond.notify_all()

    def engine_info(self) -> EngineInfo:
        """A replay steers its playback, not physics: what the dashboard may offer."""
        recorded = "a recorded trajectory"
        return EngineInfo(
            name=f"replay of {self.structure.topology.title or 'a trajectory'}"[:128],
            kind="replay",
            controls=["pause", "resume", "step", "seek", "speed", "loop", "reset", "stop"],
            params={
                "frame_interval": ParamRange(
                    min=1, max=max(1, self.n_frames), unit="frames", recommended=self.stride
                )
            },
            unavailable={
                "temperature_K": f"{recorded} has no thermostat",
                "timestep_fs": f"{recorded} has a fixed time step",
                "friction_per_ps": f"{recorded} has no friction",
                "pull": f"{recorded} cannot be pulled",
            },
            pull=None,
            n_frames=self.n_frames,
            playback=Playback(speed=self.speed, loop=self.loop),
        )

    def _apply(self, messages: list[Message]) -> None:
        for msg in messages:
            if isinstance(msg, Control):
                ok, applied, detail = self._control(msg)
                applied = {"action": msg.action, **applied}  # the server tracks pause by it
            elif isinstance(msg, SimParams):
                ok, applied, detail = self._params(msg)
            else:
                ok, applied, detail = False, {}, "a trajectory replay cannot be pulled"
            if ok and isinstance(msg, Control) and msg.action in ("speed", "loop"):
                # the engine a reconnect declares again says how it plays now; declared before
                # the ack, so an engine that follows an acknowledgement is never older than it
                self.connection.send_engine(self.engine_info())
            step = self.shown if self.shown is not None else self.index
            self.connection.ack(msg.seq, step, None, ok=ok, applied=applied, detail=detail)

    def _control(self, msg: Control) -> tuple[bool, dict[str, Any], str]:
        with self._cond:
            action = msg.action
            if action == "pause":
                self.paused, self._budget = True, 0
                return True, {"paused": True}, ""
            if action == "resume":
                self.paused, self._budget = False, 0
                if self.index >= self.n_frames:  # paused at the end: play it again
                    self.index = 0
                return True, {"paused": False}, ""
            if action == "step":
                if not self.paused:
                    return False, {}, "step applies only while paused"
                self._budget += msg.n_steps
                return True, {"frames": msg.n_steps}, ""
            if action in ("seek", "reset"):
                target = 0 if action == "reset" else int(msg.frame or 0)
                if target >= self.n_frames:
                    return False, {}, f"frame {target} out of range [0, {self.n_frames})"
                self.index = target
                if self.paused:
                    self._budget = max(self._budget, 1)  # show the frame sought
                return True, {"frame": target}, ""
            if action == "speed":
                assert msg.speed is not None
                self.speed = float(msg.speed)
                return True, {"speed": self.speed}, ""
            if action == "loop":
                self.loop = bool(msg.loop)
                return True, {"loop": self.loop}, ""
            if action == "stop":
                self._stopped = True
                return True, {"stopped": True}, ""
        return False, {}, f"unknown action {action!r}"

    def _params(self, msg: SimParams) -> tuple[bool, dict[str, Any], str]:
        applied: dict[str, Any] = {}
        if msg.frame_interval is not None:
            with self._cond:
                self.stride = int(msg.frame_interval)
            applied["stride"] = self.stride
        rest = [
            name
            for name in ("temperature_K", "timestep_fs", "friction_per_ps")
            if getattr(msg, name) is not None
        ] + sorted(msg.engine)
        detail = f"a replay cannot change {', '.join(rest)}" if rest else ""
        return not rest, applied, detail


def _time_ps(ts: Any) -> float:
    """A frame's time without asking the reader for a dt it may not have (PDB models have
    none; MDAnalysis would warn on every frame). No time information gives 0."""
    data = ts.data
    if "time" in data:
        value = float(data["time"])
    elif "dt" in data:
        value = float(ts.frame * data["dt"] + data.get("time_offset", 0.0))
    else:
        value = 0.0
    return value if np.isfinite(value) else 0.0


# ---------------------------------------------------------------------- command line


def session_for(path: str) -> str:
    """A session name of its own for a replayed file: replay-<file name>, so a replay never
    lands in another run's session by default."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", os.path.basename(path)).lstrip(".")
    return f"replay-{stem}"[:64]


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="scalesteer replay",
        description="Stream a trajectory to a scalesteer render server, steerable from the "
        "dashboard (play, pause, seek, speed, loop).",
    )
    ap.add_argument("topology", help="structure file: PDB, GRO, PSF, mmCIF, LAMMPS data, ...")
    ap.add_argument("trajectory", nargs="*", help="trajectory files: DCD, XTC, TRR, PDB, ...")
    ap.add_argument("--fps", type=float, default=30.0, help="frames per second (default 30)")
    ap.add_argument(
        "--url",
        default="ws://127.0.0.1:8000/ws/sim",
        help="render server: ws://HOST:PORT/ws/sim, or the dashboard link it prints",
    )
    ap.add_argument("--token", default=os.environ.get("SCALESTEER_TOKEN"), help="access token")
    ap.add_argument(
        "--session",
        default=None,
        help="session name on the server (default: replay-<topology file name>)",
    )
    ap.add_argument(
        "--takeover", action="store_true", help="replace the session's current simulation"
    )
    ap.add_argument("--loop", action="store_true", help="start again after the last frame")
    ap.add_argument("--paused", action="store_true", help="start paused at frame 0")
    ap.add_argument("--exit-at-end", action="store_true", help="exit after the last frame")
    ap.add_argument(
        "--drop-frames", action="store_true", help="latest wins when the server is slow"
    )
    ap.add_argument("--no-guess-bonds", action="store_true", help="do not guess missing bonds")
    add_retry(ap)
    ap.add_argument("-v", "--verbose", action="store_true")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    args = parse(build_parser(), argv)
    if isinstance(args, int):
        return args
    configure_logging(args.verbose)
    if not args.fps > 0:
        print("scalesteer replay: error: --fps must be positive", file=sys.stderr)
        return 2
    try:
        structure = load(args.topology, args.trajectory, guess_bonds=not args.no_guess_bonds)
        session = args.session or session_for(args.topology)
        replay = TrajectoryReplay(
            structure,
            args.url,
            args.token,
            session,
            fps=args.fps,
            loop=args.loop,
            lossless=not args.drop_frames,
            start_paused=args.paused,
            exit_at_end=args.exit_at_end,
            takeover=args.takeover,
            give_up_after=args.retry,
        )
    except (StructureError, ValueError) as exc:
        print(f"scalesteer replay: error: {exc}", file=sys.stderr)
        return 2
    print(
        f"scalesteer replay: {structure.topology.n_atoms} atoms, {structure.n_frames} frames "
        f"-> {args.url}, session {session!r} (open the dashboard with ?session={session})",
        file=sys.stderr,
    )
    try:
        replay.run()
    except ReplayError as exc:
        print(f"scalesteer replay: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        replay.close()
        return 130
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
