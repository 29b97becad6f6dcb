"""Image encoding (JPEG for streaming, PNG for lossless stills), run off the event loop.

Pillow (libjpeg-turbo) is always there. It reads the renderer's RGBA pixels in place (as RGBX)
and encodes into a per-thread in-memory file: Pillow releases the GIL only when it encodes to a
file descriptor, so encoder threads then run in parallel with each other and the event loop.

With the `gpu-jpeg` extra installed and a CUDA render device, JPEG goes through nvImageCodec
(nvJPEG) on that GPU instead: a live session's render lane encodes its image where it was
rendered and reads back only the JPEG (`GpuQueue.jpeg`), other images are encoded from the host.
If it fails at run time the server logs a warning and stays on Pillow. `ImageEncoder.describe()`
names the encoder in use (shown by /healthz).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import os
import tempfile
import threading
import time
from typing import TYPE_CHECKING, Any, BinaryIO, Literal, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
from PIL import Image

if TYPE_CHECKING:
    from server.render.rgb import DeviceImage

log = logging.getLogger("scalesteer.encoder")

Format = Literal["jpeg", "png"]
PILLOW = "pillow-libjpeg-turbo"


class JpegBackend(Protocol):
    """A JPEG encoder other than Pillow; it must be safe to call from several threads."""

    name: str

    def encode(self, rgba: npt.NDArray[np.uint8], quality: int) -> bytes: ...


def _subsampling_444(quality: int) -> bool:
    """4:4:4 chroma from quality 90 up, 4:2:0 below (what the stream has always used)."""
    return quality >= 90


class _Scratch:
    """A thread's reusable in-memory file: a real descriptor, so Pillow drops the GIL."""

    def __init__(self) -> None:
        if hasattr(os, "memfd_create"):
            self.fd = os.memfd_create("scalesteer-encode", os.MFD_CLOEXEC)
        else:
            self.fd, path = tempfile.mkstemp(prefix="scalesteer-encode-")
            os.unlink(path)
        # the descriptor is this object's: it closes when the thread (and so this) goes
        self.file: BinaryIO = open(self.fd, "w+b", buffering=0, closefd=False)  # noqa: SIM115

    def __del__(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.fd)

    def save(self, image: Image.Image, **options: Any) -> bytes:
        f = self.file
        f.seek(0)
        f.truncate()
        image.save(f, **options)
        return os.pread(self.fd, f.tell(), 0)


_local = threading.local()


def _save(image: Image.Image, **options: Any) -> bytes:
    scratch: _Scratch | None = getattr(_local, "scratch", None)
    if scratch is None:
        scratch = _local.scratch = _Scratch()
    return scratch.save(image, **options)


def _as_pillow(rgba: npt.NDArray[np.uint8], mode: str) -> Image.Image:
    """A Pillow image over the same memory (no copy) for an (h, w, 4) uint8 array."""
    a = np.ascontiguousarray(rgba, dtype=np.uint8)
    if a.ndim != 3 or a.shape[2] != 4:
        raise ValueError(f"expected an (h, w, 4) RGBA array, got shape {a.shape}")
    h, w = a.shape[:2]
    return Image.frombuffer(mode, (w, h), a, "raw", mode, 0, 1)


def pillow_jpeg(rgba: npt.NDArray[np.uint8], quality: int) -> bytes:
    """JPEG of the RGB channels; alpha is ignored (read in place as the padding byte of RGBX)."""
    image = _as_pillow(rgba, "RGBX")
    return _save(
        image,
        format="JPEG",
        quality=int(quality),
        subsampling=0 if _subsampling_444(quality) else 2,
    )


def pillow_png(rgba: npt.NDArray[np.uint8]) -> bytes:
    return _save(_as_pillow(rgba, "RGBA"), format="PNG", compress_level=3)


