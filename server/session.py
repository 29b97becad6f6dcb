"""A session: one simulation source, its scene, shared render state, and the clients watching it.

The session decides *when* to render (a new frame, a parameter or camera change; bursts coalesce,
latest wins) and at which quality (reduced while someone interacts, a full still ~150 ms after).
Viewers with the same camera and size share one render. Rendering and encoding overlap: a render
hands its pixels to the encoder pool and the next render starts at once, with at most one encode
in flight per encoder thread; an image whose encode finishes after a newer one's is dropped.
Steering is validated upstream, applied here, logged, broadcast and forwarded to the simulation,
and acknowledged with the step at which the simulation applied it.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import time
from collections import deque
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

import protocol as p
from server.clients import Client, ImageOffer
from server.encoder import ImageEncoder
from server.gpu import GpuQueue, RenderOutput
from server.metrics import Metrics
from server.settings import ServerSettings
from server.steering_log import SteeringLog

log = logging.getLogger("scalesteer.session")

ViewKey = tuple[str, int, int, bool]


@dataclass
class PendingSteer:
    client_id: str
    client_seq: int | None
    kind: str
    log_id: int


@dataclass(frozen=True)
class Scene:
    """What one render pass draws: a topology and one frame of positions."""

    topology: p.Topology
    topology_id: int
    positions: npt.NDArray[np.float32]
    positions_id: int
    step: int
    version: int


@dataclass
class Rendered:
    """A render waiting for its encode: the pixels and what its image message will say."""

    out: RenderOutput
    frame_id: int
    step: int
    width: int
    height: int
    jpeg_quality: int


@dataclass
class ActivePull:
    pull: p.Pull
    client_id: str


def pull_forces(
    pulls: dict[int, ActivePull], positions: npt.NDArray[np.float32]
) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]:
    """Spring forces (kJ/mol/A) toward each pull's target, capped at its `max_force`."""
    atoms = [a for a in sorted(pulls) if a < len(positions)]
    idx = np.asarray(atoms, dtype=np.int32)
    out = np.zeros((len(atoms), 3), dtype=np.float32)
    for row, atom in enumerate(atoms):
        pull = pulls[atom].pull
        if pull.force is not None:
            f = np.asarray(pull.force, dtype=np.float64)
        else:
            assert pull.target is not None
            f = pull.spring_k * (np.asarray(pull.target, dtype=np.float64) - positions[atom])
        norm = float(np.linalg.norm(f))
        if norm > pull.max_force:
            f *= pull.max_force / norm
        out[row] = f
    return idx, out


