"""Whether cells walk for part bounds, chosen by timing both on the renderer's own frames.

The rule of sizes (`tuning.VISIBLE_ATOMS` and the rest) walks every open cell for its part
bounds below 500,000 atoms, faster at most sizes by up to 37 %; but whole cells were 8-16 %
faster at 5,684 and 10,000 atoms (one NVIDIA H200, `render_h200_parts_iso.json`): a window of
the systems measured, not a rule of size. So a CUDA renderer below `tuning.TRIAL_ATOMS` atoms
(where whole cells have ever won) tries both on the frames of each set-up (density, render
mode, image): by turns the rule's choice and whole cells, `FRAMES` frames each after one
unmeasured (its kernels and graph are new). It keeps whole cells only when both the least and
the median of their device times are `MARGIN` below the rule's: other work on the device only
adds time to a frame. Neither changes the image. Only frames that build their grid anyway
(new positions, a new set-up) take turns: on still positions a turn would rebuild the grid
only to time a build the frames after it do not pay, so those frames keep the grid they have
(the renderer's `_choose_parts`). A set-up is its rule's too (the rule changes with the
views of still positions) and its topology's. A choice `EXPIRES` frames old is tried again:
a molecule in motion changes shape, and the two with it.
"""

from __future__ import annotations

import statistics
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass, field

from server.render.tuning import PartMode

FRAMES = 4
"""Measured frames of each choice in a trial (after one unmeasured of each)."""
MARGIN = 0.03
"""How much faster whole cells must be to replace the rule's choice (two medians of four
frames of one set-up differ by about 1 % on an H200)."""
EXPIRES = 5_000
"""Frames after which a set-up's choice is tried again (under two minutes at 60 fps)."""
KEPT = 16
"""Set-ups whose choice is remembered (the least recently seen dropped first)."""


@dataclass
class _Trial:
    rule: PartMode
    times: dict[PartMode, list[float]] = field(default_factory=dict)
    turn: int = 0
    chosen: PartMode | None = None
    at: int = 0
    """The frame count at which `chosen` was decided."""


class PartTrial:
    """The part-bound choice of each set-up: `mode` for a frame about to be rendered,
    `timed` with that frame's device time once it is done."""

    def __init__(
        self, frames: int = FRAMES, margin: float = MARGIN, expires: int = EXPIRES
    ) -> None:
        self.frames = frames
        self.margin = margin
        self.expires = expires
        self._trials: OrderedDict[Hashable, _Trial] = OrderedDict()
        self._frame = 0
        self._pending: tuple[_Trial, PartMode] | None = None

    def mode(self, key: Hashable, rule: PartMode) -> PartMode:
        """The choice for the next frame of set-up `key`, whose rule of sizes says `rule`."""
        self._frame += 1
        self._pending = None
        if rule == "none":
            return rule
        trial = self._trials.get(key)
        stale = trial is not None and trial.chosen is not None
        if trial is None or trial.rule != rule or (stale and self._frame - trial.at > self.expires):
            trial = self._trials[key] = _Trial(rule)
        self._trials.move_to_end(key)
        while len(self._trials) > KEPT:
            self._trials.popitem(last=False)
        if trial.chosen is not None:
            return trial.chosen
        mode: PartMode = rule if trial.turn % 2 == 0 else "none"
        trial.turn += 1
        self._pending = (trial, mode)
        return mode

    def skip(self) -> None:
        """The next frame is none of a trial's (a time taken before it is no one's)."""
        self._pending = None

    def timed(self, ms: float) -> None:
        """The device time of the frame `mode` was last asked for (ignored unless that frame
        was one of a trial's)."""
        if self._pending is None:
            return
        trial, mode = self._pending
        self._pending = None
        trial.times.setdefault(mode, []).append(ms)
        rule, whole = trial.times.get(trial.rule, []), trial.times.get("none", [])
        if min(len(rule), len(whole)) <= self.frames:
            return
        # other work on the device only adds time to a frame: the least of each says what the
        # choice costs, and both the least and the median must favour whole cells
        keep = 1.0 - self.margin
        fewest = min(whole[1:]) < keep * min(rule[1:])
        typical = statistics.median(whole[1:]) < keep * statistics.median(rule[1:])
        trial.chosen = "none" if fewest and typical else trial.rule
        trial.at = self._frame

    def chosen(self, key: Hashable) -> PartMode | None:
        """What set-up `key`'s trial chose (None: none yet)."""
        trial = self._trials.get(key)
        return None if trial is None else trial.chosen
