"""A session's frames as displayed: the render parameters' periodic options (molecules whole,
a selection centred, wrapping, following atoms across the box, a fit) applied on the render
device to every frame that needs them, in order, the newest frame replacing one still waiting.

The centre and fit selections are evaluated once per topology by the session's selection
worker (they name fixed atoms: a distance-based one is refused when it is set). A frame that
does not follow the last one (a seek, a reset, new options or a new topology) starts again:
`unwrap` makes its molecules whole, and a fit takes it as its reference.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

import protocol as p
from server.pipeline.gpu import DisplayRequest
from server.render.boxes import Options, Shown, usable_box
from server.session.services import RenderBackend
from structures.selection import SelectionError
from structures.selection_pool import Held, SelectionBusyError

log = logging.getLogger("scalesteer.session")


@dataclass
class _Frame:
    topology: p.Topology
    topology_id: int
    positions: npt.NDArray[np.float32]
    box: npt.NDArray[np.float32] | None
    step: int
    params: p.RenderParams
    restart: bool


Publish = Callable[[npt.NDArray[np.float32], Shown | None, int], None]
"""(displayed positions, how they were displayed, step): a frame is ready to draw."""


class PeriodicFrames:
    """Displays a session's frames on its render slot, one at a time, newest first."""

    def __init__(self, slot: str, backend: RenderBackend, publish: Publish) -> None:
        self._slot = slot
        self._backend = backend
        self._publish = publish
        self._pending: _Frame | None = None
        self._last: _Frame | None = None
        self._task: asyncio.Task[None] | None = None
        self._atoms: dict[tuple[int, str], npt.NDArray[np.int32] | None] = {}
        self._key: tuple[Any, ...] | None = None
        self._warned: set[str] = set()
        self.held: Held | None = None
        """The session's topology in its selection worker (set by the session)."""

    def submit(
        self,
        topology: p.Topology,
        topology_id: int,
        positions: npt.NDArray[np.float32],
        box: npt.NDArray[np.float32] | None,
        step: int,
        params: p.RenderParams,
        restart: bool,
    ) -> None:
        """Display this frame next (a frame still waiting is dropped, its restart kept)."""
        waiting = self._pending
        frame = _Frame(
            topology, topology_id, positions, box, step, params,
            restart or (waiting is not None and waiting.restart),
        )  # fmt: skip
        self._pending = frame
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(
                self._run(), name=f"display-{self._slot}"
            )

    def drop(self) -> None:
        """Frames no longer need displaying: forget a waiting one."""
        self._pending = None
        self._last = None
        self._key = None

    async def close(self) -> None:
        self._pending = None
        task = self._task
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _run(self) -> None:
        while self._pending is not None:
            frame, self._pending = self._pending, None
            options = await self._options(frame)
            key = (frame.topology_id, *options.key())
            restart = frame.restart or key != self._key
            self._key = key
            request = DisplayRequest(
                self._slot, frame.topology, frame.positions, frame.box, options, restart
            )
            try:
                shown: Shown | None = await self._backend.display(request)
            except asyncio.CancelledError:
                raise
            except Exception:
                log.exception("displaying a frame of %s failed; drawn as sent", self._slot)
                shown = None
            self._last = frame
            if self._pending is not None and self._pending.topology_id != frame.topology_id:
                continue  # a frame of another system is waiting: this one is stale
            self._publish(frame.positions if shown is None else shown.positions, shown, frame.step)

    async def _options(self, frame: _Frame) -> Options:
        params = frame.params
        boxed = usable_box(frame.box) is not None
        centre_text = None
        if params.center == "selection":
            centre_text = params.center_selection
        elif params.center == "auto" and boxed:
            centre_text = p.AUTO_CENTER
        centre = await self._select(frame, centre_text) if centre_text else None
        fit_atoms = None
        if params.fit != "off":
            fit_atoms = await self._select(frame, params.fit_selection)
        return Options(
            mode=params.periodic if boxed else "off",
            centre=centre if centre is not None and len(centre) else None,
            fit=params.fit if fit_atoms is not None and len(fit_atoms) else "off",
            fit_atoms=fit_atoms if fit_atoms is not None and len(fit_atoms) else None,
        )

    async def _select(self, frame: _Frame, text: str) -> npt.NDArray[np.int32] | None:
        """The atoms of a static selection on this topology (None when it cannot be had)."""
        key = (frame.topology_id, text.strip())
        if key in self._atoms:
            return self._atoms[key]
        held = self.held
        if held is None:
            return None
        try:
            found = (await asyncio.wrap_future(held.submit([text])))[0]
        except SelectionError as exc:
            found = exc
        if isinstance(found, SelectionBusyError):
            return None  # asked again with the next frame
        if isinstance(found, SelectionError):
            if text not in self._warned:
                self._warned.add(text)
                log.warning("%s: selection %r not used: %s", self._slot, text, found.reason)
            atoms = None
        else:
            atoms = np.asarray(found, dtype=np.int32)
        if len(self._atoms) > 16:
            self._atoms.clear()
        self._atoms[key] = atoms
        return atoms
