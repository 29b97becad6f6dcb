"""What a selection will cost, decided before it runs.

MDAnalysis evaluates a selection with no bound of its own, and the text comes from whoever may
type one: `around 1000 index 0:4999` asks a 40,000-atom system for 200 million atom pairs (13 GB),
sixty nested `around 5 (...)` take 14 s. So a selection is measured before it is evaluated:

1. its text: length and nesting (`text_refusal`, no parsing);
2. its parse tree (MDAnalysis's own parser): the tree's depth, then its price in *pair checks*
   (`estimate`). A distance term (`around R sel`, `isolayer`) checks every atom of `sel`
   against the atoms within R of it, so it costs |sel| x (atoms within R); every term also
   passes over the system once, which costs a fraction of a pair check per atom (measured
   below). |sel| is exact where `sel` is cheap to count (no distance term inside: `name CA`,
   `index 0:4999`), else an upper bound; the atoms within R come from the frame itself (atoms
   per cell around each atom), so a dense clump is priced as dense.

A selection whose price exceeds the limit is refused before anything runs, naming the limit;
what slips past the estimate is still held by the process it runs in (a wall-time and memory
limit: `structures.selection_pool`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

TOKEN = re.compile(r"\(|\)|[^\s()]+")
"""A token of the selection language as MDAnalysis splits it (parentheses stand alone)."""


@dataclass(frozen=True)
class SelectionLimits:
    """What evaluating one selection (or the layers of one render, together) may cost."""

    max_chars: int = 2048
    """Characters of one selection's text."""
    max_depth: int = 32
    """Depth of its parse tree: nested parentheses, prefixes (`not`, `around R`, `byres`,
    `same ... as`) and chained `and` / `or`."""
    max_pairs: int = 4_000_000
    """Pair checks, estimated (about 4 s of MDAnalysis on one core of a 2020s CPU)."""


@dataclass(frozen=True)
class Refusal:
    """Why a selection is not evaluated: the reason (naming the limit), where in the text,
    and which limit (`selection_max_pairs`, ...) with its value."""

    reason: str
    position: int
    limit: str
    value: int


@dataclass
class Estimate:
    """The price of one selection: pair checks in all, and the term that costs the most."""

    pairs: int = 0
    term: str = ""
    position: int = 0
    _top: float = field(default=0.0, repr=False)

    def add(self, pairs: float, term: str, position: int) -> None:
        self.pairs += math.ceil(pairs)
        if pairs > self._top:
            self._top, self.term, self.position = pairs, term, position


def text_refusal(text: str, limits: SelectionLimits) -> Refusal | None:
    """Length and parenthesis depth, checked on the text alone (before the parser, whose
    recursion follows the nesting)."""
    if len(text) > limits.max_chars:
        return Refusal(
            f"the selection is {len(text):,} characters long, more than the limit of "
            f"{limits.max_chars:,} (selection_max_chars)",
            limits.max_chars,
            "selection_max_chars",
            limits.max_chars,
        )
    depth = 0
    for match in TOKEN.finditer(text):
        if match.group() == "(":
            depth += 1
            if depth > limits.max_depth:
                return _too_deep(match.start(), limits)
        elif match.group() == ")":
            depth = max(0, depth - 1)
    return None


def _too_deep(position: int, limits: SelectionLimits) -> Refusal:
    return Refusal(
        f"the selection is nested more than {limits.max_depth} deep, the limit "
        "(selection_max_depth)",
        position,
        "selection_max_depth",
        limits.max_depth,
    )


def _children(node: Any) -> list[Any]:
    """A tree node's operands, in the order their text appears (a binary operation's token
    sits between them)."""
    return [c for a in ("lsel", "rsel", "sel") if hasattr(c := getattr(node, a, None), "apply")]


def _in_text_order(tree: Any) -> Iterator[tuple[Any, int]]:
    """(node, depth) in the order of the nodes' keywords in the text: a binary operation
    after its left operand, any other node before its operands (iterative: no recursion)."""
    stack: list[tuple[Any, int, bool]] = [(tree, 1, False)]
    while stack:
        node, depth, expanded = stack.pop()
        if expanded:
            yield node, depth
            continue
        kids = _children(node)
        if hasattr(node, "lsel"):
            stack.append((node.rsel, depth + 1, False))
            stack.append((node, depth, True))
            stack.append((node.lsel, depth + 1, False))
        else:
            for kid in reversed(kids):
                stack.append((kid, depth + 1, False))
            stack.append((node, depth, True))


