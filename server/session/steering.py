"""Steering state of a session: render parameters merged from patches, simulation parameters
confirmed by the engine, and the correlation of forwarded messages with their acknowledgements.

Pure logic, no I/O: the session facade logs, broadcasts and forwards what these return.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, TypeVar

from pydantic import BaseModel

import protocol as p

M = TypeVar("M", bound=BaseModel)


def _changed_leaves(old: Any, new: Any, prefix: str = "") -> dict[str, Any]:
    """Dotted paths of the leaves where `new` differs from `old` (nested dicts compared deeply)."""
    if isinstance(old, dict) and isinstance(new, dict):
        out: dict[str, Any] = {}
        for key in new:
            out.update(_changed_leaves(old.get(key), new[key], f"{prefix}{key}."))
        return out
    return {} if old == new else {prefix.rstrip("."): new}


def _deep_merge(base: dict[str, Any], patch: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in patch.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def merge_patch(current: M, patch: Mapping[str, Any]) -> tuple[M, dict[str, Any]]:
    """`current` with `patch` merged in deeply (a nested model keeps the fields the patch does
    not name), validated as a whole, and the leaves that really changed ("lighting.ambient": 0.5).

    Raises pydantic's ValidationError when the merged model is invalid."""
    before = current.model_dump(mode="json")
    merged = type(current).model_validate(_deep_merge(current.model_dump(), patch))
    return merged, _changed_leaves(before, merged.model_dump(mode="json"))


@dataclass(frozen=True)
class Pending:
    """A steering message forwarded to the simulation, waiting for its `params_ack`."""

    client_id: str
    client_seq: int | None
    kind: str
    log_id: int
    proposal: p.SimParams | None = None
    """For `sim_params`: the change, applied to the confirmed parameters only once acked."""


class AckBook:
    """Server-side sequence numbers for messages sent to the simulation, and what each awaits."""

    def __init__(self) -> None:
        self._seq = itertools.count(1)
        self._pending: dict[int, Pending] = {}

    def next_seq(self) -> int:
        """A sequence number for a message nobody waits on (automatic force refreshes)."""
        return next(self._seq)

    def expect(self, pending: Pending) -> int:
        seq = next(self._seq)
        self._pending[seq] = pending
        return seq

    def take(self, ref: int) -> Pending | None:
        return self._pending.pop(ref, None)

    def take_all(self) -> list[Pending]:
        out = list(self._pending.values())
        self._pending.clear()
        return out

    def __len__(self) -> int:
        return len(self._pending)


def apply_sim_params(current: p.SimParams, change: p.SimParams) -> p.SimParams:
    """`current` with the fields `change` sets (engine parameters merged key by key)."""
    fields = change.model_dump(exclude_none=True, exclude={"seq", "type", "engine"})
    merged = current.model_copy(update=fields)
    if change.engine:
        merged = merged.model_copy(update={"engine": {**merged.engine, **change.engine}})
    return merged


def sim_params_changes(change: p.SimParams) -> dict[str, Any]:
    """What a `sim_params` message asks to change, as logged."""
    out: dict[str, Any] = change.model_dump(exclude_none=True, exclude={"seq", "type"})
    if not change.engine:
        out.pop("engine", None)
    return out
