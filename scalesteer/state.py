"""What a client knows of a session: the server's `state` messages merged into one picture."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from protocol import (
    Camera,
    ClientInfo,
    EngineInfo,
    Legend,
    Pull,
    RenderParams,
    SimParams,
    SimStatus,
    State,
)


@dataclass(frozen=True)
class SessionState:
    """The shared state of a session as the server last described it.

    `render_params`: how the session draws (every field, layers included); `sim_params`: the
    simulation parameters the simulation confirmed; `sim`: its status and latest observables;
    `engine`: what it can be steered with (None before a simulation declared it); `camera`:
    the session's camera, which frames the molecule; `clients`: who is connected."""

    render_params: RenderParams = field(default_factory=RenderParams)
    sim_params: SimParams = field(default_factory=SimParams)
    sim: SimStatus = field(default_factory=SimStatus)
    engine: EngineInfo | None = None
    camera: Camera | None = None
    legend: Legend | None = None
    pulling: tuple[Pull, ...] = ()
    clients: tuple[ClientInfo, ...] = ()

    def merged(self, message: State) -> SessionState:
        """This state with the parts `message` changes (absent parts did not change)."""
        changes: dict[str, object] = {}
        for name in ("render_params", "sim_params", "sim", "engine", "camera", "legend"):
            value = getattr(message, name)
            if value is not None:
                changes[name] = value
        if message.pulling is not None:
            changes["pulling"] = tuple(message.pulling)
        clients = list(self.clients)
        if message.clients is not None:
            clients = list(message.clients)
        if message.left:
            gone = set(message.left)
            clients = [c for c in clients if c.client_id not in gone]
        if message.joined:
            known = {c.client_id for c in clients}
            clients += [c for c in message.joined if c.client_id not in known]
        if message.clients is not None or message.left or message.joined:
            changes["clients"] = tuple(clients)
        return replace(self, **changes) if changes else self  # type: ignore[arg-type]