def positions_of(text: str, tree: Any) -> dict[int, int]:
    """Each node's character offset in `text` (by id): the k-th node of a keyword in text
    order is the k-th occurrence of that keyword among the text's tokens."""
    offsets: dict[str, list[int]] = {}
    for m in TOKEN.finditer(text):
        offsets.setdefault(m.group(), []).append(m.start())
    seen: dict[str, int] = {}
    out: dict[int, int] = {}
    for node, _depth in _in_text_order(tree):
        token = str(getattr(node, "token", ""))
        k = seen.get(token, 0)
        seen[token] = k + 1
        spots = offsets.get(token, [])
        out[id(node)] = spots[k] if k < len(spots) else 0
    return out


def depth_refusal(text: str, tree: Any, limits: SelectionLimits) -> Refusal | None:
    """The parse tree's depth against the limit (checked before the tree is walked by
    anything recursive: MDAnalysis's evaluation recurses once per level); a refusal points at
    the first term past the limit."""
    for node, depth in _in_text_order(tree):
        if depth > limits.max_depth:
            return _too_deep(positions_of(text, tree).get(id(node), 0), limits)
    return None


class Density:
    """How crowded a frame is around each atom: atoms per cell of a grid, cells of 2 to 64 A
    (a power of two at or below the cutoff asked about), counted once per cell size. Cells
    share counters through a hash, which can only overcount."""

    def __init__(self, positions: npt.ArrayLike) -> None:
        self._raw = positions
        self.n = int(np.shape(positions)[0]) if np.ndim(positions) else 0
        self._pos: npt.NDArray[np.float64] | None = None
        self._finite: npt.NDArray[np.bool_] = np.zeros(0, dtype=bool)
        self._occupancy: dict[float, npt.NDArray[np.int64]] = {}

    @staticmethod
    def cell(cutoff: float) -> float:
        return float(2.0 ** min(6, max(1, math.floor(math.log2(max(cutoff, 2.0))))))

    def occupancy(self, cell: float) -> npt.NDArray[np.int64]:
        """For each atom, the atoms of its cell (itself included; 0 where not finite)."""
        known = self._occupancy.get(cell)
        if known is not None:
            return known
        if self._pos is None:  # built on first use: most selections measure no distance
            pos = np.asarray(self._raw, dtype=np.float64).reshape(-1, 3)
            self._finite = np.asarray(np.isfinite(pos).all(axis=1), dtype=bool)
            self._pos = np.where(self._finite[:, None], pos, 0.0)
            self.n = len(pos)
        idx = np.floor(np.clip(self._pos / cell, -(2.0**40), 2.0**40)).astype(np.int64)
        key = (idx[:, 0] * 73856093) ^ (idx[:, 1] * 19349663) ^ (idx[:, 2] * 83492791)
        size = 1 << max(4, (2 * max(self.n, 1) - 1).bit_length())
        slot = key & (size - 1)
        counts = np.bincount(slot[self._finite], minlength=size)
        occ = np.where(self._finite, counts[slot], 0).astype(np.int64)
        self._occupancy[cell] = occ
        return occ

    def pairs(self, cutoff: float, atoms: npt.NDArray[np.int64] | None, bound: int) -> float:
        """Atom pairs within `cutoff` of the atoms `atoms` (when known) or of any `bound`
        atoms of typical surroundings (when only their number's bound is known)."""
        if cutoff <= 0 or bound <= 0 or self.n == 0:
            return 0.0
        cell = self.cell(cutoff)
        occ = self.occupancy(cell)
        # an atom's neighbours: the others of its cell scaled to the ball's volume (at least
        # its cell, so a clump in a cell wider than the ball counts whole), and itself
        ball = max(1.0, 4.0 / 3.0 * math.pi * cutoff**3 / cell**3)
        if atoms is not None:
            others = float(occ[atoms].sum()) - len(atoms)
            return min(others * ball + len(atoms), float(len(atoms)) * self.n)
        typical = float(np.square(occ, dtype=np.float64).sum()) / max(1, int(occ.sum()))
        return min(bound * ((typical - 1) * ball + 1), float(bound) * self.n)


# measured with MDAnalysis 2.11 on 1M atoms (one core): a distance pair costs about 1 us; a term's
# pass over the system costs this many pair checks per atom
_CHEAP = 1 / 32  # keyword terms (`name`, `resname`, `index`, `protein`): 2-20 ns an atom
_SET = 1 / 16  # `and`, `not`, `byres`, `same resid as`, `prop`, one-centre zones: 25-50 ns
_OR = 2.0  # `or` (its union and regrouping): 0.7-1.7 us an atom
_BONDED = 2.0  # `bonded`: about 1.5 us an atom, and per bond:
_BOND = 16.0  # MDAnalysis gathers the group's bonds in Python, twice: 8-14 us a bond (40,000 to
# 200,000 atoms, a bond each); four nested `bonded` on 47,681 atoms ran past 10 s
_FRAGMENTS = 64.0  # `same fragment as`, per atom: the fragments traced through the bonds, 2.6 s
# on 40,000 atoms, 6.7 s on 100,000 (cached by the universe afterwards, priced every time)
_GRID = 1.0  # a neighbour grid over the system, for `around` (`isolayer` builds two)
_CHEMISTRY = 16.0  # `smarts`, `aromatic`: the whole system converted for RDKit
_UNKNOWN = 2.0  # a term this table does not know (a newer MDAnalysis): priced as `or`
_SAME_SORTED = frozenset(
    ["residue", "segment", "resid", "resnum", "mass", "charge", "radius", "bfactor"]
)
"""`same P as` properties held as numbers, which numpy's `isin` sorts (one pass); any other is
compared atom by atom (`_Pricer._same_by_comparison`)."""


