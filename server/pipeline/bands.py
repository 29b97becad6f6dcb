"""A one-off image drawn in bands of rows, each band its own turn on its device's thread.

A device's thread takes one piece of work at a time, and live sessions go first only between
pieces (`server.pipeline.turns`). A one-off render drawn as one piece held every live view on
its device for as long as it took: a geodesic image of villin at sigma 4.5 A and 1920x1080 took
484 s on two CPU cores, and a 160x120 image behind it waited 469 s. Drawn in bands, live work
takes its turn between bands; and the bands drawn so far measure what the rest will cost, so a
render that would hold the device past the server's limit is refused after its first bands,
naming the estimate, rather than drawn.

The first band is a small share of the rows (FIRST_SHARE): it also builds the frame's grids and
may compile kernels, so it is neither counted against the limit nor judged. Every later band is
sized from the one before to about BAND_SECONDS of the device, and after each the device time of
the bands after the first, plus the rows left at the last band's rate, must stay within the
limit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from server.render.errors import CapacityError

FIRST_SHARE = 1.0 / 128.0
"""The first band's share of the image's rows (one row at least): it is not judged, so it is
what a render past every limit still costs (about 4 s of two CPU cores for the image above)."""
BAND_SECONDS = 0.1
"""Device time each later band is sized to: about what a live view waits behind one."""
GROWTH = 8.0
"""Most a band grows over the one before (a band of few rows times mostly its fixed costs)."""


class TooCostlyError(CapacityError):
    """A one-off render whose measured bands say the whole would hold its device past the
    server's limit."""


@dataclass
class BandPlan:
    """Where a one-off image's bands start and how many rows each takes. `limit_s`: the most
    device seconds the bands after the first may take in all."""

    width: int
    height: int
    limit_s: float
    y: int = 0
    """The first row not drawn yet."""
    spent_s: float = 0.0
    """Device seconds of the bands after the first."""
    bands: int = 0

    def first(self) -> int:
        """The first band's rows."""
        return max(1, min(self.height, math.ceil(self.height * FIRST_SHARE)))

    def drawn(self, rows: int, seconds: float) -> int:
        """Note a band of `rows` rows just drawn at row `y` in `seconds` of the device; the next
        band's rows, 0 once the image is whole. Raises TooCostlyError when the rest at this band's
        rate would take the bands after the first past `limit_s`."""
        self.y += rows
        if self.bands:
            self.spent_s += seconds
        self.bands += 1
        left = self.height - self.y
        if left <= 0:
            return 0
        rate = max(seconds, 1e-6) / rows
        if self.bands > 1:
            projected = self.spent_s + rate * left
            if projected > self.limit_s:
                raise TooCostlyError(
                    f"this {self.width}x{self.height} image would hold the device for about "
                    f"{projected:,.0f} s ({rate * 1000:,.1f} ms a row, measured on its rows "
                    f"{self.y - rows}-{self.y - 1}), over this server's limit of "
                    f"{self.limit_s:g} s for one image (one_off_render_seconds); ask for a "
                    "smaller image, a smaller sigma or the classical density"
                )
        grown = max(1, math.floor(rows * GROWTH))
        return max(1, min(left, grown, math.floor(BAND_SECONDS / rate)))
