"""A one-off image drawn in bands, each band its own turn on its device's thread.

A device's thread takes one piece of work at a time, and live sessions go first only between
pieces (`server.pipeline.turns`). A one-off render drawn as one piece held every live view on
its device for as long as it took: a geodesic image of villin at sigma 4.5 A and 1920x1080 took
484 s on two CPU cores, and a 160x120 image behind it waited 469 s. Drawn in bands, live work
takes its turn between bands; and the bands drawn so far measure what the rest will cost, so a
render that would hold the device past the server's limit is refused after its first bands,
naming the estimate, rather than drawn.

A pixel's cost follows the molecule, not the row: an image whose top rows are empty and whose
bottom rows are dense, sized by the rows before, went from bands of empty rows straight into one
band of 170 s. So the image is weighed first (`footprint`: how many atoms' reach covers each
block of BLOCK x BLOCK pixels, projected through the camera), and a band's work (its ray cast,
as the renderer times its stages) is taken as `a` a pixel plus `b` a unit of cover: `a` from the
bands no atom covers, `b` from the others. The rest of a band's time (its dispatch, uploads,
compositing, reading back) is `c`, the same whatever it draws: on two busy CPU cores some 45 ms
a band of a small image, and taken for work, the first bands' few rows said that a 320x240
image of a second or so would take 139 s. A band is the run of pixels, in row order, whose work
is expected to take BAND_SECONDS (and at most GROWTH times the band before's): whole rows, or
part of one row when a row takes longer (a band is a rectangle, `(x0, y0, w, h)`).

The first band is whole rows holding FIRST_SHARE of the cover: it also builds the frame's grids
and may compile kernels, so its time is not counted, and its rate (too high) only sizes the next
band. After each later band, the time the bands after the first took, plus the pixels and cover
left at their rates (`b` the mean over the covered bands) and `c` (their mean) for each band
left, must stay within the limit once they have taken JUDGED_AFTER_S (a rate from a few bands
of little work is mostly noise); past the limit in time alone, the render is refused whatever
is left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from server.render.errors import CapacityError

FIRST_SHARE = 1.0 / 4096.0
"""The first band's share of the image's cover: its time, the grids' build aside, is this
share of the whole image's, which nothing bounds before it is drawn (1/128 of an image that
would take 7,300 s took 61 s)."""
BAND_SECONDS = 0.1
"""Ray-cast time each later band is sized to (a band's fixed time, `BandPlan.c`, comes on
top): about what a live view waits behind one."""
GROWTH = 4.0
"""Most a band's expected time grows over the time of the one before (the cover is an estimate
of where the time goes)."""
GROWN_FROM = 0.025
"""Bands shorter than this grow as if they took this long: on a GPU a band's fixed costs are a
millisecond or so, and growing from there took villin at 1920x1080 2.2 times as long as drawn
whole (`results/latency_h200_oneoff_bands.json`)."""
JUDGED_AFTER_S = 0.5
"""Device seconds of bands after the first before their rate may refuse the rest."""
BLOCK = 8
"""Pixels a side of the blocks the weights are kept in."""
WEIGHED_ATOMS = 1 << 16
"""Most atoms `footprint` projects (every k-th of a larger system, each counting k): the cover
is an estimate, and 1M atoms took 0.2 s of two CPU cores."""
MIN_SEGMENT = 16
"""Fewest pixels of a band that is part of a row (a row of the last few pixels excepted)."""

Tile = tuple[int, int, int, int]


class TooCostlyError(CapacityError):
    """A one-off render whose measured bands say the whole would hold its device past the
    server's limit."""


