"""Steering marks: a recording's steering log turned into points on its timeline.

A recorded run is frames plus the steering log of the same span. Each accepted action becomes a
*mark* at the trajectory frame where it took effect: the step the simulation acknowledged (an
`applied` entry naming the action) where there is one, else the step the action arrived at,
mapped to the first recorded frame at or after that step. Actions the simulation refused are
left out. Pulls are kept twice: a mark where a pull on an atom starts and where it is released
(not one per pointer move), and the whole target path, for the arrows of a movie overlay.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Sequence
from typing import Any

Mark = dict[str, Any]


def frame_at(frame_steps: Sequence[int], step: int) -> int:
    """The first frame whose step is at or after `step` (the last frame if none is)."""
    if not frame_steps:
        return 0
    return min(bisect.bisect_left(frame_steps, step), len(frame_steps) - 1)


def _describe(entry: dict[str, Any]) -> tuple[str, str] | None:
    """(kind, text) of a logged action, or None for entries that are not marks."""
    event = entry.get("event")
    changes = entry.get("changes") or {}
    if event == "sim_params":
        return "sim_params", ", ".join(f"{k} {v}" for k, v in changes.items()) or "parameters"
    if event == "render_params":
        return "render", ", ".join(f"{k} {v}" for k, v in changes.items()) or "render"
    if event == "control":
        action = str(entry.get("action", "control"))
        shown = {"frame", "speed", "loop"} | ({"n_steps"} if action == "step" else set())
        words = [f"{k} {v}" for k, v in entry.items() if k in shown]
        return "control", " ".join([action, *words])
    if event == "forces":
        return "forces", f"forces on {len(entry.get('atoms') or [])} atom(s)"
    if event == "sim_event":
        return "event", f"{entry.get('code', 'event')}: {entry.get('message', '')}".strip()
    return None


def steering_marks(entries: Iterable[dict[str, Any]], frame_steps: Sequence[int]) -> list[Mark]:
    """The marks of a recording, in log order; `frame_steps` are the recorded frames' steps
    (ascending)."""
    entries = list(entries)
    applied: dict[int, int] = {}
    failed: set[int] = set()
    for e in entries:
        ref = e.get("ref")
        if isinstance(ref, int) and e.get("event") == "applied" and isinstance(e.get("step"), int):
            applied[ref] = e["step"]
        elif isinstance(ref, int) and e.get("event") == "failed":
            failed.add(ref)
    marks: list[Mark] = []
    pulling: set[int] = set()
    for e in entries:
        log_id = e.get("id")
        if not isinstance(log_id, int) or log_id in failed:
            continue
        step = applied.get(log_id, e.get("step") if e.get("event") == "sim_event" else None)
        if not isinstance(step, int):
            step = int(e.get("sim_step") or 0)
        mark: Mark = {"id": log_id, "step": step, "frame": frame_at(frame_steps, step)}
        if e.get("event") == "pull":
            atom = int(e["atom"])
            if e.get("release"):
                if atom not in pulling:
                    continue
                pulling.discard(atom)
                marks.append({**mark, "kind": "release", "atom": atom, "text": f"release {atom}"})
            elif atom not in pulling:
                pulling.add(atom)
                marks.append({**mark, "kind": "pull", "atom": atom, "text": f"pull atom {atom}"})
            continue
        described = _describe(e)
        if described is None:
            continue
        kind, text = described
        mark.update(kind=kind, text=text)
        if kind == "render":
            mark["changes"] = e.get("changes") or {}
        marks.append(mark)
    return marks


def pull_path(entries: Iterable[dict[str, Any]], frame_steps: Sequence[int]) -> list[Mark]:
    """Every accepted pull update as {frame, atom, target, release}: where each pulled atom
    was being drawn to, frame by frame, for a movie's arrows."""
    out: list[Mark] = []
    for e in entries:
        if e.get("event") != "pull":
            continue
        step = int(e.get("sim_step") or 0)
        out.append(
            {
                "frame": frame_at(frame_steps, step),
                "atom": int(e["atom"]),
                "target": e.get("target"),
                "release": bool(e.get("release")),
            }
        )
    return out


def active_pulls(path: Sequence[Mark], frame: int) -> dict[int, list[float]]:
    """Atom -> target of the pulls active at `frame` (the latest update at or before it)."""
    active: dict[int, list[float]] = {}
    for update in path:
        if update["frame"] > frame:
            break
        if update["release"] or update["target"] is None:
            active.pop(update["atom"], None)
        else:
            active[update["atom"]] = update["target"]
    return active