class Session:
    """State and behaviour of one session; all methods run on the event loop."""

    def __init__(
        self,
        session_id: str,
        settings: ServerSettings,
        gpu: GpuQueue,
        encoders: Executor,
        metrics: Metrics,
        steering_log: SteeringLog,
        encoder: ImageEncoder | None = None,
        encode_slots: asyncio.Semaphore | None = None,
    ) -> None:
        self.id = session_id
        self.scene_key = f"session:{session_id}"  # GPU scene; ':' never occurs in a name
        self.settings = settings
        self.gpu = gpu
        self.encoders = encoders
        self.encoder = encoder or ImageEncoder()
        self.encode_slots = encode_slots or asyncio.Semaphore(settings.encode_workers)
        """Taken before a render, given back when its encode ends: bounds encodes in flight."""
        self.metrics = metrics
        self.steering_log = steering_log
        self.created = time.time()
        self.idle_since: float | None = time.monotonic()
        """When the last client and the simulation left (None while anyone is connected)."""
        self.clients: dict[str, Client] = {}
        self.sim: Client | None = None
        self.topology: p.Topology | None = None
        self.topology_id = 0
        self.positions: npt.NDArray[np.float32] | None = None
        self.positions_id = 0
        self.status = p.SimStatus(state="waiting")
        self.render_params = settings.render_defaults
        self.sim_params = p.SimParams()
        self.camera: p.Camera | None = None
        self.pulls: dict[int, ActivePull] = {}
        self.pending: dict[int, PendingSteer] = {}
        self._server_seq = itertools.count(1)
        self._log_seq = itertools.count(1)
        self._frame_ids = itertools.count(1)
        self._scene_version = 0
        self._rendered: dict[ViewKey, int] = {}
        self._interactive_until = 0.0
        self._dirty = asyncio.Event()
        self._closed = False
        self._last_state_sent = 0.0
        self._rate_window: deque[tuple[float, int]] = deque()
        """(time, step) of the frames of the last 3 s, for steps/s."""
        self.render_count = 0
        self.last_timings: dict[str, float] = {}
        self.last_encode_ms = 0.0
        self._render_times: list[float] = []
        self._last_hist = 0.0
        self.histogram: npt.NDArray[np.float32] | None = None
        self._encoding: set[asyncio.Task[None]] = set()
        self._frame_taken = asyncio.Event()
        self._frame_taken.set()
        self._tasks = [
            asyncio.create_task(self._render_loop(), name=f"render-{session_id}"),
            asyncio.create_task(self._stats_loop(), name=f"stats-{session_id}"),
        ]

    # ------------------------------------------------------------------ clients

    def attach(self, client: Client) -> None:
        self.idle_since = None
        if client.role == "simulation":
            if self.sim is not None and self.sim is not client:
                old = self.sim
                self._fail_pending("the simulation was replaced by a new connection")
                old.send(
                    p.Error(
                        code=p.ErrorCode.FORBIDDEN,
                        message="replaced by a new simulation connection",
                    )
                )
                old.close_after_flush()
            self.sim = client
        else:
            self.clients[client.client_id] = client
            client.needs_image = True
        self.metrics.clients.labels(client.role).inc()
        client.send(self.full_state())
        self.broadcast(p.State(clients=self.client_infos()))
        self.mark_dirty()

    def detach(self, client: Client) -> None:
        self.metrics.clients.labels(client.role).dec()
        if client.role == "simulation":
            if self.sim is client:
                self.sim = None
                self.status = self.status.model_copy(
                    update={"state": "disconnected", "steps_per_s": 0.0}
                )
                self._fail_pending("simulation disconnected")
                self.broadcast(p.State(sim=self.status))
        else:
            self.clients.pop(client.client_id, None)
            if not self.clients:
                self._frame_taken.set()
            mine = [a for a, pull in self.pulls.items() if pull.client_id == client.client_id]
            for atom in mine:
                self.pulls.pop(atom)
            if mine:
                self._send_forces()
                self.broadcast(p.State(pulling=[a.pull for a in self.pulls.values()]))
        self.broadcast(p.State(clients=self.client_infos()))
        if not self.clients and self.sim is None:
            self.idle_since = time.monotonic()

    def _fail_pending(self, why: str) -> None:
        """Steering forwarded to a simulation that is gone will never be acknowledged."""
        for seq in list(self.pending):
            self._reply_ack(self.pending.pop(seq), p.ParamsAck(ref=0, ok=False, detail=why))

    def client_infos(self) -> list[p.ClientInfo]:
        infos = [c.info() for c in self.clients.values()]
        if self.sim is not None:
            infos.insert(0, self.sim.info())
        return infos

    def full_state(self) -> p.State:
        return p.State(
            render_params=self.render_params,
            sim_params=self.sim_params,
            sim=self.status,
            clients=self.client_infos(),
            pulling=[a.pull for a in self.pulls.values()],
            camera=self.camera,
        )

    def broadcast(self, message: p.Message) -> None:
        for client in list(self.clients.values()):
            client.send(message)

    # ------------------------------------------------------------------ simulation input

    def on_topology(self, topology: p.Topology) -> None:
        changed = self.topology is None or self.topology.n_atoms != topology.n_atoms
        self.topology = topology
        self.topology_id += 1
        if changed:
            self.positions = None
            self.camera = None
            self.pulls.clear()
        self.status = self.status.model_copy(
            update={"n_atoms": topology.n_atoms, "engine": topology.engine, "state": "running"}
        )
        self.broadcast(p.State(sim=self.status))

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
        window = self._rate_window
        while window and now - window[0][0] >= 3.0:
            window.popleft()
        window.append((now, frame.step))
        rate = 0.0
        if len(self._rate_window) > 1:
            (t0, s0), (t1, s1) = self._rate_window[0], self._rate_window[-1]
            rate = max(0.0, (s1 - s0) / (t1 - t0)) if t1 > t0 else 0.0
        self.positions = frame.positions.to_numpy()
        self.positions_id += 1
        if self.camera is None:
            from server.render.camera import fit_camera

            w, h = self.settings.default_size
            self.camera = fit_camera(self.positions, w, h)
            self.broadcast(p.State(camera=self.camera))
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
        self.metrics.sim_frames.inc()
        self._scene_version += 1
        if self.clients:
            self._frame_taken.clear()
        if self.pulls:
            self._send_forces()
        if now - self._last_state_sent >= self.settings.state_interval_s:
            self._last_state_sent = now
            self.broadcast(p.State(sim=self.status))
        self.mark_dirty()

    def on_ack(self, ack: p.ParamsAck) -> None:
        pending = self.pending.pop(ack.ref, None)
        if pending is None:
            return  # an ack for an automatic force update
        if pending.kind == "control" and ack.ok:
            action = ack.applied.get("action")
            if action in ("pause", "resume"):
                state = "paused" if action == "pause" else "running"
                self.status = self.status.model_copy(update={"state": state})
                self.broadcast(p.State(sim=self.status))
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
        self._reply_ack(pending, ack)

    def _reply_ack(self, pending: PendingSteer, ack: p.ParamsAck) -> None:
        client = self.clients.get(pending.client_id)
        if client is not None and pending.client_seq is not None:
            client.send(ack.model_copy(update={"ref": pending.client_seq, "seq": None}))

    # ------------------------------------------------------------------ steering

    def _log(self, entry: dict[str, Any]) -> int:
        log_id = next(self._log_seq)
        self.steering_log.append(self.id, {"id": log_id, "sim_step": self.status.step, **entry})
        return log_id

    def _forward(self, message: p.Message, client: Client, kind: str, log_id: int) -> bool:
        """Send a steering message to the simulation; the ack comes back through `on_ack`."""
        if self.sim is None:
            return False
        seq = next(self._server_seq)
        self.pending[seq] = PendingSteer(client.client_id, message.seq, kind, log_id)
        self.sim.send(message.model_copy(update={"seq": seq}))
        return True

    def _no_sim(self, message: p.Message) -> p.ProtocolError:
        return p.ProtocolError(
            p.ErrorCode.NOT_READY,
            "no simulation is connected to this session",
            message.type,
            message.seq,
        )

    def steer(self, client: Client, message: p.Message) -> None:
        """Apply a steering message from a steerer (roles and rates checked by the caller)."""
        who = {"client_id": client.client_id, "client": client.name}
        match message:
            case p.SetRenderParams():
                changes = message.changes()
                merged = p.RenderParams.model_validate(
                    {**self.render_params.model_dump(), **changes}
                )
                self.render_params = merged
                self._log({"event": "render_params", **who, "changes": changes})
                self.broadcast(p.State(render_params=merged))
                self._scene_version += 1
                self._interactive_until = time.monotonic() + self.settings.interactive_idle_s
                client.view_ref = message.seq
                self.mark_dirty()
            case p.SimParams():
                if self.sim is None:
                    raise self._no_sim(message)
                changes = message.model_dump(exclude_none=True, exclude={"seq", "type"})
                log_id = self._log({"event": "sim_params", **who, "changes": changes})
                self.sim_params = self.sim_params.model_copy(
                    update={k: v for k, v in changes.items() if k != "engine"}
                )
                if message.engine:
                    self.sim_params = self.sim_params.model_copy(
                        update={"engine": {**self.sim_params.engine, **message.engine}}
                    )
                self.broadcast(p.State(sim_params=self.sim_params))
                self._forward(message, client, "sim_params", log_id)
            case p.Control():
                if self.sim is None:
                    raise self._no_sim(message)
                changes = message.model_dump(exclude_none=True, exclude={"seq", "type"})
                log_id = self._log({"event": "control", **who, **changes})
                self._forward(message, client, "control", log_id)
            case p.Forces():
                if self.sim is None:
                    raise self._no_sim(message)
                if message.indices.count > self.settings.limits.max_forces:
                    raise p.ProtocolError(
                        p.ErrorCode.TOO_LARGE,
                        f"more than {self.settings.limits.max_forces} forces",
                        "forces.indices",
                        message.seq,
                    )
                self._check_atoms(message.indices.to_numpy(), "forces.indices", message.seq)
                log_id = self._log(
                    {"event": "forces", **who, "atoms": message.indices.to_numpy().tolist()}
                )
                self._forward(message, client, "forces", log_id)
            case p.Pull():
                if self.sim is None:
                    raise self._no_sim(message)
                self._check_atoms(np.asarray([message.atom]), "pull.atom", message.seq)
                if message.release:
                    self.pulls.pop(message.atom, None)
                elif (
                    message.atom not in self.pulls
                    and len(self.pulls) >= self.settings.limits.max_forces
                ):
                    raise p.ProtocolError(
                        p.ErrorCode.TOO_LARGE,
                        f"at most {self.settings.limits.max_forces} atoms may be pulled at once",
                        "pull.atom",
                        message.seq,
                    )
                else:
                    self.pulls[message.atom] = ActivePull(message, client.client_id)
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
                self.broadcast(p.State(pulling=[a.pull for a in self.pulls.values()]))
                idx, forces = self._current_forces()
                self._forward(
                    p.Forces(
                        seq=message.seq,
                        indices=p.WireArray.from_numpy(idx, "<i4"),
                        forces=p.WireArray.from_numpy(forces, "<f4"),
                    ),
                    client,
                    "pull",
                    log_id,
                )
            case _:
                raise p.ProtocolError(
                    p.ErrorCode.FORBIDDEN,
                    f"{message.type} is not a steering message",
                    "type",
                    message.seq,
                )

    def _check_atoms(self, atoms: npt.NDArray[Any], path: str, seq: int | None) -> None:
        n = self.topology.n_atoms if self.topology is not None else 0
        if atoms.size and (int(atoms.max()) >= n or int(atoms.min()) < 0):
            raise p.ProtocolError(
                p.ErrorCode.INVALID_MESSAGE, f"atom index out of range [0, {n})", path, seq
            )

    def _current_forces(self) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]:
        if not self.pulls or self.positions is None:
            return np.zeros(0, np.int32), np.zeros((0, 3), np.float32)
        return pull_forces(self.pulls, self.positions)

    def _send_forces(self) -> None:
        """Refresh the spring forces from the newest positions (no ack is awaited)."""
        if self.sim is None:
            return
        idx, forces = self._current_forces()
        self.sim.send(
            p.Forces(
                seq=next(self._server_seq),
                indices=p.WireArray.from_numpy(idx, "<i4"),
                forces=p.WireArray.from_numpy(forces, "<f4"),
            )
        )

    # ------------------------------------------------------------------ views and rendering

    def set_view(self, client: Client, view: p.View) -> None:
        lim = self.settings.limits
        if (
            max(view.width, view.height) > lim.max_image_side
            or view.width * view.height > lim.max_image_pixels
        ):
            raise p.ProtocolError(
                p.ErrorCode.TOO_LARGE,
                f"view {view.width}x{view.height} exceeds the image limit "
                f"({lim.max_image_side} px a side, {lim.max_image_pixels} px)",
                "view.width",
                view.seq,
            )
        client.view = view
        client.view_ref = view.seq
        client.needs_image = True
        if view.interacting:
            client.interacting_until = time.monotonic() + self.settings.interactive_idle_s
        self.mark_dirty()

    def mark_dirty(self) -> None:
        self._dirty.set()

    def _view_of(self, client: Client) -> tuple[p.Camera, int, int]:
        default_w, default_h = self.settings.default_size
        if client.view is not None:
            return client.view.camera, client.view.width, client.view.height
        return self.camera or p.Camera(), default_w, default_h

    def _groups(self, now: float) -> dict[ViewKey, list[Client]]:
        groups: dict[ViewKey, list[Client]] = {}
        for client in self.clients.values():
            camera, w, h = self._view_of(client)
            interactive = now < self._interactive_until or now < client.interacting_until
            key = (camera.model_dump_json(), w, h, interactive)
            groups.setdefault(key, []).append(client)
        return groups

    async def _render_loop(self) -> None:
        while not self._closed:
            await self._dirty.wait()
            self._dirty.clear()
            try:
                await self._render_pending()
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("render failed in session %s", self.id)
                self.broadcast(
                    p.Error(code=p.ErrorCode.INTERNAL, message="render failed; see the server log")
                )
                await asyncio.sleep(0.5)

    async def _render_pending(self) -> None:
        if self.topology is None or self.positions is None or not self.clients:
            return
        still_due = False
        frame: list[Scene] = []  # the frame of this pass, taken when its first render starts
        for key, members in self._groups(time.monotonic()).items():
            camera_json, _w, _h, interactive = key
            still_due = still_due or interactive
            version = self._scene_version
            if self._rendered.get(key) == version and not any(c.needs_image for c in members):
                continue
            refs = {c.client_id: c.view_ref for c in members}
            for c in members:  # a view arriving during the render sets it again
                c.needs_image = False
            camera = p.Camera.model_validate_json(camera_json)
            rendered_version = await self._render_group(key, members, camera, refs, frame)
            if rendered_version is not None:
                self._rendered[key] = rendered_version
        if still_due:  # come back for the full-quality still once the interaction pauses
            delay = self.settings.interactive_idle_s + 0.01
            asyncio.get_running_loop().call_later(delay, self.mark_dirty)
        if len(self._rendered) > 256:
            self._rendered.clear()

    def _scene(self) -> Scene | None:
        if self.topology is None or self.positions is None:
            return None
        return Scene(
            self.topology,
            self.topology_id,
            self.positions,
            self.positions_id,
            self.status.step,
            self._scene_version,
        )

    async def _render_group(
        self,
        key: ViewKey,
        members: list[Client],
        camera: p.Camera,
        refs: dict[str, int | None],
        frame: list[Scene],
    ) -> int | None:
        """Render one view on the GPU, then leave its encoding and delivery to a task of its own.
        Returns the scene version rendered (None: nothing was).

        The encoder slot is taken before the scene is read, so a render waiting for a free
        encoder renders the newest frame once it gets one; the other views of the same pass
        (`frame`) render that same frame, so its upload and grid serve them all.
        """
        await self.encode_slots.acquire()
        try:
            if not frame:
                scene = self._scene()
                if scene is not None:
                    frame.append(scene)
                    self._frame_taken.set()
            rendered = await self._render(camera, key, frame[0]) if frame else None
        except BaseException:
            self.encode_slots.release()
            raise
        if rendered is None:
            self.encode_slots.release()
            return None
        task = asyncio.create_task(
            self._encode_and_offer(key, rendered, members, refs),
            name=f"encode-{self.id}-{rendered.frame_id}",
        )
        self._encoding.add(task)
        task.add_done_callback(self._encoding.discard)
        return frame[0].version

    async def _render(self, camera: p.Camera, key: ViewKey, scene: Scene) -> Rendered | None:
        """One render of `scene` for a view; None when a new topology arrived since the scene
        was taken (the next pass renders that one)."""
        if scene.topology_id != self.topology_id:
            return None
        _camera_json, w, h, interactive = key
        params = self.render_params
        scale = params.quality * (self.settings.interactive_scale if interactive else 1.0)
        rw, rh = max(1, round(w * scale)), max(1, round(h * scale))
        lim = self.settings.limits
        shrink = min(
            1.0, lim.max_image_side / max(rw, rh), (lim.max_image_pixels / (rw * rh)) ** 0.5
        )
        rw, rh = max(1, int(rw * shrink)), max(1, int(rh * shrink))
        now = time.monotonic()
        want_hist = not interactive and now - self._last_hist > 1.0
        step = scene.step  # the step of the positions rendered, not of a later frame
        out: RenderOutput = await self.gpu.call(
            self.gpu.render_sync,
            self.scene_key,
            scene.topology,
            scene.topology_id,
            scene.positions,
            scene.positions_id,
            params,
            camera,
            rw,
            rh,
            want_hist,
        )
        if want_hist:
            self._last_hist = now
            self.histogram = out.histogram
        self.render_count += 1
        self.last_timings = out.timings
        self._render_times.append(time.monotonic())
        self.metrics.frames_rendered.inc()
        self.metrics.render_ms.observe(out.timings.get("total", 0.0))
        quality = self.settings.interactive_jpeg_quality if interactive else params.jpeg_quality
        return Rendered(out, next(self._frame_ids), step, rw, rh, quality)

    async def _encode_and_offer(
        self,
        key: ViewKey,
        rendered: Rendered,
        members: list[Client],
        refs: dict[str, int | None],
    ) -> None:
        """Encode off the event loop, then offer the image to the view's clients."""
        out = rendered.out
        loop = asyncio.get_running_loop()
        try:
            data, encode_ms = await loop.run_in_executor(
                self.encoders, self.encoder.encode, out.rgba, "jpeg", rendered.jpeg_quality
            )
        except Exception:
            log.exception("encoding failed in session %s", self.id)
            self._rendered.pop(key, None)  # render this view again on the next change
            self.broadcast(
                p.Error(code=p.ErrorCode.INTERNAL, message="encoding failed; see the server log")
            )
            return
        finally:
            self.encode_slots.release()
        if self._closed:
            return
        self.last_encode_ms = encode_ms
        self.metrics.encode_ms.observe(encode_ms)
        hist = p.WireArray.from_numpy(out.histogram, "<f4") if out.histogram is not None else None
        base = p.Image(
            frame_id=rendered.frame_id,
            step=rendered.step,
            format="jpeg",
            data=data,
            width=rendered.width,
            height=rendered.height,
            still=not key[3],
            render_ms=out.timings.get("total", 0.0),
            encode_ms=encode_ms,
            server_time=time.time(),
            histogram=hist,
        )
        packed: dict[int | None, bytes] = {}  # viewers that echo the same ref share the bytes
        for client in members:
            ref = refs.get(client.client_id)
            if ref not in packed:
                packed[ref] = p.encode(base.model_copy(update={"ref": ref}))
            match client.offer_encoded(rendered.frame_id, packed[ref]):
                case ImageOffer.REPLACED:
                    self.metrics.frames_dropped.inc()
                case ImageOffer.STALE:
                    self.metrics.frames_stale.inc()
                case _:
                    pass

    async def pick(self, client: Client, pick: p.Pick) -> p.Picked:
        if self.topology is None or self.positions is None:
            raise p.ProtocolError(p.ErrorCode.NOT_READY, "nothing to pick yet", "pick", pick.seq)
        camera, w, h = self._view_of(client)
        if pick.x >= w or pick.y >= h:
            raise p.ProtocolError(
                p.ErrorCode.INVALID_MESSAGE,
                f"pixel ({pick.x}, {pick.y}) is outside the {w}x{h} view",
                "pick.x",
                pick.seq,
            )
        topo, positions = self.topology, self.positions
        atom, depth = await self.gpu.call(
            self.gpu.pick_sync,
            self.scene_key,
            topo,
            self.topology_id,
            positions,
            self.positions_id,
            self.render_params,
            camera,
            w,
            h,
            pick.x,
            pick.y,
        )
        if atom is None:
            return p.Picked(ref=pick.seq)
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
        )

    async def _stats_loop(self) -> None:
        while not self._closed:
            await asyncio.sleep(self.settings.stats_interval_s)
            now = time.monotonic()
            self._render_times = [t for t in self._render_times if now - t < 2.0]
            fps = len(self._render_times) / 2.0
            t = self.last_timings
            for client in list(self.clients.values()):
                client.send(
                    p.Stats(
                        render_fps=fps,
                        render_ms=t.get("total", 0.0),
                        encode_ms=self.last_encode_ms,
                        grid_ms=t.get("grid", 0.0),
                        upload_ms=t.get("upload", 0.0),
                        frames_sent=client.frames_sent,
                        frames_dropped=client.frames_dropped,
                        sim_frames=self.positions_id,
                        device=self.gpu.actual_device,
                    )
                )

    def summary(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "created": self.created,
            "status": self.status.model_dump(),
            "clients": [c.model_dump() for c in self.client_infos()],
            "n_atoms": self.topology.n_atoms if self.topology else 0,
            "title": self.topology.title if self.topology else "",
            "render_params": self.render_params.model_dump(),
            "renders": self.render_count,
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
        self._closed = True
        self._frame_taken.set()
        tasks = [*self._tasks, *self._encoding]
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self.gpu.release(self.scene_key)