def encode_image(
    rgba: npt.NDArray[np.uint8], fmt: Format, quality: int = 85
) -> tuple[bytes, float]:
    """Encode an (h, w, 4) RGBA image with Pillow; returns the bytes and the time taken in ms."""
    t0 = time.perf_counter()
    data = pillow_jpeg(rgba, quality) if fmt == "jpeg" else pillow_png(rgba)
    return data, (time.perf_counter() - t0) * 1000.0


@runtime_checkable
class DeviceJpeg(Protocol):
    """A JPEG encoder that reads images in the memory of the device they were rendered on
    (`server.render.rgb`), so that only the JPEG's bytes come back to the host."""

    name: str
    device: str
    """The render device whose images it reads ("cuda:0")."""

    def encode_on_device(self, image: DeviceImage, quality: int) -> bytes: ...


class NvJpeg:
    """nvImageCodec's JPEG encoder on one CUDA device; one nvimgcodec Encoder per thread. It
    encodes host images (`encode`) and images still on the device (`encode_on_device`).

    Raises ImportError when nvImageCodec is not installed, RuntimeError when it cannot run on
    the device (both at construction, so selection can fall back before any frame).
    """

    def __init__(self, device_id: int = 0) -> None:
        from nvidia import nvimgcodec

        self._nv: Any = nvimgcodec
        self._device_id = device_id
        self.device = f"cuda:{device_id}"
        self._local = threading.local()
        self.name = f"nvimagecodec-nvjpeg (cuda:{device_id})"
        probe = np.zeros((8, 8, 4), np.uint8)
        self.encode(probe, 85)

    def _encoder(self) -> Any:
        enc = getattr(self._local, "encoder", None)
        if enc is None:
            nv = self._nv
            kinds = nv.BackendKind
            enc = self._local.encoder = nv.Encoder(
                device_id=self._device_id,
                # our encoder pool already runs one encode per thread
                max_num_cpu_threads=1,
                # nvJPEG's CUDA encoder is a hybrid backend; nvImageCodec's own CPU codecs are
                # left out so that a GPU failure shows instead of a silent CPU encode
                backends=[
                    nv.Backend(kinds.GPU_ONLY),
                    nv.Backend(kinds.HYBRID_CPU_GPU),
                    nv.Backend(kinds.HW_GPU_ONLY),
                ],
            )
        return enc

    def _params(self, quality: int) -> Any:
        nv = self._nv
        css = nv.ChromaSubsampling
        return nv.EncodeParams(
            quality_type=nv.QualityType.QUALITY,
            quality_value=float(quality),
            chroma_subsampling=css.CSS_444 if _subsampling_444(quality) else css.CSS_420,
        )

    def encode(self, rgba: npt.NDArray[np.uint8], quality: int) -> bytes:
        image = _as_pillow(rgba, "RGBX")
        # Pillow packs RGBX to RGB several times faster than numpy copies the strided view
        rgb = np.frombuffer(image.tobytes("raw", "RGB"), np.uint8).reshape(*rgba.shape[:2], 3)
        encoded = self._encoder().encode(
            rgb, "jpeg", params=self._params(quality), cuda_stream=self._stream()
        )
        return self._bytes(encoded)

    def _stream(self) -> int:
        """This thread's own CUDA stream for host images. Never the legacy default stream:
        used while a render lane captures a CUDA graph on the device, it fails the encode and
        the capture both (CUDA error 906, the legacy stream's implicit dependency)."""
        stream = getattr(self._local, "stream", None)
        if stream is None:
            import warp as wp

            stream = self._local.stream = wp.Stream(self.device)
        handle: int = stream.cuda_stream
        return handle

    def encode_on_device(self, image: DeviceImage, quality: int) -> bytes:
        """JPEG of an RGB image in this device's memory, read on the stream that wrote it."""
        nv = self._nv
        source = nv.as_image(image, cuda_stream=image.stream)
        encoded = self._encoder().encode(
            source, "jpeg", params=self._params(quality), cuda_stream=image.stream
        )
        return self._bytes(encoded)

    @staticmethod
    def _bytes(encoded: Any) -> bytes:
        if encoded is None:
            raise RuntimeError("nvImageCodec could not encode the image")
        return bytes(encoded)


