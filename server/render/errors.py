"""The one exception of the render core, so callers can map bad input to a clear reply."""

from __future__ import annotations


class RenderError(ValueError):
    """Invalid render input (positions, parameters, image size, device), raised before any
    kernel launch with a message that names the offending value."""


class CapacityError(RenderError):
    """A system (or layers) larger than a device holds, as configured (`max_atoms`,
    `--device-atoms`): valid input, too large for this server; told as `too_large`."""
