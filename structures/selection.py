"""Atom selections in MDAnalysis's selection language, evaluated on a protocol topology.

The server knows a system only through its `topology` message, so a selection runs against an
MDAnalysis universe built from that message: names, residue names and numbers, chain ids
(as both `segid` and `chainID`), elements, masses from the elements, charges where the engine
sent them, and the bonds. Selections that read coordinates (`around`, `point`, `prop x`, ...)
are *dynamic*: `Selector.select` evaluates them on the positions it is given.

The default layers follow what every molecular viewer does: solvent and ions hidden, the polymer
(protein or nucleic acid) at the session's scale, and any other residues, ligands, at a finer
scale of their own.

Kept whole: the MDAnalysis universe built from a topology message and the selections evaluated on
it are one translation of the protocol's topology, tested as one.
"""

from __future__ import annotations

import itertools
import re
import threading
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt

from protocol import Topology
from structures.selection_cost import (
    TOKEN,
    Density,
    Refusal,
    SelectionLimits,
    depth_refusal,
    estimate,
    secondary_refusal,
    text_refusal,
)

SOLVENT_RESNAMES = (
    "SOL", "WAT", "HOH", "H2O", "TIP", "TIP3", "TIP3P", "TIP4", "TIP4P", "TIP5", "TIP5P", "T3P",
    "T4P", "T4E", "SPC", "SPCE", "OPC", "OPC3", "DOD",
)  # fmt: skip
"""Water, by the residue names of the common force fields (matched in any letter case)."""
ION_RESNAMES = (
    "NA", "NA+", "SOD", "CL", "CL-", "CLA", "K", "K+", "POT", "MG", "MG2", "CA", "CAL", "CA2",
    "ZN", "ZN2", "LI", "LI+", "RB", "CS", "CES", "F", "BR", "BR-", "I", "IOD",
)  # fmt: skip

POLYMER_SELECTION = "protein or nucleic"
DYNAMIC_KEYWORDS = frozenset(
    ["around", "sphzone", "sphlayer", "cyzone", "cylayer", "point", "prop", "isolayer"]
)
"""Selection keywords whose result depends on the coordinates."""

LIGAND_SIGMA_FACTOR = 0.5
"""A ligand's default layer shows it at half the session's scale (its chemistry, not its blob)."""

_MASS = {"H": 1.008, "C": 12.011, "N": 14.007, "O": 15.999, "P": 30.974, "S": 32.06}


SECONDARY_CODES = {"H": 1, "E": 2}
"""DSSP's helix and strand as per-atom codes (0: coil or not protein)."""


TOO_DEEP_FOR_THE_PARSER = (
    "the selection nests its operators deeper than the parser can follow (each `not`, "
    "`byres`, `same ... as` or `around` holds what follows it one level down, as a "
    "parenthesis does); write fewer of them one inside another"
)
"""Said when the selection parser runs out of recursion: operators nested without
parentheses, which `selection_max_depth` (a count of parentheses) does not see."""


def _backbone(names: set[str]) -> bool:
    """N, CA, C and an oxygen as DSSP reads them (O, or OC1 / OT1 at a C terminus)."""
    return {"N", "CA", "C"} <= names and bool(names & {"O", "OC1", "OT1"})


class SelectionError(ValueError):
    """A selection that cannot be evaluated: MDAnalysis could not parse it, or it would cost
    more than a limit allows (`limit` names the limit, `value` its value). `position` is the
    0-based character offset of the offending token in the text (its length when the text
    ended too soon)."""

    def __init__(
        self, text: str | None, reason: str, position: int, limit: str = "", value: int = 0
    ) -> None:
        """`text` None: not about one text (a request for several that failed as a whole)."""
        self.text = text or ""
        self._whole = text is None
        self.reason = reason
        self.position = position
        self.limit = limit
        self.value = value
        if text is None:
            super().__init__(reason)
            return
        shown = text if len(text) <= 80 else text[:60] + "..."
        super().__init__(f"selection {shown!r} at character {position + 1}: {reason}")

    @classmethod
    def refused(cls, text: str, refusal: Refusal) -> SelectionError:
        return cls(text, refusal.reason, refusal.position, refusal.limit, refusal.value)

    def __reduce__(self) -> tuple[Any, ...]:  # crosses process boundaries whole
        text = None if self._whole else self.text
        return (type(self), (text, self.reason, self.position, self.limit, self.value))


def is_dynamic(text: str) -> bool:
    """Whether `text` reads coordinates (its atoms change as the system moves): a distance
    keyword, or `same x|y|z as ...`."""
    tokens = [t.lower() for t in TOKEN.findall(text)]
    if any(t in DYNAMIC_KEYWORDS for t in tokens):
        return True
    return any(a == "same" and b in ("x", "y", "z") for a, b in itertools.pairwise(tokens))


