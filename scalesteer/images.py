"""Pictures from the server as numpy arrays and PIL images (Pillow: `pip install
scalesteer[client]`)."""

from __future__ import annotations

import io
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from protocol import Image

if TYPE_CHECKING:
    from PIL.Image import Image as PILImage


def decode(data: bytes, mode: str = "RGB") -> PILImage:
    """A PNG or JPEG as a PIL image in `mode` (`RGB`, `RGBA`, `L`)."""
    from PIL import Image as PILModule

    picture = PILModule.open(io.BytesIO(data))
    picture.load()
    return picture if picture.mode == mode else picture.convert(mode)


def array(data: bytes, mode: str = "RGB") -> npt.NDArray[np.uint8]:
    """A PNG or JPEG as a (height, width, channels) uint8 array."""
    return np.asarray(decode(data, mode), dtype=np.uint8)


@dataclass(frozen=True)
class StreamedImage:
    """One image of a session's live stream (`message`: the server's `image` message)."""

    message: Image

    @property
    def frame_id(self) -> int:
        return self.message.frame_id

    @property
    def step(self) -> int | None:
        """The simulation step it shows."""
        return self.message.step

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.message.width, self.message.height

    @property
    def data(self) -> bytes:
        """The encoded bytes (`message.format`: jpeg or png)."""
        return self.message.data

    def array(self, mode: str = "RGB") -> npt.NDArray[np.uint8]:
        return array(self.message.data, mode)

    def pil(self, mode: str = "RGB") -> Any:
        return decode(self.message.data, mode)

    def __repr__(self) -> str:
        w, h = self.size
        return (
            f"StreamedImage(frame {self.frame_id}, step {self.step}, {w}x{h} {self.message.format})"
        )
