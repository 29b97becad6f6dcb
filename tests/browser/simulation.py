"""The simulation behind the browser tests: a real OpenMM run (villin headpiece, CPU platform)
driven through the real adapter, `SteeringReporter` + `run_steered`, on a background thread.

`stop()` disconnects it as if the process died; `start()` brings it back on the same system.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Any

from simulation_adapters.openmm_reporter import SteeringReporter, run_steered
from simulation_adapters.openmm_systems import build_villin_simulation

_VILLIN: list[Any] = []


def villin() -> Any:
    """One villin simulation for the whole browser suite (building it costs seconds)."""
    if not _VILLIN:
        _VILLIN.append(
            build_villin_simulation(
                platform="CPU", properties={"Threads": "1"}, minimize_iterations=100
            )
        )
    return _VILLIN[0]


@dataclass
class OpenMMSimulation:
    url: str
    token: str | None
    session: str = "default"
    interval: int = 10
    _simulation: Any = None
    _reporter: SteeringReporter | None = None
    _thread: threading.Thread | None = None
    _stop: threading.Event = field(default_factory=threading.Event)

    def start(self) -> OpenMMSimulation:
        if self._simulation is None:
            self._simulation = villin()
        self._stop.clear()
        reporter = SteeringReporter(
            self.url, token=self.token, interval=self.interval, session=self.session
        )
        self._simulation.reporters.append(reporter)
        self._reporter = reporter
        self._thread = threading.Thread(
            target=self._run, args=(reporter,), name="openmm", daemon=True
        )
        self._thread.start()
        deadline = time.monotonic() + 60
        while reporter.frames_reported == 0 or not reporter.connection.connected:
            if time.monotonic() > deadline:
                raise RuntimeError("the OpenMM simulation could not join the server")
            time.sleep(0.05)
        return self

    def _run(self, reporter: SteeringReporter) -> None:
        while not self._stop.is_set() and not reporter.stop_requested:
            run_steered(self._simulation, 50, reporter=reporter)

    def stop(self) -> None:
        """Disconnect, as if the simulation process died."""
        self._stop.set()
        if self._reporter is not None:
            self._reporter.close(timeout=5)
        if self._thread is not None:
            self._thread.join(timeout=30)
            assert not self._thread.is_alive(), "the OpenMM thread did not stop"
            self._thread = None
        if self._reporter is not None:
            self._simulation.reporters.remove(self._reporter)
            self._reporter = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()
