"""A scripted simulation for the browser tests: a small helix on /ws/sim that moves, reports
observables, obeys steering and acknowledges each change with the step it took effect at.

It stands in for a real adapter behind one fixture (`simulation` in conftest.py); anything that
connects to /ws/sim as role `simulation`, streams frames and acknowledges steering can replace it.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

import numpy as np
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

import protocol as p
from tests.server.peers import frame, molecule


@dataclass
class ScriptedSimulation:
    url: str
    token: str | None
    session: str = "default"
    n_atoms: int = 24
    frame_period_s: float = 0.1
    ack_delay_s: float = 0.4
    """Acks wait this long, so a dashboard has time to show "pending"."""
    steps_per_frame: int = 10
    received: list[p.Message] = field(default_factory=list)
    _thread: threading.Thread | None = None
    _stop: threading.Event = field(default_factory=threading.Event)
    _connected: threading.Event = field(default_factory=threading.Event)

    def start(self) -> ScriptedSimulation:
        self._stop.clear()
        self._connected.clear()
        self._thread = threading.Thread(target=self._run, name="scripted-sim", daemon=True)
        self._thread.start()
        if not self._connected.wait(30):
            raise RuntimeError("the scripted simulation could not join the server")
        return self

    def stop(self) -> None:
        """Disconnect, as if the simulation process died."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
            assert not self._thread.is_alive(), "the scripted simulation did not stop"
            self._thread = None

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _run(self) -> None:
        topo, base = molecule(self.n_atoms)
        rng = np.random.default_rng(1)
        step, temperature, target = 0, 300.0, 300.0
        paused = False
        acks: list[tuple[float, p.ParamsAck]] = []
        with connect(self.url, max_size=None, open_timeout=20) as ws:

            def send(message: p.Message) -> None:
                ws.send(p.encode(message))

            send(
                p.Hello(
                    role="simulation", token=self.token, client="scripted-sim", session=self.session
                )
            )
            welcome = p.decode(ws.recv(timeout=20))
            assert isinstance(welcome, p.Welcome), welcome
            send(topo)
            next_frame = 0.0
            try:
                while not self._stop.is_set():
                    now = time.monotonic()
                    if not paused and now >= next_frame:
                        next_frame = now + self.frame_period_s
                        step += self.steps_per_frame
                        temperature += 0.3 * (target - temperature) + rng.normal(0, 2.0)
                        wobble = 0.15 * np.sin(step / 50.0 + np.arange(self.n_atoms))[:, None]
                        send(
                            frame(
                                (base + wobble).astype(np.float32),
                                step,
                                temperature_K=float(temperature),
                                potential_kJmol=float(-850.0 + rng.normal(0, 5.0)),
                                kinetic_kJmol=float(0.0249 * temperature * self.n_atoms * 1.5),
                            )
                        )
                        self._connected.set()
                    for due, ack in [a for a in acks if a[0] <= now]:
                        acks.remove((due, ack))
                        send(ack.model_copy(update={"step": step, "time_ps": step * 0.002}))
                    try:
                        raw = ws.recv(timeout=0.02)
                    except TimeoutError:
                        continue
                    message = p.decode(raw, p.Limits(max_message_bytes=1 << 30))
                    self.received.append(message)
                    applied: dict[str, object] = {}
                    match message:
                        case p.SimParams():
                            applied = message.model_dump(exclude_none=True, exclude={"seq", "type"})
                            if message.temperature_K is not None:
                                target = message.temperature_K
                        case p.Control():
                            applied = {"action": message.action}
                            if message.action in ("pause", "resume"):
                                paused = message.action == "pause"
                            elif message.action == "step":
                                step += message.n_steps
                            elif message.action == "reset":
                                step, temperature = 0, 300.0
                        case p.Forces():
                            applied = {"forces": message.indices.count}
                        case _:
                            continue
                    if message.seq is not None:
                        ack = p.ParamsAck(ref=message.seq, applied=applied)
                        acks.append((time.monotonic() + self.ack_delay_s, ack))
            except ConnectionClosed:
                pass
