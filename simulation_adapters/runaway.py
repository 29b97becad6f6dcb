"""The runaway guard's judgement: is a reported temperature a blow-up, or a run that heats or
cools as it should?

A blow-up heats faster and faster. A thermostat heats a cold start more and more slowly
(towards its target), and a run hotter than its thermostat (a hot start, or a steered change to
a lower temperature) cools. So a temperature is compared with two references: the engine's own
thermostat target where it reports one, and the run's recent level, the mean of the last
`window` calm reports (the first report is where the run starts: a hot start is no blow-up).
It is a runaway only when it is far above both (`runaway_limit`: twice the reference, and at
least 300 K above it). A rise that slows down never doubles its own trailing mean (the mean of
a concave rise over any window is at least half its end), so a cold start heating to its
thermostat never trips the guard, whatever its target; an accelerating rise does.

That holds for reports dense enough to follow the rise. An engine that reports every few
picoseconds may report 3 K and then 311 K: a step no trailing mean can tell from a blow-up. So
without a thermostat target, a temperature that thermostats hold runs at (up to `ORDINARY_K`)
is never a runaway by itself; a blow-up passes it within a few steps (thousands of kelvin).
With a target the target's limit stands alone (a cold start cannot pass twice its target).
"""

from __future__ import annotations

import math
from collections import deque

WINDOW = 32
"""Calm reports the run's recent level is the mean of."""
ORDINARY_K = 1000.0
"""Without a thermostat target, no temperature up to this trips the guard (high-temperature
unfolding runs at 500-800 K)."""


def runaway_limit(reference_K: float) -> float:
    """The temperature above which a run held at `reference_K` has blown up."""
    return max(2.0 * reference_K, reference_K + 300.0)


class RunawayGuard:
    """Judges each reported temperature against the thermostat's target and the run's own
    recent level. `limit_K` (a user's absolute limit) replaces both when given."""

    def __init__(self, limit_K: float | None = None, window: int = WINDOW) -> None:
        self.limit_K = limit_K
        self._recent: deque[float] = deque(maxlen=max(1, int(window)))

    @property
    def level(self) -> float | None:
        """The run's recent level: the mean of the last calm reports (None before any)."""
        return math.fsum(self._recent) / len(self._recent) if self._recent else None

    def limit(self, target_K: float | None = None) -> float | None:
        """The temperature that trips the guard now; None before the first report, which is
        where the run starts (a hot start is no blow-up) and becomes its level."""
        if self.limit_K is not None:
            return self.limit_K
        level = self.level
        if level is None:
            return None
        if target_K:
            return max(runaway_limit(level), runaway_limit(target_K))
        return max(runaway_limit(level), ORDINARY_K)

    def check(self, temperature_K: float, target_K: float | None = None) -> str:
        """Why this temperature is a runaway, or '' when it is not (it then joins the run's
        recent level)."""
        if not math.isfinite(temperature_K):
            return "non-finite temperature"
        limit = self.limit(target_K)
        if limit is not None and temperature_K > limit:
            return f"temperature {temperature_K:.3g} K, above the guard's {limit:.0f} K"
        self._recent.append(float(temperature_K))
        return ""
