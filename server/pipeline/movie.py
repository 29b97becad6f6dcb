"""Writers for batch-render output: a zip of PNGs or an H.264 MP4 (PyAV).

Both write to a temporary path; `close()` finishes the file and only then moves it into place,
so a reader never sees a truncated result reported as done.
"""

from __future__ import annotations

import os
import zipfile
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt


class FrameWriter(Protocol):
    def add(self, index: int, rgba: npt.NDArray[np.uint8], png: bytes | None) -> None: ...
    def close(self) -> None: ...
    def abort(self) -> None: ...


class ZipWriter:
    """frame_000000.png, ... in a zip (stored: PNG is already compressed)."""

    needs_png = True

    def __init__(self, final: Path) -> None:
        self.final = final
        self.tmp = final.with_suffix(final.suffix + ".part")
        self._zip = zipfile.ZipFile(self.tmp, "w", compression=zipfile.ZIP_STORED)

    def add(self, index: int, rgba: npt.NDArray[np.uint8], png: bytes | None) -> None:
        assert png is not None
        self._zip.writestr(f"frame_{index:06d}.png", png)

    def close(self) -> None:
        self._zip.close()
        os.replace(self.tmp, self.final)

    def abort(self) -> None:
        self._zip.close()
        self.tmp.unlink(missing_ok=True)


class Mp4Writer:
    """H.264 (yuv420p) at `fps`; odd image sizes are padded by one pixel."""

    needs_png = False

    def __init__(self, final: Path, fps: float, width: int, height: int) -> None:
        import av

        self.final = final
        self.tmp = final.with_suffix(".part.mp4")
        self._container: Any = av.open(str(self.tmp), mode="w")
        self._stream: Any = self._container.add_stream("libx264", rate=round(fps))
        self._stream.width = width + (width % 2)
        self._stream.height = height + (height % 2)
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": "18", "preset": "veryfast"}

    def add(self, index: int, rgba: npt.NDArray[np.uint8], png: bytes | None) -> None:
        import av

        h, w = rgba.shape[:2]
        rgb = np.zeros((self._stream.height, self._stream.width, 3), dtype=np.uint8)
        rgb[:h, :w] = rgba[..., :3]
        frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)

    def close(self) -> None:
        for packet in self._stream.encode():
            self._container.mux(packet)
        self._container.close()
        os.replace(self.tmp, self.final)

    def abort(self) -> None:
        try:
            self._container.close()
        finally:
            self.tmp.unlink(missing_ok=True)
