"""An image as a JPEG encoder on the device takes it: interleaved 8-bit RGB, (height, width, 3),
packed on the device from the renderer's RGBA image.

Why: a JPEG encoded where the image already is (nvJPEG through nvImageCodec) brings back only
its bytes; encoding on the host first reads the whole RGBA image back and then spends a CPU
thread on it (benchmarks/README.md, "Latency"). nvJPEG takes three interleaved channels, not
four, hence this one small kernel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, no_type_check

import numpy as np
import numpy.typing as npt
import warp as wp


@wp.kernel(enable_backward=False)
@no_type_check
def rgb_kernel(rgba: wp.array[wp.uint32], out: wp.array[wp.uint8]):
    """One pixel: its red, green and blue bytes, alpha dropped."""
    i = wp.tid()
    v = rgba[i]
    out[3 * i] = wp.uint8(v & wp.uint32(255))
    out[3 * i + 1] = wp.uint8((v >> wp.uint32(8)) & wp.uint32(255))
    out[3 * i + 2] = wp.uint8((v >> wp.uint32(16)) & wp.uint32(255))


@dataclass(frozen=True)
class DeviceImage:
    """An (height, width, 3) uint8 RGB image in device memory, valid until the next image is
    packed. On a CUDA device it exposes `__cuda_array_interface__` (read it on `stream`, the
    CUDA stream handle its kernel ran on); on the CPU device `numpy()` reads it."""

    array: Any
    """A warp uint8 array of shape (height, width, 3)."""
    stream: int
    """The CUDA stream handle the image was written on (0 on the CPU device)."""

    @property
    def __cuda_array_interface__(self) -> dict[str, Any]:
        cai: dict[str, Any] = self.array.__cuda_array_interface__
        return cai

    @property
    def shape(self) -> tuple[int, int, int]:
        h, w, c = self.array.shape
        return int(h), int(w), int(c)

    def numpy(self) -> npt.NDArray[np.uint8]:
        out: npt.NDArray[np.uint8] = self.array.numpy()
        return out


class RgbPacker:
    """Packs a device's RGBA images into one RGB buffer kept between frames (grown, never
    shrunk: interactive and still sizes take turns)."""

    def __init__(self, device: Any) -> None:
        self.device = wp.get_device(device)
        self._buffer: wp.array[wp.uint8] | None = None

    def pack(self, rgba: wp.array[wp.uint32], size: tuple[int, int]) -> DeviceImage:
        """The first width * height pixels of the packed RGBA image `rgba` as RGB."""
        w, h = size
        n = w * h
        buffer = self._buffer
        if buffer is None or buffer.shape[0] < 3 * n:
            buffer = self._buffer = wp.empty(3 * n, dtype=wp.uint8, device=self.device)
        stream = wp.get_stream(self.device) if self.device.is_cuda else None
        wp.launch(rgb_kernel, dim=n, inputs=[rgba], outputs=[buffer], device=self.device,
                  stream=stream)  # fmt: skip
        view: wp.array[wp.uint8] = wp.array(
            ptr=buffer.ptr, dtype=wp.uint8, shape=(h, w, 3), device=self.device
        )
        return DeviceImage(view, stream.cuda_stream if stream is not None else 0)
