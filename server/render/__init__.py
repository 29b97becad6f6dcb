"""GPU render core: direct ray casting of the multiscale Gaussian molecular density.

`Renderer` and the kernels load warp-lang on first use; `server.render.camera`,
`colors` and `transfer` are plain numpy and import without it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from server.render.errors import RenderError

if TYPE_CHECKING:
    from server.render.renderer import Renderer

__all__ = ["RenderError", "Renderer"]


def __getattr__(name: str) -> Any:
    if name == "Renderer":
        from server.render.renderer import Renderer

        return Renderer
    raise AttributeError(f"module 'server.render' has no attribute {name!r}")
