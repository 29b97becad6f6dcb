"""Reading a renderer's last image back from the device, shared by every renderer kind (the
density caster, the shape caster and the layer compositor)."""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import warp

from server.render.errors import RenderError
from server.render.rgb import DeviceImage, RgbPacker
from server.render.yuv import I420Converter

wp: Any = warp  # warp's host API is unannotated


class ImageOutputs:
    """The last image: `_image` (width, height) and the device buffers `_outputs()` names
    (packed RGBA, float distance along each ray, int32 atom id)."""

    _image: tuple[int, int] | None = None
    _i420: I420Converter | None = None
    _rgb: RgbPacker | None = None
    _host_reads: dict[Any, Any] | None = None

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
        """The first w * h items of a device buffer as an (h, w) host array of the caller's.
        From a CUDA device the copy lands in a page-locked buffer kept for the next read (one
        DMA at the link's rate, where a pageable destination goes through a bounce buffer)."""
        w, h = self._need_image()
        n = w * h
        if not buffer.device.is_cuda:
            out: npt.NDArray[Any] = buffer[:n].numpy().reshape(h, w)
            return out.copy()
        reads = self._host_reads
        if reads is None:
            reads = self._host_reads = {}
        host = reads.get(buffer.dtype)
        if host is None or host.shape[0] < n:
            host = reads[buffer.dtype] = wp.empty(n, dtype=buffer.dtype, device="cpu", pinned=True)
        stream = wp.get_stream(buffer.device)
        wp.copy(host, buffer, count=n, stream=stream)
        wp.synchronize_stream(stream)
        result: npt.NDArray[Any] = host.numpy()[:n].reshape(h, w).copy()
        return result

    def read_rgba(self) -> npt.NDArray[np.uint8]:
        """(height, width, 4) uint8, row 0 at the top."""
        w, h = self._need_image()
        rgba: npt.NDArray[np.uint8] = self._read(self._outputs()[0]).view(np.uint8)
        return rgba.reshape(h, w, 4)

    def read_rgba_into(self, out: npt.NDArray[np.uint8]) -> None:
        """The last image into `out` ((height, width, 4) uint8, C-contiguous): from a CUDA
        device one copy straight into it, at the link's rate when `out` is page-locked (a
        caller that keeps a few such buffers reads images without a host copy)."""
        w, h = self._need_image()
        if out.shape != (h, w, 4) or out.dtype != np.uint8 or not out.flags.c_contiguous:
            raise RenderError(f"read_rgba_into needs a C-contiguous ({h}, {w}, 4) uint8 array")
        buffer = self._outputs()[0]
        if not buffer.device.is_cuda:
            out[...] = self.read_rgba()
            return
        dest = wp.array(out.reshape(-1).view(np.uint32), dtype=wp.uint32, device="cpu", copy=False)
        stream = wp.get_stream(buffer.device)
        wp.copy(dest, buffer, count=w * h, stream=stream)
        wp.synchronize_stream(stream)

    def read_i420(self, size: tuple[int, int]) -> npt.NDArray[np.uint8]:
        """The last image as a video encoder takes it, scaled to `size` (width, height):
        (h * 3 / 2, w) uint8 I420 planes, sides padded to even (`server.render.yuv`)."""
        src = self._need_image()
        rgba = self._outputs()[0]
        if self._i420 is None or self._i420.device != rgba.device:
            self._i420 = I420Converter(rgba.device)
        return self._i420.convert(rgba, src, size)

    def device_rgb(self) -> DeviceImage:
        """The last image as (height, width, 3) RGB in device memory, for an encoder that
        reads it there (`server.render.rgb`); valid until the next call."""
        size = self._need_image()
        rgba = self._outputs()[0]
        if self._rgb is None or self._rgb.device != rgba.device:
            self._rgb = RgbPacker(rgba.device)
        return self._rgb.pack(rgba, size)

    def read_depth(self) -> npt.NDArray[np.float32]:
        """(height, width) float32 distance along each ray; inf where nothing was hit."""
        depth: npt.NDArray[np.float32] = self._read(self._outputs()[1]).astype(np.float32)
        return depth

    def read_atom_ids(self) -> npt.NDArray[np.int32]:
        """(height, width) int32 id of the atom hit (the one contributing most to a density
        at its hit); -1 over the background."""
        ids: npt.NDArray[np.int32] = self._read(self._outputs()[2]).astype(np.int32)
        return ids