def _classes() -> dict[str, type]:
    from MDAnalysis.core import selection as sel

    names = [
        "AndOperation", "OrOperation", "NotSelection", "GlobalSelection", "ByResSelection",
        "AroundSelection", "IsoLayerSelection", "SphericalLayerSelection",
        "SphericalZoneSelection", "CylindricalSelection", "PointSelection", "BondedSelection",
        "SameSelection", "PropertySelection", "SmartsSelection", "AromaticSelection",
        "AllSelection", "AtomSelection", "SelgroupSelection", "SingleCharSelection",
        "_ProtoStringSelection", "ResidSelection", "BoolSelection", "RangeSelection",
        "ProteinSelection", "NucleicSelection", "WaterSelection",
    ]  # fmt: skip
    return {n: c for n in names if isinstance(c := getattr(sel, n, None), type)}


class _Pricer:
    """Walks one parse tree: the passes first (no evaluation), then sizes and pairs."""

    def __init__(self, text: str, tree: Any, universe: Any, density: Density | None) -> None:
        self.c = _classes()
        self.tree = tree
        self.universe = universe
        self.n = int(universe.atoms.n_atoms)
        self.density = density
        self.bonds = _bond_count(universe)
        self.where = positions_of(text, tree)
        self._bounds: dict[int, tuple[int, npt.NDArray[np.int64] | None]] = {}
        self._countable: dict[int, bool] = {}

    def _is(self, node: Any, *names: str) -> bool:
        return any(isinstance(node, self.c[n]) for n in names if n in self.c)

    def _same_by_comparison(self, node: Any) -> bool:
        """`same P as sel` that compares every atom with each atom of `sel`: by position
        (`x`, `y`, `z`, `fragment`), or by a text property (`name`, `type`, `resname`,
        `segid`), which numpy's `isin` cannot sort and so compares one value at a time."""
        return self._is(node, "SameSelection") and node.prop not in _SAME_SORTED

    def weight(self, node: Any) -> float:
        """Pair checks per atom of this node's own pass over the system."""
        known = self._weight(node)
        return _UNKNOWN if known is None else known

    def _weight(self, node: Any) -> float | None:
        if self._is(node, "OrOperation"):
            return _OR
        if self._is(node, "BondedSelection"):
            return _BONDED
        if self._is(node, "AroundSelection"):
            return _GRID
        if self._is(node, "IsoLayerSelection"):
            return 2 * _GRID
        if self._is(node, "SmartsSelection", "AromaticSelection"):
            return _CHEMISTRY
        if self._is(
            node,
            "AndOperation", "NotSelection", "ByResSelection", "SameSelection",
            "PropertySelection", "SphericalLayerSelection", "SphericalZoneSelection",
            "CylindricalSelection", "PointSelection",
        ):  # fmt: skip
            return _SET
        if self._is(
            node,
            "GlobalSelection", "AllSelection", "AtomSelection", "SelgroupSelection",
            "SingleCharSelection", "_ProtoStringSelection", "ResidSelection",
            "BoolSelection", "RangeSelection", "ProteinSelection", "NucleicSelection",
            "WaterSelection",
        ):  # fmt: skip
            return _CHEAP
        return None

    def _through_bonds(self, node: Any) -> float:
        """Pair checks of a pass that walks the bonds (beyond its per-atom weight)."""
        if self._is(node, "BondedSelection"):
            return _BOND * self.bonds
        if self._is(node, "SameSelection") and node.prop == "fragment":
            return _FRAGMENTS * self.n
        return 0.0

    def passes(self, estimate: Estimate) -> None:
        for node, _depth in _in_text_order(self.tree):
            cost = self.weight(node) * self.n + self._through_bonds(node)
            estimate.add(cost, self._name(node), self._at(node))

    def _name(self, node: Any) -> str:
        return str(getattr(node, "token", "") or type(node).__name__)

    def _at(self, node: Any) -> int:
        return self.where.get(id(node), 0)

    def countable(self, node: Any) -> bool:
        """Cheap to evaluate for its size: no pair term, nothing quadratic, no chemistry."""
        key = id(node)
        if key not in self._countable:
            own = not (
                self._is(node, "AroundSelection", "IsoLayerSelection")
                or self._is(node, "SmartsSelection", "AromaticSelection")
                or self._same_by_comparison(node)
                or self._weight(node) is None
            )
            self._countable[key] = own and all(self.countable(c) for c in _children(node))
        return self._countable[key]

    def bound(self, node: Any) -> tuple[int, npt.NDArray[np.int64] | None]:
        """At most how many atoms `node` selects, and which, where that is cheap to know."""
        key = id(node)
        if key in self._bounds:
            return self._bounds[key]
        n = self.n
        atoms: npt.NDArray[np.int64] | None = None
        if self.countable(node):
            atoms = np.asarray(node.apply(self.universe.atoms).indices, dtype=np.int64)
            size = len(atoms)
        elif self._is(node, "AndOperation"):
            size = min(self.bound(node.lsel)[0], self.bound(node.rsel)[0])
        elif self._is(node, "OrOperation"):
            size = min(n, self.bound(node.lsel)[0] + self.bound(node.rsel)[0])
        elif self._is(node, "GlobalSelection"):
            size = self.bound(node.sel)[0]
        elif self._is(node, "AroundSelection"):
            size = min(n, math.ceil(self._near(node.sel, node.cutoff)))
        elif self._is(node, "IsoLayerSelection"):
            size = min(n, math.ceil(self._near(node.sel, node.exRadius)))
        else:
            size = n
        self._bounds[key] = (size, atoms)
        return size, atoms

    def _near(self, inner: Any, cutoff: float) -> float:
        size, atoms = self.bound(inner)
        if self.density is None:
            return float(size) * self.n
        return self.density.pairs(float(cutoff), atoms, size)

    def pairs(self, estimate: Estimate) -> None:
        """The pair terms, each priced with the sizes of what it pairs."""
        for node, _depth in _in_text_order(self.tree):
            if self._is(node, "AroundSelection"):
                cost = self._near(node.sel, node.cutoff)
            elif self._is(node, "IsoLayerSelection"):
                cost = self._near(node.sel, node.exRadius) + self._near(node.sel, node.inRadius)
            elif self._same_by_comparison(node):
                # one comparison of every atom per atom of `sel` (about 20-60 ns for names on
                # 40,000 atoms: `same resname as all` took 37 s), positions all held at once
                cost = self.bound(node.sel)[0] * _SET * self.n
            else:
                continue
            estimate.add(cost, self._name(node), self._at(node))


