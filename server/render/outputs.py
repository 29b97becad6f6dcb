"""Reading a renderer's last image back from the device, shared by every renderer kind (the
density caster, the shape caster and the layer compositor)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

from server.render.errors import RenderError
from server.render.yuv import I420Converter


class ImageOutputs:
    """The last image: `_image` (width, height) and the device buffers `_outputs()` names
    (packed RGBA, float distance along each ray, int32 atom id)."""

    _image: tuple[int, int] | None = None
    _i420: I420Converter | None = None

    def _outputs(self) -> tuple[Any, Any, Any]:
        raise NotImplementedError

    def _need_image(self) -> tuple[int, int]:
        if self._image is None:
            raise RenderError("nothing rendered yet")
        return self._image

    def device_outputs(self) -> tuple[Any, Any, Any, int]:
        """The last image's device buffers and its pixel count, for kernels that combine
        images without a trip through the host."""
        w, h = self._need_image()
        return (*self._outputs(), w * h)

    def _read(self, buffer: Any) -> npt.NDArray[Any]:
        w, h = self._need_image()
        out: npt.NDArray[Any] = buffer[: w * h].numpy().reshape(h, w)
        return out.copy()

    def read_rgba(self) -> npt.NDArray[np.uint8]:
        """(height, width, 4) uint8, row 0 at the top."""
        w, h = self._need_image()
        rgba: npt.NDArray[np.uint8] = self._read(self._outputs()[0]).view(np.uint8)
        return rgba.reshape(h, w, 4)

    def read_i420(self, size: tuple[int, int]) -> npt.NDArray[np.uint8]:
        """The last image as a video encoder takes it, scaled to `size` (width, height):
        (h * 3 / 2, w) uint8 I420 planes, sides padded to even (`server.render.yuv`)."""
        src = self._need_image()
        rgba = self._outputs()[0]
        if self._i420 is None or self._i420.device != rgba.device:
            self._i420 = I420Converter(rgba.device)
        return self._i420.convert(rgba, src, size)

    def read_depth(self) -> npt.NDArray[np.float32]:
        """(height, width) float32 distance along each ray; inf where nothing was hit."""
        depth: npt.NDArray[np.float32] = self._read(self._outputs()[1]).astype(np.float32)
        return depth

    def read_atom_ids(self) -> npt.NDArray[np.int32]:
        """(height, width) int32 id of the atom hit (the one contributing most to a density
        at its hit); -1 over the background."""
        ids: npt.NDArray[np.int32] = self._read(self._outputs()[2]).astype(np.int32)
        return ids