def _position_of(text: str, reason: str) -> int:
    """Where MDAnalysis's complaint points in `text`: the token it names, or the end."""
    value = re.search(r"value: (\S+?)'?$", reason)
    quoted = [value.group(1)] if value else re.findall(r"'([^']*)'", reason)
    spans = [(m.group(), m.start()) for m in TOKEN.finditer(text)]
    if not quoted or quoted[0] == "None":
        return len(text.rstrip())
    word = quoted[0]
    if "end of selection" in reason:
        hits = [s for t, s in spans if t == word]
        return hits[-1] if hits else len(text)
    for t, s in spans:
        if t == word:
            return s
    at = text.find(word)
    return at if at >= 0 else len(text.rstrip())


def universe_of(topology: Topology) -> Any:
    """An MDAnalysis universe with the attributes of `topology` (no coordinates yet)."""
    import MDAnalysis as mda

    n = int(topology.n_atoms)
    chains = np.asarray(topology.chain_ids, dtype=object)
    resids = topology.residue_ids.to_numpy().astype(np.int64)
    resnames = np.asarray(topology.residue_names, dtype=object)
    if n:
        new = np.ones(n, dtype=bool)
        new[1:] = (chains[1:] != chains[:-1]) | (resids[1:] != resids[:-1])
        new[1:] |= resnames[1:] != resnames[:-1]
        atom_res = np.cumsum(new) - 1
        first = np.flatnonzero(new)
        seg_names, res_seg = np.unique(chains[first].astype(str), return_inverse=True)
    else:
        atom_res = np.zeros(0, dtype=np.int64)
        first = np.zeros(0, dtype=np.int64)
        seg_names, res_seg = np.array(["A"]), np.zeros(0, dtype=np.int64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = mda.Universe.empty(
            n,
            n_residues=max(len(first), 1) if n else 1,
            n_segments=max(len(seg_names), 1),
            atom_resindex=atom_res if n else None,
            residue_segindex=res_seg if n else None,
            trajectory=True,
        )
    elements = np.asarray([e.capitalize() for e in topology.elements], dtype=object)
    u.add_TopologyAttr("names", np.asarray(topology.names, dtype=object))
    u.add_TopologyAttr("types", np.asarray(topology.names, dtype=object))
    u.add_TopologyAttr("elements", elements)
    u.add_TopologyAttr("masses", np.array([_MASS.get(str(e), 12.0) for e in elements]))
    u.add_TopologyAttr("chainIDs", chains)
    u.add_TopologyAttr("resids", resids[first] if n else np.ones(1, dtype=np.int64))
    u.add_TopologyAttr("resnums", resids[first] if n else np.ones(1, dtype=np.int64))
    u.add_TopologyAttr("resnames", resnames[first] if n else np.array(["UNK"], dtype=object))
    u.add_TopologyAttr("segids", seg_names.astype(object))
    if topology.charges is not None:
        u.add_TopologyAttr("charges", topology.charges.to_numpy().astype(np.float64))
    bonds = topology.bonds.to_numpy().reshape(-1, 2).astype(np.int64)
    u.add_TopologyAttr("bonds", bonds)
    return u


class SelectionSkippedError(SelectionError):
    """Not evaluated: another selection of the same all-or-nothing request was refused."""


_SKIPPED = "not evaluated: another selection of the same request was refused"


@dataclass
class _Priced:
    """A selection parsed and priced, ready to run (or already known: `atoms`)."""

    text: str
    tree: Any
    dynamic: bool
    cost: int
    atoms: npt.NDArray[np.int32] | None = None


_THIS_CALL = object()
"""Positions placed for the selections of one `evaluate` call only."""
_PARSE_LOCK = threading.Lock()
"""MDAnalysis's selection parser keeps its state in one shared object."""


def parse(text: str) -> Any:
    """MDAnalysis's parse tree of `text` (nothing evaluated); raises SelectionError naming
    where the text goes wrong."""
    # the whole package first: keywords such as `index`, `name` and `resid` are registered by
    # its topology attributes, after the selection module loads. While another thread is
    # still importing MDAnalysis this waits for it; the selection module alone would be there
    # already, and a valid selection was refused ("Unknown selection token: 'index'").
    import MDAnalysis  # noqa: F401
    from MDAnalysis.core import selection as mda_selection
    from MDAnalysis.exceptions import SelectionError as MDASelectionError

    try:
        with _PARSE_LOCK, warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tree = mda_selection.Parser.parse(text, {}, periodic=True, sorted=True)
        if not _all_finite(tree, set()):  # `around nan`: a distance no one can mean
            at = re.search(r"nan|inf", text, re.IGNORECASE)
            raise SelectionError(
                text, "a distance or coordinate is not a finite number", at.start() if at else 0
            )
        return tree
    except SelectionError:
        raise
    except MDASelectionError as exc:
        raise _named(text, str(exc)) from None
    except RecursionError:
        raise SelectionError(text, TOO_DEEP_FOR_THE_PARSER, 0) from None
    except MemoryError:
        raise
    except Exception as exc:
        raise _named(text, f"{type(exc).__name__}: {exc}") from None


def _all_finite(node: Any, seen: set[int]) -> bool:
    """Whether every number in a parse tree (cutoffs, radii, points) is finite."""
    if id(node) in seen:
        return True
    seen.add(id(node))
    for value in vars(node).values() if hasattr(node, "__dict__") else ():
        if isinstance(value, float | np.floating) and not np.isfinite(value):
            return False
        if isinstance(value, np.ndarray) and value.dtype.kind == "f":
            if not np.isfinite(value).all():
                return False
        elif isinstance(value, list | tuple):
            if not all(_all_finite(v, seen) for v in value if hasattr(v, "apply")):
                return False
        elif hasattr(value, "apply") and not _all_finite(value, seen):
            return False
    return True


def _named(text: str, raw: str) -> SelectionError:
    """MDAnalysis's complaint, worded for a person typing, at the position it points to."""
    reason = raw.replace("Unknown selection token: 'None'", "the text ends too soon")
    reason = reason.replace("Unexpected token: 'None'", "the text ends too soon.")
    if "'within'" in reason:
        reason += " (VMD's `within D of sel` is `sel or around D sel` here)"
    return SelectionError(text, reason, _position_of(text, raw))


@dataclass
class Selector:
    """Selections on one topology; static results are cached by their text.

    With `limits`, a selection is priced before it runs (`structures.selection_cost`) and
    refused when it costs more; without, it runs whatever it costs (for a user's own files on
    their own machine: `scalesteer render`)."""

    topology: Topology

    def __post_init__(self) -> None:
        self._universe: Any = None
        self._static: dict[str, npt.NDArray[np.int32]] = {}
        self._density: tuple[Any, Density] | None = None
        self._placed: Any = None
        """The key of the positions the universe holds (None: none placed yet)."""
        self._key: Any = _THIS_CALL

    @property
    def universe(self) -> Any:
        if self._universe is None:
            self._universe = universe_of(self.topology)
        return self._universe

    def select(
        self,
        text: str,
        positions: npt.ArrayLike | None = None,
        box: npt.ArrayLike | None = None,
        limits: SelectionLimits | None = None,
    ) -> npt.NDArray[np.int32]:
        """Sorted indices of the atoms `text` selects. A dynamic selection needs `positions`
        (n, 3 angstrom), and measures distances through the periodic `box` (3x3 vectors,
        angstrom) when there is one; raises SelectionError naming the position of what is
        wrong (or the limit it would cross)."""
        found = self.evaluate([text], positions, box, limits)[0]
        if isinstance(found, SelectionError):
            raise found
        return found

    def evaluate(
        self,
        texts: list[str],
        positions: npt.ArrayLike | None = None,
        box: npt.ArrayLike | None = None,
        limits: SelectionLimits | None = None,
        positions_key: Any = None,
        strict: bool = False,
    ) -> list[npt.NDArray[np.int32] | SelectionError]:
        """Each text's atoms, or why not. The texts share one budget (`limits.max_pairs`,
        the layers of one render together): all are priced before any runs, and the first
        that takes the total past the limit, and any after it that would, are refused.
        `strict`: when any is refused (or does not parse), none runs (a render that cannot
        be drawn whole). `positions_key` names the positions: the same key again means the
        same positions (their placement and density are kept); None, positions to take
        afresh."""
        if positions_key is None or positions_key != self._placed:
            self._placed = None
            self._density = None
        self._key = positions_key if positions_key is not None else _THIS_CALL
        spent = 0
        priced: list[_Priced | SelectionError] = []
        for text in texts:
            try:
                item = self._price(text, positions, box, limits, spent)
            except SelectionError as exc:
                priced.append(exc)
                continue
            spent += item.cost
            priced.append(item)
        failed = any(isinstance(each, SelectionError) for each in priced)
        out: list[npt.NDArray[np.int32] | SelectionError] = []
        for each in priced:
            if isinstance(each, SelectionError):
                out.append(each)
            elif strict and failed:
                out.append(SelectionSkippedError(each.text, _SKIPPED, 0))
            else:
                try:
                    out.append(self._run(each))
                except SelectionError as exc:
                    out.append(exc)
        if positions_key is None:
            self._placed = None
        return out

    def _price(
        self,
        text: str,
        positions: npt.ArrayLike | None,
        box: npt.ArrayLike | None,
        limits: SelectionLimits | None,
        spent: int,
    ) -> _Priced:
        """Parse `text` and, with `limits`, price it (refused past them); nothing runs yet
        but the cheap parts whose sizes the price needs."""
        text = text.strip()
        if not text:
            raise SelectionError(text, "the selection is empty (use 'all' for every atom)", 0)
        dynamic = is_dynamic(text)
        if not dynamic and text in self._static:
            return _Priced(text, None, dynamic, 0, self._static[text])
        if limits is not None and (refusal := text_refusal(text, limits)) is not None:
            raise SelectionError.refused(text, refusal)
        tree = parse(text)
        if limits is not None and (refusal := depth_refusal(text, tree, limits)) is not None:
            raise SelectionError.refused(text, refusal)
        u = self.universe
        if dynamic:
            if positions is None:
                raise SelectionError(text, "this selection needs positions", 0)
            if self.topology.n_atoms and self._placed is None:
                u.atoms.positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
                self._placed = self._key
            u.dimensions = _dimensions(box)
        if limits is None:
            return _Priced(text, tree, dynamic, 0)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                density = self._density_of(positions) if dynamic else None
                price, refusal = estimate(text, tree, u, density, limits, spent)
        except MemoryError:
            raise
        except Exception as exc:  # a term that fails on this topology, found while counting
            raise _named(text, f"{type(exc).__name__}: {exc}") from None
        if refusal is not None:
            raise SelectionError.refused(text, refusal)
        return _Priced(text, tree, dynamic, price.pairs)

    def _run(self, item: _Priced) -> npt.NDArray[np.int32]:
        if item.atoms is not None:
            return item.atoms
        text = item.text
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                group = item.tree.apply(self.universe.atoms)
        except RecursionError:
            raise SelectionError(text, TOO_DEEP_FOR_THE_PARSER, 0) from None
        except MemoryError:
            raise
        except Exception as exc:  # e.g. ImportError: `smarts` without RDKit
            raise _named(text, f"{type(exc).__name__}: {exc}") from None
        indices = np.asarray(group.indices, dtype=np.int32)
        if not item.dynamic:
            if len(self._static) > 256:
                self._static.clear()
            self._static[text] = indices
        return indices

    def _density_of(self, positions: npt.ArrayLike | None) -> Density | None:
        """The density of the positions placed (kept with them)."""
        if positions is None:
            return None
        if self._density is None:
            self._density = (self._placed, Density(positions))
        return self._density[1]

    def secondary(
        self, positions: npt.ArrayLike, limits: SelectionLimits | None = None
    ) -> npt.NDArray[np.uint8]:
        """Per atom, the secondary structure of its residue by MDAnalysis's DSSP at these
        positions: 0 coil (or not protein), 1 helix, 2 strand. Residues without a complete
        backbone (N, CA, C, O) count as coil. With `limits`, a protein too large for them
        (DSSP's cost grows with the square of its residues) raises SelectionError."""
        from MDAnalysis.analysis.dssp import DSSP

        n = self.topology.n_atoms
        codes = np.zeros(n, dtype=np.uint8)
        if not n:
            return codes
        u = self.universe
        u.atoms.positions = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        self._placed = None
        residues = list(u.select_atoms("protein").residues)
        if len(residues) < 3:
            return codes
        if limits is not None and (refusal := secondary_refusal(len(residues), limits)):
            raise SelectionError.refused("secondary structure", refusal)
        found = None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:  # as MDAnalysis assigns it: every protein residue
                found = DSSP(u, guess_hydrogens=True).run(stop=1).results.dssp[0]
            except (ValueError, IndexError, KeyError):
                # a residue without its backbone atoms: assign the complete ones only
                names = ({str(x) for x in r.atoms.names} for r in residues)
                residues = [r for r, have in zip(residues, names, strict=True) if _backbone(have)]
                if len(residues) >= 3:
                    group = sum(residues[1:], residues[0]).atoms
                    try:
                        found = DSSP(group, guess_hydrogens=True).run(stop=1).results.dssp[0]
                    except (ValueError, IndexError, KeyError) as exc:
                        raise SelectionError("secondary structure", f"DSSP: {exc}", 0) from None
        if found is None or len(found) != len(residues):
            return codes
        for residue, c in zip(residues, found, strict=True):
            codes[residue.atoms.indices] = SECONDARY_CODES.get(str(c), 0)
        return codes


def _dimensions(box: npt.ArrayLike | None) -> npt.NDArray[np.float32] | None:
    """MDAnalysis's [a, b, c, alpha, beta, gamma] of box vectors; None without a usable box."""
    if box is None:
        return None
    vectors = np.asarray(box, dtype=np.float64).reshape(3, 3)
    if not np.isfinite(vectors).all() or abs(np.linalg.det(vectors)) < 1e-6:
        return None
    from MDAnalysis.lib.mdamath import triclinic_box

    dims: npt.NDArray[np.float32] = triclinic_box(*vectors).astype(np.float32)
    return dims


def _residue_mask(topology: Topology, kinds: set[str]) -> npt.NDArray[np.bool_]:
    """Atoms whose residue name is one of `kinds` (a dict lookup per atom: fast at 1M atoms,
    where numpy's set operations on strings are not)."""
    flag = {r: r in kinds for r in set(topology.residue_names)}
    return np.fromiter((flag[r] for r in topology.residue_names), bool, topology.n_atoms)


def polymer_atoms(topology: Topology) -> npt.NDArray[np.int32]:
    """The atoms `protein or nucleic` selects: MDAnalysis's own residue names, read here
    without building a universe (a default is wanted the moment a large system arrives)."""
    from MDAnalysis.core.selection import NucleicSelection, ProteinSelection

    known = set(ProteinSelection.prot_res) | set(NucleicSelection.nucl_res)
    return np.flatnonzero(_residue_mask(topology, known)).astype(np.int32)


def solvent_atoms(topology: Topology) -> npt.NDArray[np.int32]:
    """Water and ion atoms, by residue name in any letter case (`Cl`, `NA+`, `HOH`)."""
    known = {r.upper() for r in (*SOLVENT_RESNAMES, *ION_RESNAMES)}
    kinds = {r for r in set(topology.residue_names) if r.upper() in known}
    return np.flatnonzero(_residue_mask(topology, kinds)).astype(np.int32)


def default_layers(topology: Topology, sigma_A: float) -> list[dict[str, Any]]:
    """The layers a system opens with, as `protocol.Layer` fields: [] (every atom, the
    session's parameters) when nothing is solvent, ion or ligand; else the polymer, and each
    kind of other residue (a ligand) as a finer layer of its own. Solvent is left out (hidden);
    a system that is nothing but solvent stays whole."""
    n = topology.n_atoms
    if not n:
        return []
    solvent = solvent_atoms(topology)
    polymer = polymer_atoms(topology)
    others = np.ones(n, dtype=bool)
    others[solvent] = False
    others[polymer] = False
    rest = np.flatnonzero(others)
    if len(solvent) == 0 and len(rest) == 0:
        return []
    if len(solvent) == n:
        return []
    layers: list[dict[str, Any]] = []
    if len(polymer):
        layers.append({"name": "polymer", "selection": POLYMER_SELECTION})
    if len(rest):
        names = sorted({topology.residue_names[int(i)] for i in rest})
        ligand = f"not ({POLYMER_SELECTION})"
        if len(names) <= 8:
            ligand = "resname " + " ".join(names)
        elif len(solvent):
            waters = sorted({topology.residue_names[int(i)] for i in solvent})
            ligand += " and not resname " + " ".join(waters)
        fine = round(max(0.3, sigma_A * LIGAND_SIGMA_FACTOR), 3) if len(polymer) else None
        layer: dict[str, Any] = {"name": "ligand" if len(polymer) else "molecules"}
        layer["selection"] = ligand
        if fine is not None:
            layer["sigma_A"] = fine
        layers.append(layer)
    return layers


_PROBE: Selector | None = None


def check_syntax(text: str, limits: SelectionLimits | None = None) -> None:
    """Raise SelectionError when `text` does not parse (or, with `limits`, is too long or
    nested too deeply), before any topology is at hand (a one-atom system answers every
    keyword; what a selection finds, and what it costs on a real system, is not checked)."""
    global _PROBE
    if _PROBE is None:
        from protocol import WireArray

        probe = Topology(
            n_atoms=1,
            elements=["C"],
            names=["CA"],
            residue_ids=WireArray.from_numpy(np.ones(1), "<i4"),
            residue_names=["ALA"],
            chain_ids=["A"],
            bonds=WireArray.from_numpy(np.zeros((0, 2)), "<i4"),
        )
        _PROBE = Selector(probe)
    _PROBE.select(text, np.zeros((1, 3), dtype=np.float32), None, limits)
