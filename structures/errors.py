"""The error every structure reader raises (the file readers and their line checks alike)."""

from __future__ import annotations


class StructureError(ValueError):
    """A structure or trajectory that cannot be used, with a message naming the problem."""
