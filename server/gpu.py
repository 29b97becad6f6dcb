"""The GPU queue: one thread owns the device, and every render — live sessions and batch jobs —
runs on it in submission order. Each scene (a session, or a job) keeps its own Renderer so its
topology and buffers stay resident between frames.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np
import numpy.typing as npt

import protocol as p

if TYPE_CHECKING:
    from server.render import Renderer

T = TypeVar("T")


@dataclass
class RenderOutput:
    rgba: npt.NDArray[np.uint8]
    timings: dict[str, float]
    histogram: npt.NDArray[np.float32] | None = None


@dataclass
class _Scene:
    renderer: Renderer
    topology_id: int = -1
    positions_id: int = -1


@dataclass
class GpuQueue:
    """Serialises device work on one thread; methods named `*_sync` run on that thread."""

    device: str = "auto"
    max_atoms: int = 4_000_000
    max_pixels: int = 3840 * 2160
    _pool: ThreadPoolExecutor = field(
        default_factory=lambda: ThreadPoolExecutor(max_workers=1, thread_name_prefix="gpu")
    )
    _scenes: dict[str, _Scene] = field(default_factory=dict)
    actual_device: str = ""
    _lock: threading.Lock = field(default_factory=threading.Lock)

    async def call(self, fn: Callable[..., T], *args: Any) -> T:
        return await asyncio.get_running_loop().run_in_executor(self._pool, fn, *args)

    def _scene(self, key: str) -> _Scene:
        scene = self._scenes.get(key)
        if scene is None:
            from server.render import Renderer

            renderer = Renderer(
                device=self.device, max_atoms=self.max_atoms, max_pixels=self.max_pixels
            )
            self.actual_device = renderer.device
            scene = self._scenes[key] = _Scene(renderer)
        return scene

    def _prepare(
        self,
        key: str,
        topology: p.Topology,
        topology_id: int,
        positions: npt.NDArray[np.float32],
        positions_id: int,
    ) -> Renderer:
        scene = self._scene(key)
        if scene.topology_id != topology_id:
            scene.renderer.set_topology(topology)
            scene.topology_id = topology_id
            scene.positions_id = -1
        if scene.positions_id != positions_id:
            # frames were checked finite when decoded; skip the host-side scan
            scene.renderer.set_positions(positions, check_finite=False)
            scene.positions_id = positions_id
        return scene.renderer

    def render_sync(
        self,
        key: str,
        topology: p.Topology,
        topology_id: int,
        positions: npt.NDArray[np.float32],
        positions_id: int,
        params: p.RenderParams,
        camera: p.Camera,
        width: int,
        height: int,
        histogram: bool = False,
    ) -> RenderOutput:
        renderer = self._prepare(key, topology, topology_id, positions, positions_id)
        renderer.render(params, camera, width, height)
        rgba = renderer.read_rgba()
        hist = None
        if histogram:
            counts, _edges = renderer.density_histogram(64)
            hist = np.asarray(counts, dtype=np.float32)
        return RenderOutput(rgba=rgba, timings=dict(renderer.timings), histogram=hist)

    def pick_sync(
        self,
        key: str,
        topology: p.Topology,
        topology_id: int,
        positions: npt.NDArray[np.float32],
        positions_id: int,
        params: p.RenderParams,
        camera: p.Camera,
        width: int,
        height: int,
        x: int,
        y: int,
    ) -> tuple[int | None, float | None]:
        renderer = self._prepare(key, topology, topology_id, positions, positions_id)
        renderer.render(params, camera, width, height)
        atom, depth = renderer.pick(x, y)
        return atom, depth

    def release_sync(self, key: str) -> None:
        self._scenes.pop(key, None)

    async def release(self, key: str) -> None:
        await self.call(self.release_sync, key)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._scenes.clear()
