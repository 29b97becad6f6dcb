"""External forces on a session's simulation: users' spring pulls and scripts' force sets,
merged into the one set an engine applies.

Adapters treat every `forces` message as the complete set (what is not in it is released), so
the session owns the merge: each client owns its pulls and its script forces; the simulation
always receives the sum of everyone's, capped per atom (`protocol.forces.cap_forces`). A client
that leaves takes its forces with it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import numpy.typing as npt

import protocol as p
from protocol.forces import cap_forces

if TYPE_CHECKING:
    from server.render.boxes import Shown


class Positions(Protocol):
    """Atom positions a spring reads one atom at a time (an array, or `DisplayedAtoms`)."""

    def __len__(self) -> int: ...

    def __getitem__(self, atom: int) -> Any: ...


class DisplayedAtoms:
    """A frame as sent, each atom read in the displayed frame by the last display's rigid
    motion (`Shown.to_display`): only the pulled atoms are moved, not the whole frame. An atom
    the display wrapped into the box differs by a box vector, which the spring's nearest image
    takes away."""

    def __init__(self, raw: npt.NDArray[np.float32], shown: Shown) -> None:
        self.raw = raw
        self.shown = shown

    def __len__(self) -> int:
        return len(self.raw)

    def __getitem__(self, atom: int) -> npt.NDArray[np.float64]:
        return self.shown.to_display(np.asarray(self.raw[atom], dtype=np.float64))


DEFAULT_MAX_FORCE = 1000.0
"""kJ/mol/A on one atom, for script forces (a pull carries its own `max_force`)."""


def nearest_image(
    delta: npt.NDArray[np.float64], box: npt.NDArray[Any] | None
) -> npt.NDArray[np.float64]:
    """`delta` moved by whole box vectors (rows of `box`) to its shortest image: a displayed
    frame wraps an atom that crosses the box, and a pull must not then drag it back across."""
    if box is None:
        return delta
    vectors = np.asarray(box, dtype=np.float64).reshape(3, 3)
    if abs(np.linalg.det(vectors)) < 1e-9:  # no usable box (a zero or flat one)
        return delta
    frac = np.linalg.solve(vectors.T, delta)
    out: npt.NDArray[np.float64] = (frac - np.round(frac)) @ vectors
    return out


def spring_force(
    pull: p.Pull, position: npt.ArrayLike, box: npt.NDArray[Any] | None = None
) -> npt.NDArray[np.float64]:
    """The force (kJ/mol/A) of one pull at the atom's current position: the spring toward its
    target (its nearest image in a periodic `box`), or its constant force, capped at the pull's
    `max_force`."""
    if pull.force is not None:
        f = np.asarray(pull.force, dtype=np.float64)
    else:
        assert pull.target is not None
        delta = np.asarray(pull.target, dtype=np.float64) - np.asarray(position, np.float64)
        f = pull.spring_k * nearest_image(delta, box)
    capped, _ = cap_forces(f, pull.max_force)
    out: npt.NDArray[np.float64] = capped[0]
    return out


@dataclass
class ForceBook:
    """Who pulls which atom, and which script forces each client has set."""

    max_force: float = DEFAULT_MAX_FORCE
    pulls: dict[int, tuple[str, p.Pull]] = field(default_factory=dict)
    """atom -> (client id, pull): one pull per atom, the latest wins."""
    scripted: dict[str, dict[int, npt.NDArray[np.float64]]] = field(default_factory=dict)
    """client id -> atom -> constant force."""

    def pull(self, client_id: str, pull: p.Pull) -> None:
        if pull.release:
            self.pulls.pop(pull.atom, None)
        else:
            self.pulls[pull.atom] = (client_id, pull)

    def set_scripted(self, client_id: str, indices: npt.ArrayLike, forces: npt.ArrayLike) -> None:
        """A client's `forces` message: its complete set of constant forces (empty clears it).
        Repeated atoms add up."""
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        vec = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
        mine: dict[int, npt.NDArray[np.float64]] = {}
        for atom, f in zip(idx.tolist(), vec, strict=True):
            mine[atom] = mine.get(atom, np.zeros(3)) + f
        if mine:
            self.scripted[client_id] = mine
        else:
            self.scripted.pop(client_id, None)

    def drop_client(self, client_id: str) -> bool:
        """Forget everything a client set; True when that changed the merged set."""
        had = client_id in self.scripted
        self.scripted.pop(client_id, None)
        mine = [a for a, (owner, _) in self.pulls.items() if owner == client_id]
        for atom in mine:
            self.pulls.pop(atom)
        return had or bool(mine)

    def clear(self) -> None:
        self.pulls.clear()
        self.scripted.clear()

    @property
    def active(self) -> bool:
        return bool(self.pulls or self.scripted)

    @property
    def springs(self) -> bool:
        """Whether the merged set depends on positions (and must follow every frame)."""
        return any(pull.target is not None for _, pull in self.pulls.values())

    def atoms(self) -> set[int]:
        out = set(self.pulls)
        for mine in self.scripted.values():
            out |= set(mine)
        return out

    def pulling(self) -> list[p.Pull]:
        return [pull for _, pull in self.pulls.values()]

    def merged(
        self, positions: Positions | None, box: npt.NDArray[Any] | None = None
    ) -> tuple[npt.NDArray[np.int32], npt.NDArray[np.float32]]:
        """The complete set to send: atom indices (sorted) and the summed force on each, every
        script force capped at `max_force` and every atom's total capped at the larger of that
        and its pull's `max_force`. Spring pulls need `positions` (skipped without them) and
        follow the periodic `box` (its vectors as rows, in the positions' frame) by the nearest
        image."""
        total: dict[int, npt.NDArray[np.float64]] = {}
        limit: dict[int, float] = {}
        for mine in self.scripted.values():
            for atom, f in mine.items():
                capped, _ = cap_forces(f, self.max_force)
                total[atom] = total.get(atom, np.zeros(3)) + capped[0]
                limit[atom] = self.max_force
        for atom, (_, pull) in self.pulls.items():
            if pull.target is not None and (positions is None or atom >= len(positions)):
                continue
            position = positions[atom] if positions is not None else np.zeros(3)
            total[atom] = total.get(atom, np.zeros(3)) + spring_force(pull, position, box)
            limit[atom] = max(limit.get(atom, 0.0), pull.max_force)
        atoms = sorted(total)
        idx = np.asarray(atoms, dtype=np.int32)
        out = np.zeros((len(atoms), 3), dtype=np.float32)
        for row, atom in enumerate(atoms):
            capped, _ = cap_forces(total[atom], limit[atom])
            out[row] = capped[0]
        return idx, out
