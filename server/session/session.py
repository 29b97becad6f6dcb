"""A session: one simulation source, the molecule it sends, the shared render state and the
clients watching it. This class is the facade the WebSocket edge talks to; the work is done by

- `roster.Roster`: who is connected;
- `steering`: render-parameter patches, simulation parameters confirmed by the engine, acks;
- `forces.ForceBook`: pulls and script forces merged into the one set an engine applies;
- `render_loop.RenderLoop`: renders what is due each time the session changes;
- `scheduler.RenderScheduler`: when to render which view group, at which quality;
- `delivery.Delivery`: encoding and offering images to clients;
- a `services.RenderBackend` (the GPU queue) that draws.

All methods run on the event loop; selections are evaluated in worker processes
(`layers.LayerBook`), never on it.

Kept whole: the state every message reads and changes (topology, frame, render parameters, camera,
layers) lives on this one object, and each public method handles one kind of message with the
checks that need that state; the work itself is in the modules listed above.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable, Hashable
from concurrent.futures import Future
from typing import Any

import numpy as np
import numpy.typing as npt
from pydantic import ValidationError

import protocol as p
from protocol.fields import error_location
from server import heap
from server.pipeline.gpu import RenderRequest, Snapshot
from server.pipeline.periodic import (
    PERIODIC_FIELDS,
    PeriodicError,
    atoms_problem,
    check_periodic,
    displayed_cell,
    needs_display,
    selection_fields,
)
from server.render.boxes import Shown, usable_box
from server.render.layerplan import LayerPlan, visible_atoms
from server.session.clients import Client
from server.session.delivery import Delivery
from server.session.engine_limits import check_control, check_pull, check_sim_params
from server.session.forces import DisplayedAtoms, ForceBook, Positions
from server.session.layers import LayerBook
from server.session.periodic import PeriodicFrames
from server.session.render_loop import RenderLoop, Scene
from server.session.roster import Roster
from server.session.scheduler import RenderScheduler
from server.session.services import Services
from server.session.steering import (
    AckBook,
    Pending,
    apply_sim_params,
    merge_patch,
    sim_params_changes,
)
from server.session.steps import StepRate, StepRun
from server.settings import ServerSettings
from structures.selection import SelectionError, check_syntax, is_dynamic
from structures.selection_pool import SelectionBusyError

log = logging.getLogger("scalesteer.session")

FrameSink = Callable[[int, float, "npt.NDArray[np.float32]", "npt.NDArray[Any] | None"], None]
"""(step, time_ps, positions, box) of one frame."""


def _invalid(exc: ValidationError, path: str, seq: int | None) -> p.ProtocolError:
    loc, msg = error_location(exc.errors(include_url=False)[0])
    where = ".".join(loc)
    return p.ProtocolError(
        p.ErrorCode.INVALID_MESSAGE,
        f"{where}: {msg}" if where else msg,
        f"{path}.{where}" if where else path,
        seq,
    )


def _declared(engine: p.EngineInfo) -> p.EngineInfo:
    """What an engine declares, apart from the sequence number it came with."""
    return engine.model_copy(update={"seq": None})


class Session:
    """State and behaviour of one session."""

    def __init__(self, session_id: str, settings: ServerSettings, services: Services) -> None:
        self.id = session_id
        self.slot = f"session:{session_id}"  # its renderer on the GPU; ':' never occurs in a name
        self.settings = settings
        self.services = services
        self.created = time.time()
        self.idle_since: float | None = time.monotonic()
        """When the last client and the simulation left (None while anyone is connected)."""
        self.roster = Roster()
        self.topology: p.Topology | None = None
        self.legend: p.Legend | None = None
        self._legend_key: Any = None
        self._legend_plans: tuple[LayerPlan, ...] | None = None
        """The layers the legend was made for (it lists only the atoms they show)."""
        self.engine: p.EngineInfo | None = None
        """What the simulation declared it can be steered with (kept until a new one says)."""
        self.stopped_why: p.Event | None = None
        """Why the simulation stopped (`simulation_stopped`), told to every viewer who joins
        until another simulation connects."""
        self.topology_id = 0
        self.positions: npt.NDArray[np.float32] | None = None
        self.positions_id = 0
        self.box: npt.NDArray[np.float32] | None = None
        """The last frame's periodic box vectors (3x3, angstrom), if it sent any."""
        self.raw_positions: npt.NDArray[np.float32] | None = None
        """The last frame's positions as the simulation sent them (`positions` are the ones
        displayed: molecules whole, centred, fitted, as the render parameters say)."""
        self.shown: Shown | None = None
        """How `positions` were displayed (None: as sent)."""
        self._cell_sent: p.Cell | None = None
        self._arrived = StepRun()
        self.status = p.SimStatus(state="waiting")
        self.render_params = settings.render_defaults
        self.sim_params = p.SimParams()
        """What the simulation has confirmed (a change shows here once acknowledged)."""
        self.camera: p.Camera | None = None
        self.forces = ForceBook()
        self._history: deque[tuple[int, npt.NDArray[np.float32]]] = deque(maxlen=1)
        """The last frames (positions_id, positions) for temporal smoothing."""
        self._history_epoch = 0
        self._displayed = StepRun()
        self.frame_sinks: list[FrameSink] = []
        """Called with each frame as the simulation sent it (a recording keeps these)."""
        self.shown_sinks: list[Callable[[int], None]] = []
        """Called with a frame's step once it is displayed (`snapshot()` holds it then): a
        movie of the view takes these, after the periodic steps."""
        self.close_hooks: list[Callable[[], Awaitable[None]]] = []
        """Run (in order, each once) when the session closes: reaped, or the server stops.
        A recording hooks its stop here, so it never stays "recording" without a session."""
        """Called with every frame the simulation sends (recordings): they must only queue."""
        self.acks = AckBook()
        self.layers = LayerBook(self._selection_moved, services.selections)
        self.periodic = PeriodicFrames(self.slot, services.backend, self._publish)
        self.scheduler = RenderScheduler(settings)
        self.delivery = Delivery(session_id, services)
        self.version = 0
        """Counts every change to what the session draws (positions, render parameters)."""
        self._roster_flush: asyncio.TimerHandle | None = None
        self._status_flush: asyncio.TimerHandle | None = None
        self._step_rate = StepRate()
        self._closed = False
        self._last_state_sent = 0.0
        self._frame_taken = asyncio.Event()
        self._frame_taken.set()
        self.renders = RenderLoop(
            self, session_id, self.slot, settings, services, self.scheduler, self.delivery
        )
        self._tasks = [
            self.renders.start(),
            asyncio.create_task(self._stats_loop(), name=f"stats-{session_id}"),
        ]

    # ------------------------------------------------------------------ clients

    @property
    def sim(self) -> Client | None:
        return self.roster.sim

    @property
    def clients(self) -> dict[str, Client]:
        return self.roster.clients

    def attach(self, client: Client) -> None:
        self.idle_since = None
        replaced = self.roster.add(client)
        if replaced is not None:
            self._fail_pending("the simulation was replaced by a new connection")
            replaced.send(
                p.Error(
                    code=p.ErrorCode.FORBIDDEN, message="replaced by a new simulation connection"
                )
            )
            replaced.close_after_flush()
        if client.role != "simulation":
            client.needs_image = True
        self.services.metrics.clients.labels(client.role).inc()
        if replaced is not None:
            self.roster.note_leave(replaced)
        self.roster.note_join(client)
        self._roster_changed()
        # the newcomer gets the whole roster now (the coming delta repeats it, harmlessly)
        client.send(self.full_state())
        if client.role == "simulation":
            self.stopped_why = None
        elif self.stopped_why is not None and self.sim is None:
            client.send(self.stopped_why)
        self.mark_dirty()

    def simulation_stopped(self, event: p.Event) -> None:
        """Tell the viewers why the simulation stopped (a replay that failed), and each
        viewer who joins before another simulation connects."""
        self.stopped_why = event
        self.broadcast(event)

    def _roster_changed(self) -> None:
        """Send the roster's changes soon, coalesced over `state_interval_s`."""
        if self._roster_flush is None:
            self._roster_flush = asyncio.get_running_loop().call_later(
                self.settings.state_interval_s, self._flush_roster
            )

    def _flush_roster(self) -> None:
        self._roster_flush = None
        delta = self.roster.take_changes()
        if delta is not None:
            self.broadcast(delta)

    def detach(self, client: Client) -> None:
        self.services.metrics.clients.labels(client.role).dec()
        member = client is self.roster.sim or client.client_id in self.roster.clients
        if self.roster.remove(client):
            self.status = self.status.model_copy(
                update={"state": "disconnected", "steps_per_s": 0.0}
            )
            self._fail_pending("simulation disconnected")
            self.broadcast(p.State(sim=self.status))
        elif client.role != "simulation":
            self.delivery.leave(client)
            if not self.clients:
                self._frame_taken.set()
            if self.forces.drop_client(client.client_id):
                self._send_forces()
                self.broadcast(p.State(pulling=self.forces.pulling()))
        if member:  # a replaced simulation left the roster when it was replaced
            self.roster.note_leave(client)
            self._roster_changed()
        if self.roster.empty:
            self.idle_since = time.monotonic()

    def _fail_pending(self, why: str) -> None:
        """Steering forwarded to a simulation that is gone will never be acknowledged."""
        for pending in self.acks.take_all():
            self._settle(pending, p.ParamsAck(ref=0, ok=False, detail=why))

    def full_state(self) -> p.State:
        return p.State(
            render_params=self.render_params,
            sim_params=self.sim_params,
            sim=self.status,
            clients=self.roster.infos(),
            pulling=self.forces.pulling(),
            engine=self.engine,
            legend=self.legend,
            camera=self.camera,
            cell=self._cell(),
        )

    def broadcast(self, message: p.Message) -> None:
        self.roster.broadcast(message)

    # ------------------------------------------------------------------ simulation input

    def on_topology(self, topology: p.Topology) -> None:
        changed = self.topology is None or self.topology.n_atoms != topology.n_atoms
        self.topology = topology
        self.topology_id += 1
        if self.layers.auto:
            self._default_layers(topology)
        self.layers.topology(topology, self.topology_id, prepare=bool(self.render_params.layers))
        self.periodic.held = self.layers.held
        if changed:
            self.positions = None
            self.raw_positions = None
            self.shown = None
            self.camera = None
            self.forces.clear()
            self._history.clear()  # frames of another system: the window starts again
            self._history_epoch += 1
            self._displayed.reset()
        # an adapter that said it starts paused (its events go out before its topology) stays so
        state = "paused" if self.status.state == "paused" else "running"
        self.status = self.status.model_copy(
            update={"n_atoms": topology.n_atoms, "engine": topology.engine, "state": state}
        )
        self.broadcast(p.State(sim=self.status))
        self._legend_plans = None  # the last layers' atoms were of the last topology
        self._legend_changed()
        if topology.n_atoms >= heap.LARGE_TOPOLOGY:
            heap.settle()  # its per-atom lists leave the collector's walk (server.heap)

    def _default_layers(self, topology: p.Topology) -> None:
        """Open a system on what matters: solvent and ions hidden, a ligand at a finer scale
        (until a steerer sets layers of their own)."""
        try:
            layers = self.layers.defaults(topology, self.render_params.sigma_A)
        except Exception:
            log.exception("default layers of session %s", self.id)
            return
        if layers == self.render_params.layers:
            return
        self.render_params = self.render_params.model_copy(update={"layers": layers})
        self.broadcast(p.State(render_params=self.render_params))
        self.version += 1

    def _selection_moved(self) -> None:
        """A layer selection's atoms arrived from the worker, or a distance-based one took in
        or let go of atoms."""
        if self.camera is None:
            self._fit_camera()
        self.version += 1
        self.mark_dirty()

    def _fit_camera(self) -> None:
        """Frame what the layers show (once their selections are ready)."""
        if self.positions is None or self.topology is None:
            return
        n = self.topology.n_atoms
        plans = self.layers.plans(
            self.render_params, n, self._selected_positions(), self.positions_id, self.box
        )
        if not self.layers.ready:
            return  # once the layers' atoms arrive (`_selection_moved`)
        from server.render.camera import fit_camera

        shown = visible_atoms(plans, n)
        w, h = self.settings.default_size
        self.camera = fit_camera(self.positions[shown] if len(shown) else self.positions, w, h)
        self.broadcast(p.State(camera=self.camera))

    def _layer_plans(self, snap: Snapshot) -> tuple[LayerPlan, ...] | None:
        return self.layers.plans(
            self.render_params, snap.topology.n_atoms, self._selected_positions(),
            snap.positions_id, self.box,
        )  # fmt: skip

    def _selected_positions(self) -> npt.NDArray[np.float32] | None:
        """The positions selections read (`around`, `point`): the frame as the simulation sent
        it, with its box (a fit rotates the displayed frame off the box's axes)."""
        return self.raw_positions if self.raw_positions is not None else self.positions

    async def select(
        self, client: Client, message: p.Select, owner: Hashable | None = None
    ) -> p.Selected:
        """Count the atoms a selection takes now (nothing changes): priced, then evaluated by
        a selection worker, its time charged to `owner` (the client across its connections);
        a selection past a limit is answered with the limit."""
        if self.topology is None:
            raise p.ProtocolError(
                p.ErrorCode.NOT_READY, "no topology to select from yet", "select", message.seq
            )
        try:
            count = await self.layers.count(
                message.text, self._selected_positions(), self.positions_id, self.box, owner
            )
        except SelectionError as exc:
            return p.Selected(
                ref=message.seq,
                text=message.text,
                error=exc.reason[:1024],
                position=min(exc.position, len(message.text)),
            )
        return p.Selected(
            ref=message.seq,
            text=message.text,
            count=count,
            dynamic=is_dynamic(message.text),
        )

    def on_engine(self, info: p.EngineInfo) -> None:
        if self.engine is not None and _declared(self.engine) == _declared(info):
            return  # declared again as the viewers have it (a replay's change, a reconnect)
        self.engine = info
        if info.pull is not None:
            self.forces.max_force = min(self.forces.max_force, info.pull.max_force)
        self.broadcast(p.State(engine=info))

    def on_event(self, event: p.Event) -> None:
        """Relay the simulation's event to everyone and log it. A guard that fired has dropped
        every external force, so the pulls end here too."""
        self._log(
            {"event": "sim_event", "level": event.level, "code": event.code,
             "message": event.message, "step": event.step}
        )  # fmt: skip
        # a guard that fired paused the adapter and dropped every external force
        if event.code == "guard" and (self.forces.pulls or self.forces.scripted):
            self.forces.clear()
            self.broadcast(p.State(pulling=self.forces.pulling()))
        if event.code in ("guard", "paused"):  # the adapter is paused (a replay may start so)
            self.status = self.status.model_copy(update={"state": "paused", "steps_per_s": 0.0})
            self.broadcast(p.State(sim=self.status))
        self.broadcast(event.model_copy(update={"seq": None}))

    def on_frame(self, frame: p.Frame) -> None:
        """Take a frame: the topology must be known and the atom counts must agree."""
        if self.topology is None:
            raise p.ProtocolError(
                p.ErrorCode.NOT_READY, "send a topology before frames", "frame", frame.seq
            )
        n = frame.positions.shape[0]
        if n != self.topology.n_atoms:
            raise p.ProtocolError(
                p.ErrorCode.INVALID_MESSAGE,
                f"frame.positions has {n} atoms, the topology has {self.topology.n_atoms}",
                "frame.positions",
                frame.seq,
            )
        now = time.monotonic()
        rate = self._step_rate.add(now, frame.step)
        raw = frame.positions.to_numpy()
        self.raw_positions = raw
        self.box = None if frame.box is None else frame.box.to_numpy()
        jumped = self._arrived.advance(frame.step)
        if self.frame_sinks:
            for sink in list(self.frame_sinks):
                sink(frame.step, frame.time_ps, raw, self.box)
        paused = self.status.state == "paused"
        self.status = p.SimStatus(
            state="paused" if paused else "running",
            step=frame.step,
            time_ps=frame.time_ps,
            steps_per_s=rate,
            n_atoms=n,
            engine=self.status.engine,
            observables=dict(frame.observables),
        )
        self.services.metrics.sim_frames.inc()
        if self.forces.springs:  # from every frame: a spring that lags its atom pumps energy in
            self._send_forces()
        if self.clients:
            self._frame_taken.clear()  # taken by the render that draws it, once displayed
        if needs_display(self.render_params, self.box):
            self.periodic.submit(
                self.topology, self.topology_id, raw, self.box, frame.step, self.render_params,
                jumped,
            )  # fmt: skip
        else:
            self.periodic.drop()
            self._publish(raw, None, frame.step)
        self._report(now)

    def _report(self, now: float) -> None:
        """Send the status (and the tracked atoms, the cell) now, or once `state_interval_s`
        has passed since the last: the last frame of a burst is reported too."""
        wait = self.settings.state_interval_s - (now - self._last_state_sent)
        if wait <= 0:
            self._send_status()
        elif self._status_flush is None:
            self._status_flush = asyncio.get_running_loop().call_later(wait, self._send_status)

    def _publish(self, positions: npt.NDArray[np.float32], shown: Shown | None, step: int) -> None:
        """A frame is ready to draw: `positions` as displayed (`shown` says how; None: as
        the simulation sent them)."""
        if self._closed or self.topology is None or len(positions) != self.topology.n_atoms:
            return
        self.positions = positions
        self.shown = shown
        self.positions_id += 1
        self.services.backend.stage(self.slot, self.positions_id, positions)
        self._remember(step)
        for shown_sink in list(self.shown_sinks):
            shown_sink(step)
        if self.camera is None:
            self._fit_camera()
        self.version += 1
        if shown is not None or self._cell_sent is not None:
            self._report(time.monotonic())  # markers and the cell as displayed now
        self.mark_dirty()

    def _remember(self, step: int) -> None:
        """Keep the last `time_window` frames while the render parameters smooth over time
        (or colour by motion); a jump in the steps (a replay seeked) starts them again."""
        params = self.render_params
        if not params.needs_history():
            self._history.clear()
            self._displayed.reset()
            return
        if self._history.maxlen != params.time_window:
            self._history = deque(self._history, maxlen=params.time_window)
        if self._displayed.advance(step):
            self._history.clear()
            self._history_epoch += 1
        assert self.positions is not None
        self._history.append((self.positions_id, self.positions))

    def _send_status(self) -> None:
        """The simulation's status and the tracked atoms, at most every `state_interval_s`."""
        if self._status_flush is not None:
            self._status_flush.cancel()
            self._status_flush = None
        self._last_state_sent = time.monotonic()
        cell = self._cell()
        if cell is not None and cell != self._cell_sent:
            self._cell_sent = cell
            self.broadcast(p.State(sim=self.status, cell=cell))
        else:
            self.broadcast(p.State(sim=self.status))
        self._send_tracked()

    def _cell(self) -> p.Cell | None:
        """The periodic box of the frame shown, as displayed (moved with it by a fit)."""
        return displayed_cell(self.shown, self.box)

    def _send_tracked(self, only: Client | None = None) -> None:
        """Where each viewer's tracked atoms are now (markers and measurements follow them)."""
        positions = self.positions
        if positions is None:
            return
        for client in [only] if only is not None else list(self.clients.values()):
            atoms = client.view.track if client.view is not None else []
            atoms = [a for a in atoms if a < len(positions)]  # asked for before a topology
            if not atoms:
                continue
            xyz = positions[np.asarray(atoms, dtype=np.int64)].astype(float)
            client.send(
                p.Tracked(
                    step=self.status.step,
                    atoms=list(atoms),
                    positions=[(float(a), float(b), float(c)) for a, b, c in xyz],
                )
            )

    def _legend_changed(self) -> None:
        """The colouring changed, or the topology: the legend again, for the atoms shown."""
        self._legend_key = None
        self._show_legend(self._legend_plans)

    def _show_legend(self, plans: tuple[LayerPlan, ...] | None) -> None:
        """What the colours of the atoms the layers show mean (hidden solvent and ions are
        not in it), sent when it changes."""
        if self.topology is None:
            return
        rp = self.render_params
        atoms = None if plans is None else tuple(plan.atoms_key for plan in plans)
        key = (self.topology_id, rp.color_by, rp.uniform_color, atoms)
        if key == self._legend_key:
            return
        self._legend_key, self._legend_plans = key, plans
        from server.render.colors import legend
        from server.render.layerplan import subset_topology

        topology = self.topology
        shown = visible_atoms(plans, topology.n_atoms)
        if 0 < len(shown) < topology.n_atoms:
            topology = subset_topology(topology, shown)
        drawn = legend(topology, rp.color_by, rp.uniform_color)
        if drawn != self.legend:
            self.legend = drawn
            self.broadcast(p.State(legend=self.legend))

    def on_ack(self, ack: p.ParamsAck) -> None:
        pending = self.acks.take(ack.ref)
        if pending is None:
            return  # an ack for an automatic force update
        self._log(
            {
                "event": "applied" if ack.ok else "failed",
                "ref": pending.log_id,
                "kind": pending.kind,
                "step": ack.step,
                "time_ps": ack.time_ps,
                "detail": ack.detail,
            }
        )
        self._settle(pending, ack)

    def _settle(self, pending: Pending, ack: p.ParamsAck) -> None:
        """Apply what an acknowledgement confirms (or undo what it refuses), then answer the
        client that asked."""
        if pending.kind == "control" and ack.ok:
            action = ack.applied.get("action")
            if action in ("pause", "resume"):
                state = "paused" if action == "pause" else "running"
                self.status = self.status.model_copy(update={"state": state})
                self.broadcast(p.State(sim=self.status))
            elif action in ("speed", "loop"):
                self._playback_changed(action, ack.applied.get(action))
        if pending.proposal is not None:
            if ack.ok:
                self.sim_params = apply_sim_params(self.sim_params, pending.proposal)
            # refused: every dashboard goes back to the confirmed values
            self.broadcast(p.State(sim_params=self.sim_params))
        client = self.clients.get(pending.client_id)
        if client is not None and pending.client_seq is not None:
            client.send(ack.model_copy(update={"ref": pending.client_seq, "seq": None}))

    def _playback_changed(self, field: str, value: Any) -> None:
        """A replay acknowledged a new speed or loop: its engine says so to every viewer (a
        value the playback cannot hold leaves it as it was)."""
        engine = self.engine
        if engine is None or engine.playback is None:
            return
        try:
            playback = p.Playback.model_validate({**engine.playback.model_dump(), field: value})
        except ValidationError:
            return
        if playback == engine.playback:
            return  # the replay had declared it already, or nothing changed
        self.engine = engine.model_copy(update={"playback": playback})
        self.broadcast(p.State(engine=self.engine))

    # ------------------------------------------------------------------ steering

    def _log(self, entry: dict[str, Any]) -> int:
        return self.log_event(entry)[0]

    def log_event(self, entry: dict[str, Any]) -> tuple[int, Future[None]]:
        """Append `entry` to the session's steering log with a new id and the current step;
        the future resolves once it is on disk."""
        log_id = self.services.steering_log.next_id(self.id)
        done = self.services.steering_log.append(
            self.id, {"id": log_id, "sim_step": self.status.step, **entry}
        )
        return log_id, done

    def _forward(self, message: p.Message, pending: Pending) -> None:
        """Send a steering message to the simulation; the ack comes back through `on_ack`."""
        assert self.sim is not None
        seq = self.acks.expect(pending)
        self.sim.send(message.model_copy(update={"seq": seq}))

    def _need_sim(self, message: p.Message) -> None:
        if self.sim is None:
            raise p.ProtocolError(
                p.ErrorCode.NOT_READY,
                "no simulation is connected to this session",
                message.type,
                message.seq,
            )

    async def steer(self, client: Client, message: p.Message) -> None:
        """Apply a steering message from a steerer (roles and rates checked by the caller).
        New layers wait for their selections to be checked by a worker."""
        who = {"client_id": client.client_id, "client": client.name}
        match message:
            case p.SetRenderParams():
                await self._set_render_params(client, message, who)
            case p.SimParams():
                self._need_sim(message)
                check_sim_params(self.engine, message)
                changes = sim_params_changes(message)
                log_id = self._log({"event": "sim_params", **who, "changes": changes})
                pending = Pending(client.client_id, message.seq, "sim_params", log_id, message)
                self._forward(message, pending)
            case p.Control():
                self._need_sim(message)
                check_control(self.engine, message)
                changes = message.model_dump(exclude_none=True, exclude={"seq", "type"})
                log_id = self._log({"event": "control", **who, **changes})
                self._forward(message, Pending(client.client_id, message.seq, "control", log_id))
            case p.Forces():
                self._need_sim(message)
                self._script_forces(client, message, who)
            case p.Pull():
                self._need_sim(message)
                message = check_pull(self.engine, message)
                self._pull(client, message, who)
            case _:
                raise p.ProtocolError(
                    p.ErrorCode.FORBIDDEN,
                    f"{message.type} is not a steering message",
                    "type",
                    message.seq,
                )

    async def _set_render_params(
        self, client: Client, message: p.SetRenderParams, who: dict[str, str]
    ) -> None:
        try:
            merged, changes = merge_patch(self.render_params, message.changes())
        except ValidationError as exc:
            raise _invalid(exc, "render_params.params", message.seq) from None
        if any(f in changes for f in PERIODIC_FIELDS):
            await self._check_periodic(merged, message.seq)
        if "layers" in changes:
            await self._check_layers(merged, message.seq)
            # other steering may have landed meanwhile: the patch applies to what is now
            try:
                merged, changes = merge_patch(self.render_params, message.changes())
            except ValidationError as exc:
                raise _invalid(exc, "render_params.params", message.seq) from None
            self.layers.auto = False
        client.view_ref = message.seq
        if not changes:
            if message.seq is not None:  # nothing for the others; the sender learns it is in
                client.send(p.State(ref=message.seq, by=client.client_id))
            return
        # logged first: a change the log cannot record is refused (an error naming the
        # message) rather than drawn without a state telling the viewers of it
        self._log({"event": "render_params", **who, "changes": changes})
        self._new_render_params(merged, changes, message.seq, client.client_id)
        self.scheduler.interacting(time.monotonic())
        self.mark_dirty()

    def _new_render_params(
        self, merged: p.RenderParams, changes: dict[str, Any], ref: int | None, by: str | None
    ) -> None:
        """The session draws `merged` from now on (logged already): every client is told, and
        what the changed fields touch besides the image follows (the legend, the display)."""
        self.render_params = merged
        self.broadcast(p.State(render_params=merged, ref=ref, by=by))
        if "color_by" in changes or "uniform_color" in changes:
            self._legend_changed()
        if any(f in changes for f in PERIODIC_FIELDS):
            self._redisplay()
        self.version += 1

    def take_back_render_params(self, params: p.RenderParams, why: str) -> bool:
        """Go back to `params` (the render loop's last drawn) because the present ones are too
        large to draw on this server: logged as the server's change, with why, and told to every
        client as the session's state."""
        try:
            merged, changes = merge_patch(self.render_params, params.model_dump())
        except ValidationError:
            return False
        if not changes:
            return False
        try:
            entry = {"event": "render_params", "client": "server", "changes": changes, "why": why}
            self._log(entry)
        except Exception:  # unrecorded, it is not made: the refusal alone is told
            log.exception("session %s: taking back render parameters failed", self.id)
            return False
        self._new_render_params(merged, changes, None, None)
        self.mark_dirty()
        return True

    def _redisplay(self) -> None:
        """The periodic options changed: the last frame is displayed again with them (also
        while the simulation is paused)."""
        raw = self.raw_positions
        if raw is None or self.topology is None:
            return
        step = self.status.step
        if needs_display(self.render_params, self.box):
            self.periodic.submit(
                self.topology, self.topology_id, raw, self.box, step, self.render_params, True
            )
        else:
            self.periodic.drop()
            self._publish(raw, None, step)

    async def _check_periodic(self, params: p.RenderParams, seq: int | None) -> None:
        """The centre and fit selections in use must parse, name fixed atoms (a distance-based
        selection changes from frame to frame) and evaluate on this topology; the first that
        does not is named, and nothing changes."""
        try:
            check_periodic(params, self.services.selections.limits.selection)
        except PeriodicError as exc:
            raise p.ProtocolError(
                p.ErrorCode.INVALID_MESSAGE, str(exc), f"render_params.params.{exc.path}", seq
            ) from None
        if self.topology is None:
            return
        for field, text in selection_fields(params):
            try:
                (found,) = await self.layers.evaluate([text], None, self.positions_id)
            except SelectionError as exc:
                found = exc
            if not isinstance(found, SelectionError):
                problem = atoms_problem(field, text, len(found), params)
                if problem is not None:
                    raise p.ProtocolError(
                        p.ErrorCode.INVALID_MESSAGE,
                        f"{field}: {problem}",
                        f"render_params.params.{field}",
                        seq,
                    )
                continue
            if isinstance(found, SelectionBusyError):
                code = p.ErrorCode.NOT_READY
            else:
                code = p.ErrorCode.TOO_LARGE if found.limit else p.ErrorCode.INVALID_MESSAGE
            path = f"render_params.params.{field}"
            raise p.ProtocolError(code, f"{field}: {found}", path, seq)

    async def _check_layers(self, params: p.RenderParams, seq: int | None) -> None:
        """Every layer's selection must parse, keep to the selection limits and evaluate on
        this topology (all of them together within one budget, in a worker); the first that
        does not is named with the position of what is wrong, and nothing changes. A layer
        past a limit is `too_large`, naming the limit."""
        limits = self.services.selections.limits.selection
        layers = params.layers
        # the text first, here: it must parse, and its length and nesting are bounded
        for i, layer in enumerate(layers):
            try:
                check_syntax(layer.selection, limits)
            except SelectionError as exc:
                raise self._layer_error(exc, i, layer, seq) from None
        try:
            if self.topology is None:
                return  # checked on the topology when it comes (drawn as nothing if it fails)
            # distance-based layers are priced on the frame; before one, they parse only
            checked = [
                (i, layer)
                for i, layer in enumerate(layers)
                if self.positions is not None or not is_dynamic(layer.selection)
            ]
            if not checked:
                return
            found = await self.layers.check(
                [layer.selection for _, layer in checked], self._selected_positions(),
                self.positions_id, self.box,
            )  # fmt: skip
        except SelectionError as exc:  # the request as a whole: its time or memory
            if len(checked) == 1:  # the one layer it was
                raise self._layer_error(exc, checked[0][0], checked[0][1], seq) from None
            raise self._layer_error(exc, -1, None, seq) from None
        for (i, layer), error in zip(checked, found, strict=True):
            if error is not None:
                raise self._layer_error(error, i, layer, seq)

    @staticmethod
    def _layer_error(
        exc: SelectionError, i: int, layer: p.Layer | None, seq: int | None
    ) -> p.ProtocolError:
        if isinstance(exc, SelectionBusyError):
            code = p.ErrorCode.NOT_READY  # nothing wrong with them: asking again may answer
        else:
            code = p.ErrorCode.TOO_LARGE if exc.limit else p.ErrorCode.INVALID_MESSAGE
        if layer is None:
            return p.ProtocolError(code, f"layers: {exc}", "render_params.params.layers", seq)
        return p.ProtocolError(
            code,
            f"layer {i + 1} ({layer.name or 'unnamed'}): {exc}",
            f"render_params.params.layers.{i}.selection",
            seq,
        )

    def _script_forces(self, client: Client, message: p.Forces, who: dict[str, str]) -> None:
        limit = self.settings.limits.max_forces
        if message.indices.count > limit:
            raise p.ProtocolError(
                p.ErrorCode.TOO_LARGE, f"more than {limit} forces", "forces.indices", message.seq
            )
        atoms = message.indices.to_numpy()
        self._check_atoms(atoms, "forces.indices", message.seq)
        vectors = message.forces.to_numpy()
        if not np.isfinite(vectors).all():
            raise p.ProtocolError(
                p.ErrorCode.INVALID_MESSAGE, "forces must be finite", "forces.forces", message.seq
            )
        self.forces.set_scripted(client.client_id, atoms, vectors)
        log_id = self._log({"event": "forces", **who, "atoms": atoms.tolist()})
        self._forward(
            self._merged_forces(), Pending(client.client_id, message.seq, "forces", log_id)
        )

    def _pull(self, client: Client, message: p.Pull, who: dict[str, str]) -> None:
        self._check_atoms(np.asarray([message.atom]), "pull.atom", message.seq)
        limit = self.settings.limits.max_forces
        new = not message.release and message.atom not in self.forces.pulls
        if new and len(self.forces.pulls) >= limit:
            raise p.ProtocolError(
                p.ErrorCode.TOO_LARGE,
                f"at most {limit} atoms may be pulled at once",
                "pull.atom",
                message.seq,
            )
        self.forces.pull(client.client_id, message)
        log_id = self._log(
            {
                "event": "pull",
                **who,
                "atom": message.atom,
                "target": message.target,
                "force": message.force,
                "release": message.release,
            }
        )
        self.broadcast(p.State(pulling=self.forces.pulling()))
        pending = Pending(client.client_id, message.seq, "pull", log_id)
        self._forward(self._merged_forces(), pending)

    def _check_atoms(self, atoms: npt.NDArray[Any], path: str, seq: int | None) -> None:
        n = self.topology.n_atoms if self.topology is not None else 0
        if atoms.size and (int(atoms.max()) >= n or int(atoms.min()) < 0):
            raise p.ProtocolError(
                p.ErrorCode.INVALID_MESSAGE, f"atom index out of range [0, {n})", path, seq
            )

    def _merged_forces(self) -> p.Forces:
        # springs follow the newest frame as sent, taken into the displayed frame (where the
        # targets are given) by the last display's transform; before a first display (the
        # periodic steps wait for the selection worker) they pull in the engine's own frame
        shown = self.shown if self.positions is not None else None
        box = (shown.cell[1] if shown.cell is not None else None) if shown else usable_box(self.box)
        raw = self.raw_positions
        at: Positions | None = self.positions if raw is None else raw
        if raw is not None and shown is not None:
            at = DisplayedAtoms(raw, shown)
        idx, forces = self.forces.merged(at, box)
        if shown is not None and len(forces):
            # given in the displayed frame: a fit rotated it (F_engine = R^T F_displayed)
            forces = (np.asarray(forces, dtype=np.float64) @ shown.rotation).astype(np.float32)
        return p.Forces(
            indices=p.WireArray.from_numpy(idx, "<i4"),
            forces=p.WireArray.from_numpy(forces, "<f4"),
        )

    def _send_forces(self) -> None:
        """Send the merged forces again (springs follow the atoms; no ack is awaited)."""
        if self.sim is None:
            return
        message = self._merged_forces()
        self.sim.send(message.model_copy(update={"seq": self.acks.next_seq()}))

    # ------------------------------------------------------------------ views and rendering

    def set_view(self, client: Client, view: p.View) -> None:
        """A client's view: its canvas, camera, codecs and tracked atoms. A canvas past the
        image limits is kept as it is (its picks are in its pixels); its images are shrunk to
        fit (`RenderScheduler.image_size`), as docs/server.md says: it had been refused, and
        the Python client, which does not wait for an answer to a view, got no image."""
        if view.track and self.topology is not None:
            # before the simulation's topology the atoms cannot be checked: they are kept, and
            # those the topology lacks are left out of what is sent (`_send_tracked`)
            self._check_atoms(np.asarray(view.track), "view.track", view.seq)
        tracking_changed = client.view is None or client.view.track != view.track
        if client.view is None or client.view.video != view.video:
            client.force_jpeg = False  # a new offer of decoders: video may work again
        client.view = view
        client.view_ref = view.seq
        client.needs_image = True
        if tracking_changed and view.track:
            self._send_tracked(only=client)
        if view.interacting:
            now = time.monotonic()
            client.interacting_until = now + self.settings.interactive_idle_s
            client.interacted_at = now
        self.mark_dirty()

    def on_frame_ack(self, client: Client, ack: p.FrameAck) -> None:
        """A video frame or image reached `client`'s screen: its link estimate learns from it,
        and a view that skipped frames for the link renders again if it is behind."""
        client.link.on_ack(ack.frame_id, time.monotonic())
        if client.video_stream is None:
            client.paced_images = True  # it acknowledges its JPEG images: pace them too
        if client.needs_image:  # it skipped the newest picture while its link was busy
            self.mark_dirty()

    def mark_dirty(self) -> None:
        """Something the viewers see changed: the render loop looks for due renders."""
        self.renders.mark_dirty()

    @property
    def render_count(self) -> int:
        return self.renders.render_count

    @property
    def last_timings(self) -> dict[str, float]:
        return self.renders.last_timings

    def snapshot(self) -> Snapshot | None:
        """The molecule as it is now, for one render pass."""
        if self.topology is None or self.positions is None:
            return None
        return Snapshot(
            topology=self.topology,
            positions=self.positions,
            topology_id=self.topology_id,
            positions_id=self.positions_id,
            step=self.status.step,
            version=self.version,
            history=tuple(self._history),
            history_epoch=self._history_epoch,
            live=self.engine is None or self.engine.kind != "replay",
        )

    def can_render(self) -> bool:
        return self.topology is not None and self.positions is not None

    def take_snapshot(self) -> Snapshot | None:
        """`snapshot()` for a render pass: the newest frame counts as taken (`frame_taken`)."""
        snap = self.snapshot()
        if snap is not None:
            self._frame_taken.set()
        return snap

    def scene(self, snap: Snapshot) -> Scene | None:
        """What the render loop draws `snap` with (`RenderHost.scene`)."""
        if snap.topology_id != self.topology_id:
            return None
        layers = self._layer_plans(snap)
        if not self.layers.ready:
            return None  # a layer's atoms are still being evaluated; they call again
        self._show_legend(layers)
        return Scene(layers)

    async def pick(self, client: Client, pick: p.Pick) -> p.Picked:
        snap = self.snapshot()
        if snap is None:
            raise p.ProtocolError(p.ErrorCode.NOT_READY, "nothing to pick yet", "pick", pick.seq)
        camera, w, h = self.scheduler.view_of(client, self.camera)
        if pick.x >= w or pick.y >= h:
            raise p.ProtocolError(
                p.ErrorCode.INVALID_MESSAGE,
                f"pixel ({pick.x}, {pick.y}) is outside the {w}x{h} view",
                "pick.x",
                pick.seq,
            )
        pw, ph = self.scheduler.pick_size(w, h)
        layers = self._layer_plans(snap)
        if not self.layers.ready:
            raise p.ProtocolError(
                p.ErrorCode.NOT_READY, "the layers are still being prepared", "pick", pick.seq
            )
        request = RenderRequest(self.slot, snap, self.render_params, camera, pw, ph, layers=layers)
        x, y = min(pw - 1, pick.x * pw // w), min(ph - 1, pick.y * ph // h)
        atom, depth, layer = await self.services.backend.pick(request, x, y)
        if atom is None:
            return p.Picked(ref=pick.seq)
        topo, positions = snap.topology, snap.positions
        return p.Picked(
            ref=pick.seq,
            atom=atom,
            element=topo.elements[atom],
            name=topo.names[atom],
            residue_id=int(topo.residue_ids.to_numpy()[atom]),
            residue_name=topo.residue_names[atom],
            chain=topo.chain_ids[atom],
            position=(
                float(positions[atom, 0]),
                float(positions[atom, 1]),
                float(positions[atom, 2]),
            ),
            depth=depth,
            layer=layer or "",
        )

    async def _stats_loop(self) -> None:
        while not self._closed:
            await asyncio.sleep(self.settings.stats_interval_s)
            fps = self.renders.fps(time.monotonic())
            t = self.renders.last_timings
            for client in list(self.clients.values()):
                client.send(
                    p.Stats(
                        render_fps=fps,
                        render_ms=t.get("total", 0.0),
                        encode_ms=self.delivery.last_encode_ms,
                        grid_ms=t.get("grid", 0.0),
                        upload_ms=t.get("upload", 0.0),
                        frames_sent=client.frames_sent,
                        frames_dropped=client.frames_dropped,
                        sim_frames=self.positions_id,
                        device=self.services.backend.device_name,
                        device_ms={
                            k.removeprefix("device:"): v
                            for k, v in t.items()
                            if k.startswith("device:")
                        },
                    )
                )

    def summary(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "created": self.created,
            "status": self.status.model_dump(),
            "clients": [c.model_dump() for c in self.roster.infos()],
            "n_atoms": self.topology.n_atoms if self.topology else 0,
            "title": self.topology.title if self.topology else "",
            "render_params": self.render_params.model_dump(),
            "renders": self.render_count,
            "video_streams": self.delivery.streams.describe(),
        }

    async def frame_taken(self, timeout: float) -> None:
        """Wait, at most `timeout` s, until a render has taken the newest frame. The
        simulation's connection reads its next frame only then, so frames that no render would
        draw are neither received nor validated: ingest keeps pace with rendering, and the
        event loop's time goes to the viewers."""
        if self._frame_taken.is_set() or not self.clients:
            return
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._frame_taken.wait(), timeout)

    async def close(self) -> None:
        hooks, self.close_hooks = self.close_hooks, []
        for hook in hooks:
            try:
                await hook()
            except Exception:
                log.exception("a close hook of session %s failed", self.id)
        self._closed = True
        if self._roster_flush is not None:
            self._roster_flush.cancel()
        if self._status_flush is not None:
            self._status_flush.cancel()
        self._frame_taken.set()
        tasks = [*self._tasks, *self.delivery.in_flight()]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        self.delivery.close()
        await self.periodic.close()
        self.layers.close()
        await self.services.backend.release(self.slot)