def footprint(
    positions: npt.NDArray[np.float32], frame: Any, reach: float
) -> npt.NDArray[np.float64]:
    """(ceil(h / BLOCK), ceil(w / BLOCK)) weights of the image's blocks: how many atoms' reach
    (in A) covers each, projected through `frame` (a `camera.CameraFrame`; the atoms' depth
    sets their reach in pixels, taken at the median; at most WEIGHED_ATOMS of them)."""
    w, h = int(frame.width), int(frame.height)
    bw, bh = -(-w // BLOCK), -(-h // BLOCK)
    atoms = np.asarray(positions).reshape(-1, 3)
    step = max(1, -(-len(atoms) // WEIGHED_ATOMS))
    d = atoms[::step].astype(np.float64) - frame.eye
    z = d @ frame.forward
    u, v = d @ frame.right, d @ frame.up
    if not frame.ortho:
        ahead = z > 1e-6
        u, v, z = u[ahead] / z[ahead], v[ahead] / z[ahead], z[ahead]
    x = (u / (frame.aspect * frame.scale) + 1.0) * (0.5 * w)
    y = (1.0 - v / frame.scale) * (0.5 * h)
    if len(z) == 0:
        return np.zeros((bh, bw))
    per_a = 0.5 * h / frame.scale / (1.0 if frame.ortho else max(float(np.median(z)), 1e-6))
    # a reach past the image covers all of it: no wider box (a tiny ortho_height asked for
    # a box of 110 GiB)
    r = int(min(max(0.0, math.ceil(reach * per_a / BLOCK)), max(bw, bh)))
    counts, _, _ = np.histogram2d(
        y / BLOCK, x / BLOCK, bins=(bh + 2 * r, bw + 2 * r), range=((-r, bh + r), (-r, bw + r))
    )
    # a box of (2r + 1)^2 blocks around each atom's block, by summed-area table
    table = np.zeros((counts.shape[0] + 1, counts.shape[1] + 1))
    table[1:, 1:] = counts.cumsum(axis=0).cumsum(axis=1)
    k = 2 * r + 1
    box = table[k:, k:] - table[:-k, k:] - table[k:, :-k] + table[:-k, :-k]
    return np.asarray(box[:bh, :bw] * step, dtype=np.float64)


@dataclass
class BandPlan:
    """Where a one-off image's bands lie. `blocks`: how many atoms cover each BLOCK x BLOCK
    block of the image (`footprint`); `limit_s`: the most device seconds the bands after the
    first may take in all; `advice`: what a refusal suggests.

    A band's work is taken as `a` a pixel plus `b` a unit of cover (an atom over a pixel): `a`
    from the bands that no atom covers, `b` from the others, the newest first; the first band
    (the grids' build in it) gives `b` until another has. The rest of its time, `c`, is the
    same for every band."""

    width: int
    height: int
    limit_s: float
    blocks: npt.NDArray[np.float64] | None = None
    advice: str = "ask for a smaller image"
    x: int = 0
    y: int = 0
    """The first pixel not drawn yet (row y, column x)."""
    spent_s: float = 0.0
    """Device seconds of the bands after the first."""
    bands: int = 0
    a: float = 0.0
    """Seconds a pixel no atom covers."""
    b: float = 0.0
    """Seconds a unit of cover (for sizing bands)."""
    c: float = 0.0
    """Seconds a band takes beside its work (the mean over the bands after the first)."""
    _cover_s: float = 0.0
    _cover_w: float = 0.0
    """Seconds (less `a` a pixel) and cover of the covered bands after the first."""
    _cols: npt.NDArray[np.float64] = field(init=False, repr=False)
    """A pixel's cover in each block row, by column."""
    _row_cum: npt.NDArray[np.float64] = field(init=False, repr=False)
    """The cover of rows [0, y), by y."""

    def __post_init__(self) -> None:
        bw, bh = -(-self.width // BLOCK), -(-self.height // BLOCK)
        blocks = np.zeros((bh, bw)) if self.blocks is None else np.asarray(self.blocks)
        self._cols = np.repeat(blocks.astype(np.float64), BLOCK, axis=1)[:, : self.width]
        rows = np.repeat(self._cols.sum(axis=1), BLOCK)[: self.height]
        self._row_cum = np.concatenate([[0.0], np.cumsum(rows)])
        self.cover = float(self._row_cum[-1])

    @property
    def done(self) -> bool:
        return self.y >= self.height

    def _cover(self, tile: Tile) -> float:
        x0, y0, w, h = tile
        if x0 == 0 and w == self.width:
            return float(self._row_cum[y0 + h] - self._row_cum[y0])
        return float(self._cols[y0 // BLOCK][x0 : x0 + w].sum())

    def _left(self) -> tuple[int, float]:
        """(pixels, cover) not drawn yet."""
        if self.done:
            return 0, 0.0
        drawn = self._cols[self.y // BLOCK][: self.x].sum()
        pixels = (self.height - self.y) * self.width - self.x
        return pixels, float(self.cover - self._row_cum[self.y] - drawn)

    def estimate(self, tile: Tile) -> float:
        """Seconds `tile` is expected to take."""
        return self.a * tile[2] * tile[3] + self.b * self._cover(tile)

    def first(self) -> Tile:
        """The first band: the rows from the top holding FIRST_SHARE of the cover (of the
        pixels, where no atom covers the image); part of the first row when it holds more."""
        if self.cover > 0.0:
            want = self.cover * FIRST_SHARE
            rows = int(np.searchsorted(self._row_cum, want, side="left"))
            if rows <= 1 and self._row_cum[1] > want:
                n = int(np.searchsorted(np.cumsum(self._cols[0]), want, side="left")) + 1
                return self._segment(0, n)
        else:
            rows = math.ceil(self.height * FIRST_SHARE)
            if self.height * FIRST_SHARE < 1.0:
                return self._segment(0, math.ceil(self.width * self.height * FIRST_SHARE))
        return (0, 0, self.width, max(1, min(self.height, rows)))

    def _segment(self, x: int, n: int) -> Tile:
        """Part of row y from column x: n pixels, at least MIN_SEGMENT, and the rest of the
        row when fewer than MIN_SEGMENT would be left."""
        n = min(max(n, MIN_SEGMENT), self.width - x)
        if self.width - x - n < MIN_SEGMENT:
            n = self.width - x
        return (x, self.y, n, 1)

    def drawn(self, tile: Tile, seconds: float, work: float | None = None) -> Tile | None:
        """Note `tile` (the band `first` or the last `drawn` gave) drawn in `seconds` of the
        device, `work` of them its ray cast (None: all of them); the next band, None once the
        image is whole. Raises TooCostlyError when the rest, at the rates measured, would take
        the bands after the first past `limit_s`."""
        work = seconds if work is None else min(max(work, 0.0), seconds)
        x0, y0, w, h = tile
        cover = self._cover(tile)
        if x0 == 0 and w == self.width:
            self.x, self.y = 0, y0 + h
        else:
            self.x, self.y = (x0 + w, y0) if x0 + w < self.width else (0, y0 + 1)
        self.bands += 1
        if self.bands == 1:  # the grids' build is in it: rates for sizing, not for judging
            if cover > 0.0:
                self.b = work / cover
            else:
                self.a = work / (w * h)
            return None if self.done else self._band(GROWTH * max(work, GROWN_FROM))
        self.spent_s += seconds
        self.c += (seconds - work - self.c) / (self.bands - 1)
        if cover > 0.0:
            share = max(work - self.a * w * h, 0.0)
            self._cover_s += share
            self._cover_w += cover
            # sized by the dearer of the newest band's rate and the mean (the molecule may
            # begin here); the mean judges the rest
            self.b = max(share / cover, self._cover_s / self._cover_w)
        else:
            self.a = max(self.a if self.bands > 2 else 0.0, work / (w * h))
        if self.done:
            return None
        pixels, left = self._left()
        mean_b = self._cover_s / self._cover_w if self._cover_w > 0.0 else None
        projected = self.spent_s + self.a * pixels + (mean_b or 0.0) * left
        projected += self.c * self._bands_left()
        judged = mean_b is not None or left == 0.0
        if self.spent_s > self.limit_s or (
            judged and self.spent_s >= JUDGED_AFTER_S and projected > self.limit_s
        ):
            raise TooCostlyError(
                f"this {self.width}x{self.height} image would hold the device for about "
                f"{max(projected, self.spent_s):,.0f} s (measured on {self.bands - 1} bands "
                f"after the first, {self.spent_s:.1f} s, the rest weighed by how many atoms "
                f"cover each pixel), over this server's limit of {self.limit_s:g} s for one "
                f"image (one_off_render_seconds); {self.advice}"
            )
        return self._band(GROWTH * max(work, GROWN_FROM))

    def _bands_left(self) -> int:
        """About how many bands `_band` will cut the rows left into at the rates that size
        them: a band takes whole rows, so a row of work w (seconds) is 1 / floor(BAND_SECONDS
        / w) of a band, or ceil(w / BAND_SECONDS) parts of a row past BAND_SECONDS."""
        if self.done:
            return 0
        cover = np.diff(self._row_cum[self.y :])
        work = self.a * self.width + self.b * cover
        work = work[work > 0.0]
        whole = work <= BAND_SECONDS
        rows = float(np.sum(1.0 / np.floor(BAND_SECONDS / work[whole])))
        return math.ceil(rows + float(np.sum(np.ceil(work[~whole] / BAND_SECONDS))))

    def _band(self, most: float) -> Tile:
        """The run of pixels from (x, y) whose work is expected to take at most BAND_SECONDS
        (and `most`): the rest of a started row, whole rows, or (a row dearer than that) part
        of a row."""
        limit = min(BAND_SECONDS, most)
        y = self.y
        if self.x == 0:
            cost = self.a * self.width * np.arange(self.height - y + 1)
            cost = cost + self.b * (self._row_cum[y:] - self._row_cum[y])
            rows = int(np.searchsorted(cost, limit, side="right")) - 1
            if rows >= 1:
                return (0, y, self.width, rows)
        row = self._cols[y // BLOCK][self.x :]
        cost = np.cumsum(self.a + self.b * row)
        return self._segment(self.x, int(np.searchsorted(cost, limit, side="right")))


def reach_of(params: Any, layers: Any = None) -> float:
    """How far (A) an atom's density reaches under `params` (a `RenderParams`), or under the
    widest of `layers` (`LayerPlan`s, the visible ones) when given: the footprint's radius."""
    if layers:
        return float(max(p.params.sigma_A * p.params.cutoff_sigmas for p in layers))
    return float(params.sigma_A * params.cutoff_sigmas)


def advice_for(params: Any) -> str:
    """What a refusal of a render with `params` suggests."""
    if params.scale_space != "classical":
        return "ask for a smaller image, a smaller sigma or the classical density"
    if params.mode == "volume":
        return "ask for a smaller image, a lower quality or a larger step"
    return "ask for a smaller image or a smaller sigma"
