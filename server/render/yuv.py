"""An image as the video encoders take it: 4:2:0 planar YUV (I420), BT.709 limited range, made
on the device from the packed RGBA image and scaled to the stream's size on the way.

Why on the device: a stream keeps its size while renders shrink (an interaction renders half
the canvas), so every interactive frame is scaled up and converted before it is encoded. On the
host that is a swscale pass as long as the encode itself (benchmarks/HISTORY.md, "Video"); here
it is one small kernel and a read-back of the planes (3 MB at 1080p).
"""

from __future__ import annotations

from typing import Any, no_type_check

import numpy as np
import numpy.typing as npt
import warp as wp

# BT.709: luma weights, and the chroma scales of limited ("tv") range in 8 bits
KR, KB = 0.2126, 0.0722
KG = 1.0 - KR - KB


@wp.func
@no_type_check
def _texel(rgba: wp.array[wp.uint32], sw: int, sh: int, x: int, y: int) -> wp.vec3:
    v = rgba[wp.clamp(y, 0, sh - 1) * sw + wp.clamp(x, 0, sw - 1)]
    return wp.vec3(float(v & wp.uint32(255)), float((v >> wp.uint32(8)) & wp.uint32(255)),
                   float((v >> wp.uint32(16)) & wp.uint32(255)))  # fmt: skip


@wp.func
@no_type_check
def _bilinear(rgba: wp.array[wp.uint32], sw: int, sh: int, fx: float, fy: float) -> wp.vec3:
    """The source at (fx, fy) in pixel units (pixel centres at integers), edges clamped."""
    x0 = int(wp.floor(fx))
    y0 = int(wp.floor(fy))
    ax = fx - float(x0)
    ay = fy - float(y0)
    top = _texel(rgba, sw, sh, x0, y0) * (1.0 - ax) + _texel(rgba, sw, sh, x0 + 1, y0) * ax
    bot = _texel(rgba, sw, sh, x0, y0 + 1) * (1.0 - ax) + _texel(rgba, sw, sh, x0 + 1, y0 + 1) * ax
    return top * (1.0 - ay) + bot * ay


@wp.func
@no_type_check
def _luma(c: wp.vec3) -> float:
    return KR * c[0] + KG * c[1] + KB * c[2]


@wp.func
@no_type_check
def _byte(v: float) -> wp.uint8:
    return wp.uint8(int(wp.clamp(wp.floor(v + 0.5), 0.0, 255.0)))


@wp.kernel(enable_backward=False)
@no_type_check
def i420_kernel(
    rgba: wp.array[wp.uint32],
    sw: int,
    sh: int,
    w: int,
    h: int,
    cw: int,
    ch: int,
    out: wp.array[wp.uint8],
):
    """One 2x2 block of the (w, h) picture (w, h even): four luma samples and one chroma pair
    from their mean. `w`, `h` may exceed the picture the source fills (`cw`, `ch`: the part
    it fills; past it rows and columns repeat the last), as an encoder's padding does."""
    bx, by = wp.tid()
    sx = float(sw) / float(cw)
    sy = float(sh) / float(ch)
    total = wp.vec3(0.0, 0.0, 0.0)
    for j in range(2):
        for i in range(2):
            x = wp.min(2 * bx + i, cw - 1)
            y = wp.min(2 * by + j, ch - 1)
            c = _bilinear(rgba, sw, sh, (float(x) + 0.5) * sx - 0.5, (float(y) + 0.5) * sy - 0.5)
            total += c
            out[(2 * by + j) * w + 2 * bx + i] = _byte(16.0 + 219.0 / 255.0 * _luma(c))
    mean = total * 0.25
    luma = _luma(mean)
    cb = (mean[2] - luma) / (2.0 * (1.0 - KB))
    cr = (mean[0] - luma) / (2.0 * (1.0 - KR))
    half = (w // 2) * (h // 2)
    at = w * h + by * (w // 2) + bx
    out[at] = _byte(128.0 + 224.0 / 255.0 * cb)
    out[at + half] = _byte(128.0 + 224.0 / 255.0 * cr)


MAX_SIZES = 4
"""Stream sizes whose buffers a converter keeps (viewers of different canvas sizes take turns
on one renderer; freeing page-locked memory would synchronise the device each time)."""


class I420Converter:
    """Converts a device's RGBA images to I420 at a stream's size; keeps device and
    (page-locked, on CUDA) host buffers per size between frames."""

    def __init__(self, device: Any) -> None:
        self.device = wp.get_device(device)
        self._buffers: dict[tuple[int, int], tuple[wp.array[wp.uint8], Any]] = {}

    def convert(
        self, rgba: wp.array[wp.uint32], src: tuple[int, int], size: tuple[int, int]
    ) -> npt.NDArray[np.uint8]:
        """The (h * 3 / 2, w) I420 planes (Y, then U, then V) of the packed RGBA image `rgba`
        of `src` (width, height), scaled to `size`; odd sides are padded to even by repeating
        the last column and row, as the encoder's own padding does."""
        sw, sh = src
        cw, ch = size
        w, h = cw + cw % 2, ch + ch % 2
        buffers = self._buffers.get((w, h))
        if buffers is None:
            if len(self._buffers) >= MAX_SIZES:
                self._buffers.pop(next(iter(self._buffers)))
            n = w * h * 3 // 2
            buffers = (
                wp.empty(n, dtype=wp.uint8, device=self.device),
                wp.empty(n, dtype=wp.uint8, device="cpu", pinned=self.device.is_cuda),
            )
            self._buffers[(w, h)] = buffers
        dev, host = buffers
        stream = wp.get_stream(self.device) if self.device.is_cuda else None
        wp.launch(
            i420_kernel,
            dim=(w // 2, h // 2),
            inputs=[rgba, sw, sh, w, h, cw, ch],
            outputs=[dev],
            device=self.device,
            stream=stream,
        )
        wp.copy(host, dev, stream=stream)
        if stream is not None:
            wp.synchronize_stream(stream)  # the planes are on the host: nothing else waited
        planes: npt.NDArray[np.uint8] = host.numpy().reshape(h * 3 // 2, w).copy()
        return planes
