"""Image encoding (JPEG for streaming, PNG for lossless stills), run off the event loop.

Pillow's JPEG encoder is libjpeg-turbo; `describe()` names the encoder in use.
"""

from __future__ import annotations

import io
import time
from typing import Literal

import numpy as np
import numpy.typing as npt
from PIL import Image

Format = Literal["jpeg", "png"]


def encode_image(
    rgba: npt.NDArray[np.uint8], fmt: Format, quality: int = 85
) -> tuple[bytes, float]:
    """Encode an (h, w, 4) RGBA image; returns the bytes and the time taken in ms."""
    t0 = time.perf_counter()
    buf = io.BytesIO()
    if fmt == "jpeg":
        Image.fromarray(np.ascontiguousarray(rgba[..., :3])).save(
            buf, format="JPEG", quality=int(quality), subsampling=2 if quality < 90 else 0
        )
    else:
        Image.fromarray(rgba).save(buf, format="PNG", compress_level=3)
    return buf.getvalue(), (time.perf_counter() - t0) * 1000.0


def describe() -> str:
    return "pillow-libjpeg-turbo"
