"""Trajectory files cut short: what a reader reads to its last whole frame and says nothing of.

MDAnalysis' DCD reader counts the frames a file's size holds, so a DCD cut inside a frame
opens with its whole frames and drops the rest in silence (an XTC cut short fails to open,
with its reason). `cut_short` names such files, for a job to mark its output partial.
"""

from __future__ import annotations

import os
from typing import Any


def cut_short(u: Any) -> list[str]:
    """Trajectory files that end inside a frame. MDAnalysis' DCD reader counts the whole
    frames a file's size holds and drops a last frame cut off in silence (an XTC cut short
    fails to open); a job then rendered that many frames and said nothing."""
    try:
        trajectory = u.trajectory
    except Exception:  # MDAnalysis raises NoDataError for a universe without coordinates
        return []
    notes = []
    for reader in getattr(trajectory, "readers", [trajectory]):
        dcd: Any = getattr(reader, "_file", None)
        if type(dcd).__name__ != "DCDFile":
            continue
        try:  # the reader's own sizes; another MDAnalysis without them: nothing to say
            n = int(dcd.n_frames)
            frames = dcd._firstframesize + (n - 1) * dcd._framesize if n else 0
            whole = int(dcd._header_size + frames)
            size = os.path.getsize(reader.filename)
        except (AttributeError, OSError, TypeError):
            continue
        if size > whole:
            notes.append(
                f"{os.path.basename(reader.filename)} ends inside a frame after {n} whole "
                f"frame(s) ({size - whole} bytes over): the file is cut short"
            )
    return notes
