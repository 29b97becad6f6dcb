"""The demo's simulation, in a process of its own: villin in OpenMM, steered through a render
server's `/ws/sim` (`python -m server.commands.villin --url ws://... --token T`).

`scalesteer demo` starts it under the server's supervisor, so it ends with the demo. It is a
process apart from the server because OpenMM holds Python's interpreter lock while it steps:
in one process with the renderer the two took turns (on the 2-core test machine a thread
rendering villin drew 5.6 images a second beside a thread stepping it, 13.7 alone).

On the CPU platform it leaves the renderer and the browser room: half the cores (one of two)
and a lower priority (nice +2). It reports about `FRAMES_PER_S` frames a second, whatever its
speed: every so many steps, measured as it runs (at most every 50), so that the renderer always
has a newer frame to draw (a frame every 50 steps came 2-4 times a second on two cores, and the
page showed no more images than that). `--interval` fixes the steps, and so does a steerer's
`frame_interval`. It exits 0 when a steerer stops it.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
import sys
import time
from pathlib import Path

MAX_INTERVAL = 50
"""Steps between frames at most (0.1 ps at 2 fs): a fast engine's frames still show motion."""
MIN_INTERVAL = 3
"""Steps between frames at least: a report costs OpenMM one or two force evaluations (the
energies of the plots), as much as a step or two (every step, villin stepped 30 times a second
where it stepped 106 with a frame every 50)."""
FRAMES_PER_S = 12.0
"""Frames a second the simulation aims at: about what the CPU renderer draws (the demo's frame
budget there is 60 ms)."""
MD_NICE = 2
"""How much lower the simulation runs on the CPU than the server (the renderer, encoders, event
loop) and the browser: interaction first. Mildly: at +5 a busy machine left it a few steps a
second, and the molecule stood still while the page showed it."""
STOPPED = 0
"""Exit code when a steerer stopped the simulation (the demo then ends too)."""


def md_threads() -> int:
    """OpenMM's CPU threads: half the cores (one of two), the rest for rendering and the page."""
    return max(1, (os.cpu_count() or 2) // 2)


def lower_priority(by: int) -> None:
    """Run this process `by` lower, where the system lets it. Linux schedules each session as a
    group of its own (autogroups), and a process's nice value weighs only against the others of
    its group: this process leads a session of its own (the supervisor's), so its group's nice
    is raised too, else the server's group and this one would share the cores half and half."""
    with contextlib.suppress(OSError):
        os.nice(by)
    with contextlib.suppress(OSError, ValueError, IndexError):
        group = Path("/proc/self/autogroup")
        nice = int(group.read_text().split("nice")[1])
        group.write_text(str(min(19, nice + by)))


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m server.commands.villin", description=__doc__)
    ap.add_argument("--url", required=True, help="the server's /ws/sim, ws://HOST:PORT/ws/sim")
    ap.add_argument("--token", default=None, help="the server token")
    ap.add_argument("--session", default="default")
    ap.add_argument("--platform", default=None, help="OpenMM platform (default: the fastest)")
    ap.add_argument(
        "--interval",
        type=int,
        default=None,
        help=f"steps between frames (default: about {FRAMES_PER_S:g} frames a second, at most "
        f"every {MAX_INTERVAL} steps)",
    )
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(level="WARNING", format="%(asctime)s %(name)s %(levelname)s %(message)s")
    from simulation_adapters.openmm_reporter import SteeringReporter, run_steered
    from simulation_adapters.openmm_systems import build_villin_simulation, choose_platform

    on_cpu = choose_platform(args.platform).getName() == "CPU"
    properties = None
    if on_cpu:
        lower_priority(MD_NICE)
        properties = {"Threads": str(md_threads())}
    simulation = build_villin_simulation(platform=args.platform, properties=properties)
    interval = args.interval or (10 if on_cpu else MAX_INTERVAL)
    reporter = SteeringReporter(args.url, token=args.token, interval=interval, session=args.session)
    simulation.reporters.append(reporter)
    pace = Pace(interval) if args.interval is None else None
    try:
        while not reporter.stop_requested:
            started = time.monotonic()
            steps = run_steered(simulation, interval * 5, reporter=reporter)
            if pace is not None and reporter.interval != interval:
                pace = None  # a steerer chose the frame interval
            elif pace is not None:
                interval = reporter.interval = pace.after(steps, time.monotonic() - started)
    finally:
        reporter.close()
    return STOPPED


class Pace:
    """The steps between frames that give about `FRAMES_PER_S` frames a second, from the
    simulation's speed as it runs (a running mean, so that one slow stretch moves it little)."""

    def __init__(self, interval: int) -> None:
        self.interval = interval
        self.steps_per_s: float | None = None

    def after(self, steps: int, seconds: float) -> int:
        """The interval after `steps` took `seconds` (a pause or a stop among them, which say
        nothing of the speed, count for nothing)."""
        if steps >= 5 * self.interval and seconds > 0:
            rate = steps / seconds
            known = self.steps_per_s
            self.steps_per_s = rate if known is None else 0.7 * known + 0.3 * rate
            wanted = round(self.steps_per_s / FRAMES_PER_S)
            self.interval = max(MIN_INTERVAL, min(MAX_INTERVAL, wanted))
        return self.interval


if __name__ == "__main__":
    with contextlib.suppress(KeyboardInterrupt):
        sys.exit(main())