class ImageEncoder:
    """What the server encodes with: JPEG by the selected backend, PNG by Pillow.

    A GPU backend that fails is dropped for good (one warning) and the image is encoded again
    with Pillow, so a viewer never misses a frame because of it.
    """

    def __init__(self, jpeg: JpegBackend | None = None) -> None:
        self._jpeg = jpeg
        self._lock = threading.Lock()

    @property
    def backend(self) -> JpegBackend | None:
        """The JPEG encoder other than Pillow in use (None: Pillow)."""
        return self._jpeg

    @backend.setter
    def backend(self, jpeg: JpegBackend | None) -> None:
        with self._lock:
            self._jpeg = jpeg

    def describe(self) -> str:
        backend = self._jpeg
        return backend.name if backend is not None else PILLOW

    def on_device(self) -> DeviceJpeg | None:
        """The backend that can also encode images where they were rendered, if the one in
        use can (the render lanes of its device then encode their JPEGs themselves)."""
        backend = self._jpeg
        return backend if isinstance(backend, DeviceJpeg) else None

    def encode(
        self, rgba: npt.NDArray[np.uint8], fmt: Format, quality: int = 85
    ) -> tuple[bytes, float]:
        """Encode an (h, w, 4) RGBA image; returns the bytes and the time taken in ms."""
        backend = self._jpeg
        if fmt == "jpeg" and backend is not None:
            t0 = time.perf_counter()
            try:
                data = backend.encode(rgba, quality)
            except Exception as exc:
                self._give_up(backend, exc)
            else:
                return data, (time.perf_counter() - t0) * 1000.0
        return encode_image(rgba, fmt, quality)

    def _give_up(self, backend: JpegBackend, exc: Exception) -> None:
        with self._lock:
            if self._jpeg is backend:
                self._jpeg = None
                log.warning(
                    "JPEG encoder %s failed (%s: %s); falling back to %s",
                    backend.name,
                    type(exc).__name__,
                    exc,
                    PILLOW,
                )


def cuda_device_count() -> int:
    """CUDA devices the driver reports (0 without a driver), without importing a framework."""
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return 0
    count = ctypes.c_int(0)
    if cuda.cuInit(0) != 0 or cuda.cuDeviceGetCount(ctypes.byref(count)) != 0:
        return 0
    return int(count.value)


def cuda_index(device: str) -> int | None:
    """The CUDA ordinal a render device names ('cuda' and 'cuda:N'); None for other devices.

    'auto' renders on the first CUDA device when there is one, so it counts as 'cuda:0' then.
    """
    if device == "auto":
        return 0 if cuda_device_count() > 0 else None
    if device == "cuda":
        return 0
    if device.startswith("cuda:") and device[5:].isdigit():
        return int(device[5:])
    return None


def select_encoder(device: str, gpu: type[NvJpeg] | Any = NvJpeg) -> ImageEncoder:
    """The encoder for a render device: nvImageCodec on a CUDA device when it works, else Pillow.

    `gpu` builds the GPU backend from a CUDA ordinal (tests pass a stand-in).
    """
    index = cuda_index(device)
    if index is None:
        return ImageEncoder()
    try:
        backend: JpegBackend = gpu(index)
    except ImportError:
        log.info("nvImageCodec is not installed (extra 'gpu-jpeg'); JPEG is encoded by Pillow")
        return ImageEncoder()
    except Exception as exc:
        log.warning(
            "GPU JPEG encoder unavailable on %s (%s: %s); using %s",
            device,
            type(exc).__name__,
            exc,
            PILLOW,
        )
        return ImageEncoder()
    log.info("JPEG encoder: %s", backend.name)
    return ImageEncoder(backend)