def _bond_count(universe: Any) -> int:
    """The universe's bonds, counted without building MDAnalysis's bond objects."""
    bonds = getattr(getattr(universe, "_topology", None), "bonds", None)
    return len(getattr(bonds, "values", None) or ())


def estimate(
    text: str,
    tree: Any,
    universe: Any,
    density: Density | None,
    limits: SelectionLimits,
    spent: int = 0,
) -> tuple[Estimate, Refusal | None]:
    """The price of `tree` (the parse of `text`) on `universe`, and a refusal when it, with
    `spent` pair checks already allowed (earlier layers of the same render), exceeds
    `limits.max_pairs`. The passes are priced first: sizes are counted by evaluating the
    cheap parts, which is allowed only once their passes fit."""
    found = Estimate()
    pricer = _Pricer(text, tree, universe, density)
    pricer.passes(found)
    if spent + found.pairs <= limits.max_pairs:
        pricer.pairs(found)
    if spent + found.pairs <= limits.max_pairs:
        return found, None
    where = f"`{found.term}` at character {found.position + 1}"
    before = f" (with {spent:,} for the layers before it)" if spent else ""
    return found, Refusal(
        f"needs about {found.pairs:,} atom pair checks{before}, most in {where}; the limit is "
        f"{limits.max_pairs:,} (selection_max_pairs)",
        found.position,
        "selection_max_pairs",
        limits.max_pairs,
    )


def secondary_refusal(n_residues: int, limits: SelectionLimits) -> Refusal | None:
    """DSSP holds a residue-by-residue matrix (about 400 bytes and 1 us per residue pair
    with MDAnalysis 2.11: 4,000 residues took 20 s and 6.7 GB)."""
    pairs = n_residues * n_residues
    if pairs <= limits.max_pairs:
        return None
    return Refusal(
        f"secondary structure of {n_residues:,} residues needs {pairs:,} residue pairs; the "
        f"limit is {limits.max_pairs:,} (selection_max_pairs)",
        0,
        "selection_max_pairs",
        limits.max_pairs,
    )
