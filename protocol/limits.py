"""Size limits a peer enforces; the server announces them in `welcome`."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class Limits(BaseModel):
    """What one connection may send. Decoding checks these before allocating anything."""

    model_config = ConfigDict(frozen=True, extra="ignore")

    max_message_bytes: int = Field(default=64 * 1024 * 1024, gt=0)
    max_atoms: int = Field(default=4_000_000, gt=0)
    max_image_side: int = Field(default=4096, gt=0)
    max_image_pixels: int = Field(default=3840 * 2160, gt=0)
    max_steer_per_s: float = Field(default=120.0, gt=0)
    max_forces: int = Field(default=4096, ge=0)


DEFAULT_LIMITS = Limits()

MAX_COORDINATE_A = 1.0e6
"""The largest |coordinate| drawn (Angstrom; 100 micrometres, past any simulation box): float32
steps along a ray lose their meaning far beyond it (at 1e30 A a step no longer moves the ray,
and a frame there had held its render thread for good). A frame with a coordinate beyond it
is drawn as background, and a file with one is refused."""

MAX_CAMERA_A = 1.0e8
"""The farthest a camera may stand from its target, and the tallest orthographic view (A):
100 times `MAX_COORDINATE_A`, beyond which nothing is seen and the arithmetic overflows."""
