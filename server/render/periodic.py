"""Periodic boxes shown as chemists look at them: molecules made whole, atoms or molecules
wrapped into the box or followed across it, a selection centred, the frame fitted onto a
reference, all on the device that renders.

A frame's displayed positions are its positions moved by whole box vectors (each atom its own
integer image `n_i`), then by one rigid motion:

    y_i = x_i + (n_i + m_i) B + t        out_i = R (y_i - c) + c_ref

where B holds the box vectors as rows. The steps, in the order GROMACS' `trjconv -pbc mol
-center -fit` and MDAnalysis' transformations (unwrap, center_in_box, wrap, fit_rot_trans)
apply them:

1. whole: `n_i` joins each molecule (a connected part of the bond graph) across the box. Each
   molecule is a tree of bonds rooted at its lowest-index atom (which stays, as in MDAnalysis'
   `make_whole`); a bond's minimum image gives each atom its image relative to its parent, and
   the images along the path to the root are summed by pointer jumping (log2 of the deepest
   atom's depth launches, over the atoms deeper than one bond: a water box costs one). Sums of
   integers are exact: a whole molecule is its atoms moved by box vectors, nothing else.
   `unwrap` makes the first frame whole, then follows every atom from frame to frame without
   jumps (the image that moved it least: MDAnalysis' NoJump, in fractional coordinates, so a
   changing box is followed too).
2. centre: `t` moves the centre of geometry of a selection to the centre of the box.
3. wrap: `m_i` puts every atom (`wrap`) or every molecule's centre of geometry (`molecules`)
   into the box [0, 1)^3 in fractional coordinates.
4. fit: `R`, `c`, `c_ref` superpose a selection onto its positions in a reference frame
   (least squares, Kabsch: the SVD of the 3x3 correlation), or translate it there only.

Sums (a selection's centre, each molecule's centre, the correlation) are float64, taken in
chunks of consecutive atoms with one atomic add per chunk (per molecule run).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, no_type_check

import numpy as np
import numpy.typing as npt
import warp

from protocol import Topology
from server.render import device as _device  # noqa: F401  (warp initialised quietly)
from server.render.boxes import Options, Shown, usable_box
from server.render.graphs import GraphCache
from server.render.loans import HostLoans

wp: Any = warp


GRAPHS = 4
"""Captured launch sequences a transform keeps (one per recent set of steps and box)."""

CHUNK = wp.constant(64)
"""Atoms one thread sums before its atomic add."""


# ---------------------------------------------------------------------- kernels


@wp.func
@no_type_check
def _image(s: wp.vec3) -> wp.vec3i:
    """The integer image that brings fractional displacement `s` nearest to zero."""
    return wp.vec3i(int(wp.round(s[0])), int(wp.round(s[1])), int(wp.round(s[2])))


@wp.func
@no_type_check
def _cell_of(s: wp.vec3) -> wp.vec3i:
    """The box a fractional position lies in (0 for the primary box)."""
    return wp.vec3i(int(wp.floor(s[0])), int(wp.floor(s[1])), int(wp.floor(s[2])))


@wp.func
@no_type_check
def _shift(to_cart: wp.mat33, n: wp.vec3i):
    return to_cart * wp.vec3(float(n[0]), float(n[1]), float(n[2]))


@wp.func
@no_type_check
def _centre_shift(sums: wp.array(dtype=wp.vec3d), count: int, target: wp.vec3):
    """t: what moves the selection's centre of geometry to `target` (0 without one)."""
    if count == 0:
        return wp.vec3(0.0, 0.0, 0.0)
    c = sums[0] / wp.float64(count)
    return target - wp.vec3(float(c[0]), float(c[1]), float(c[2]))


@wp.kernel(enable_backward=False)
@no_type_check
def bond_images_kernel(
    pos: wp.array(dtype=wp.vec3),
    to_frac: wp.mat33,
    parent: wp.array(dtype=wp.int32),
    images: wp.array(dtype=wp.vec3i),
    images_b: wp.array(dtype=wp.vec3i),
):
    """Each atom's image relative to its parent in its molecule's tree (0 for a root): the
    minimum image of the bond. Written to both pointer-jumping buffers."""
    i = wp.tid()
    p = parent[i]
    k = wp.vec3i(0, 0, 0)
    if p != i:
        k = -_image(to_frac * (pos[i] - pos[p]))
    images[i] = k
    images_b[i] = k


@wp.kernel(enable_backward=False)
@no_type_check
def jump_kernel(
    deep: wp.array(dtype=wp.int32),
    images_in: wp.array(dtype=wp.vec3i),
    up_in: wp.array(dtype=wp.int32),
    images_out: wp.array(dtype=wp.vec3i),
    up_out: wp.array(dtype=wp.int32),
):
    """One pointer-jumping round over the atoms deeper than one bond: each adds the image sum
    of the atom its pointer names and points where that one points."""
    j = wp.tid()
    i = deep[j]
    u = up_in[i]
    images_out[i] = images_in[i] + images_in[u]
    up_out[i] = up_in[u]


@wp.kernel(enable_backward=False)
@no_type_check
def nojump_kernel(
    pos: wp.array(dtype=wp.vec3),
    to_frac: wp.mat33,
    prev: wp.array(dtype=wp.vec3),
    images: wp.array(dtype=wp.vec3i),
    start: int,
):
    """Follow each atom from the last frame: the image that moved it least (with `start`, only
    remember where it is: its images came from the whole molecule)."""
    i = wp.tid()
    s = to_frac * pos[i]
    if start == 0:
        images[i] = images[i] - _image(s - prev[i])
    prev[i] = s


@wp.kernel(enable_backward=False)
@no_type_check
def selection_sum_kernel(
    pos: wp.array(dtype=wp.vec3),
    images: wp.array(dtype=wp.vec3i),
    to_cart: wp.mat33,
    atoms: wp.array(dtype=wp.int32),
    sums: wp.array(dtype=wp.vec3d),
):
    """The sum of the selection's whole positions (a chunk per thread)."""
    t = wp.tid()
    n = atoms.shape[0]
    acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    for j in range(t * CHUNK, wp.min(n, (t + 1) * CHUNK)):
        i = atoms[j]
        y = pos[i] + _shift(to_cart, images[i])
        acc += wp.vec3d(wp.float64(y[0]), wp.float64(y[1]), wp.float64(y[2]))
    wp.atomic_add(sums, 0, acc)


@wp.kernel(enable_backward=False)
@no_type_check
def molecule_sum_kernel(
    pos: wp.array(dtype=wp.vec3),
    images: wp.array(dtype=wp.vec3i),
    to_cart: wp.mat33,
    order: wp.array(dtype=wp.int32),
    molecule: wp.array(dtype=wp.int32),
    sums: wp.array(dtype=wp.vec3d),
):
    """Each molecule's sum of whole positions, over the atoms grouped by molecule: a chunk per
    thread, one atomic add per molecule run."""
    t = wp.tid()
    n = order.shape[0]
    acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    current = wp.int32(-1)
    for j in range(t * CHUNK, wp.min(n, (t + 1) * CHUNK)):
        i = order[j]
        m = molecule[i]
        if m != current:
            if current >= 0:
                wp.atomic_add(sums, current, acc)
            acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
            current = m
        y = pos[i] + _shift(to_cart, images[i])
        acc += wp.vec3d(wp.float64(y[0]), wp.float64(y[1]), wp.float64(y[2]))
    if current >= 0:
        wp.atomic_add(sums, current, acc)


@wp.func
@no_type_check
def _wrapped(
    i: int,
    pos: wp.array(dtype=wp.vec3),
    images: wp.array(dtype=wp.vec3i),
    to_cart: wp.mat33,
    to_frac: wp.mat33,
    t: wp.vec3,
    wrap: int,
    molecule: wp.array(dtype=wp.int32),
    mol_sums: wp.array(dtype=wp.vec3d),
    mol_counts: wp.array(dtype=wp.int32),
):
    """y_i: atom i whole, centred and wrapped (wrap 0: not, 1: the atom, 2: its molecule)."""
    y = pos[i] + _shift(to_cart, images[i]) + t
    if wrap == 1:
        y = y - _shift(to_cart, _cell_of(to_frac * y))
    elif wrap == 2:
        m = molecule[i]
        c = mol_sums[m] / wp.float64(mol_counts[m])
        centre = wp.vec3(float(c[0]), float(c[1]), float(c[2])) + t
        y = y - _shift(to_cart, _cell_of(to_frac * centre))
    return y


@wp.kernel(enable_backward=False)
@no_type_check
def fit_sum_kernel(
    pos: wp.array(dtype=wp.vec3),
    images: wp.array(dtype=wp.vec3i),
    to_cart: wp.mat33,
    to_frac: wp.mat33,
    centre_sums: wp.array(dtype=wp.vec3d),
    centre_count: int,
    target: wp.vec3,
    wrap: int,
    molecule: wp.array(dtype=wp.int32),
    mol_sums: wp.array(dtype=wp.vec3d),
    mol_counts: wp.array(dtype=wp.int32),
    atoms: wp.array(dtype=wp.int32),
    reference: wp.array(dtype=wp.vec3),
    sums: wp.array(dtype=wp.vec3d),
    correlation: wp.array(dtype=wp.mat33d),
):
    """Over the fit selection: the sum of its positions (before the fit) and of their outer
    products with the centred reference."""
    tid = wp.tid()
    n = atoms.shape[0]
    t = _centre_shift(centre_sums, centre_count, target)
    acc = wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(0.0))
    cor = wp.mat33d()
    for j in range(tid * CHUNK, wp.min(n, (tid + 1) * CHUNK)):
        y = _wrapped(
            atoms[j], pos, images, to_cart, to_frac, t, wrap, molecule, mol_sums, mol_counts
        )
        p = wp.vec3d(wp.float64(y[0]), wp.float64(y[1]), wp.float64(y[2]))
        r = reference[j]
        q = wp.vec3d(wp.float64(r[0]), wp.float64(r[1]), wp.float64(r[2]))
        acc += p
        cor += wp.outer(p, q)
    wp.atomic_add(sums, 0, acc)
    wp.atomic_add(correlation, 0, cor)


@wp.kernel(enable_backward=False)
@no_type_check
def gather_kernel(
    pos: wp.array(dtype=wp.vec3),
    images: wp.array(dtype=wp.vec3i),
    to_cart: wp.mat33,
    to_frac: wp.mat33,
    centre_sums: wp.array(dtype=wp.vec3d),
    centre_count: int,
    target: wp.vec3,
    wrap: int,
    molecule: wp.array(dtype=wp.int32),
    mol_sums: wp.array(dtype=wp.vec3d),
    mol_counts: wp.array(dtype=wp.int32),
    atoms: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.vec3),
):
    """The fit selection's positions before the fit (a reference frame's)."""
    j = wp.tid()
    t = _centre_shift(centre_sums, centre_count, target)
    out[j] = _wrapped(
        atoms[j], pos, images, to_cart, to_frac, t, wrap, molecule, mol_sums, mol_counts
    )


@wp.kernel(enable_backward=False)
@no_type_check
def solve_kernel(
    centre_sums: wp.array(dtype=wp.vec3d),
    centre_count: int,
    target: wp.vec3,
    fit: int,
    fit_count: int,
    fit_sums: wp.array(dtype=wp.vec3d),
    correlation: wp.array(dtype=wp.mat33d),
    reference_centre: wp.vec3,
    motion: wp.array(dtype=wp.vec3),
    rotation: wp.array(dtype=wp.mat33),
):
    """One thread: the centring shift t, and the fit's rotation R and centres c, c_ref
    (R = identity, c = c_ref = 0 without a fit; R = identity for a translation only, and for
    fit atoms along one line)."""
    motion[0] = _centre_shift(centre_sums, centre_count, target)
    rot = wp.identity(n=3, dtype=float)
    c = wp.vec3(0.0, 0.0, 0.0)
    c_ref = wp.vec3(0.0, 0.0, 0.0)
    if fit > 0 and fit_count > 0:
        cd = fit_sums[0] / wp.float64(fit_count)
        c = wp.vec3(float(cd[0]), float(cd[1]), float(cd[2]))
        c_ref = reference_centre
        if fit == 2:
            # the reference is centred, so sum((p - c) q^T) = sum(p q^T)
            h = correlation[0]
            u = wp.mat33d()
            sigma = wp.vec3d()
            v = wp.mat33d()
            wp.svd3(h, u, sigma, v)
            s0 = wp.abs(sigma[0])
            s1 = wp.abs(sigma[1])
            s2 = wp.abs(sigma[2])
            top = wp.max(s0, wp.max(s1, s2))
            middle = s0 + s1 + s2 - top - wp.min(s0, wp.min(s1, s2))
            # atoms on one line (or fewer than three) leave the rotation about it free: the
            # fit then translates only, rather than turn the frame by an arbitrary angle
            solved = middle > wp.float64(1.0e-6) * top
            d = wp.float64(1.0)
            if wp.determinant(v * wp.transpose(u)) < wp.float64(0.0):
                d = wp.float64(-1.0)
            flip = wp.mat33d(
                wp.float64(1.0), wp.float64(0.0), wp.float64(0.0),
                wp.float64(0.0), wp.float64(1.0), wp.float64(0.0),
                wp.float64(0.0), wp.float64(0.0), d,
            )  # fmt: skip
            r = wp.identity(n=3, dtype=wp.float64)
            if solved:
                r = v * flip * wp.transpose(u)
            rot = wp.mat33(
                float(r[0, 0]), float(r[0, 1]), float(r[0, 2]),
                float(r[1, 0]), float(r[1, 1]), float(r[1, 2]),
                float(r[2, 0]), float(r[2, 1]), float(r[2, 2]),
            )  # fmt: skip
    motion[1] = c
    motion[2] = c_ref
    rotation[0] = rot


@wp.kernel(enable_backward=False)
@no_type_check
def apply_kernel(
    pos: wp.array(dtype=wp.vec3),
    images: wp.array(dtype=wp.vec3i),
    to_cart: wp.mat33,
    to_frac: wp.mat33,
    centre_sums: wp.array(dtype=wp.vec3d),
    centre_count: int,
    target: wp.vec3,
    wrap: int,
    molecule: wp.array(dtype=wp.int32),
    mol_sums: wp.array(dtype=wp.vec3d),
    mol_counts: wp.array(dtype=wp.int32),
    motion: wp.array(dtype=wp.vec3),
    rotation: wp.array(dtype=wp.mat33),
    out: wp.array(dtype=wp.vec3),
):
    """Every atom's displayed position."""
    i = wp.tid()
    t = _centre_shift(centre_sums, centre_count, target)
    y = _wrapped(i, pos, images, to_cart, to_frac, t, wrap, molecule, mol_sums, mol_counts)
    out[i] = rotation[0] * (y - motion[1]) + motion[2]


# ---------------------------------------------------------------------- topology (host)


@dataclass(frozen=True, eq=False)
class Molecules:
    """The molecules of a topology (connected parts of its bond graph) as trees of bonds,
    each rooted at its lowest-index atom (host arrays, built once per topology)."""

    n_atoms: int
    molecule: npt.NDArray[np.int32]
    """Each atom's molecule, numbered by root."""
    parent: npt.NDArray[np.int32]
    """Each atom's parent in its tree (a root is its own)."""
    depth: npt.NDArray[np.int32]
    order: npt.NDArray[np.int32]
    """The atoms grouped by molecule (each group in index order)."""
    counts: npt.NDArray[np.int32]
    """Atoms per molecule."""

    @property
    def n_molecules(self) -> int:
        return len(self.counts)

    @property
    def deep(self) -> npt.NDArray[np.int32]:
        """The atoms more than one bond from their root: the pointer-jumping ones."""
        return np.flatnonzero(self.depth >= 2).astype(np.int32)

    @property
    def rounds(self) -> int:
        """Pointer-jumping rounds that sum every path (log2 of the deepest depth)."""
        deepest = int(self.depth.max()) if self.n_atoms else 0
        return math.ceil(math.log2(deepest)) if deepest > 1 else 0

    @classmethod
    def of(cls, topology: Topology) -> Molecules:
        n = int(topology.n_atoms)
        bonds = topology.bonds.to_numpy().reshape(-1, 2).astype(np.int64)
        return cls.from_bonds(n, bonds)

    @classmethod
    def from_bonds(cls, n: int, bonds: npt.NDArray[np.int64]) -> Molecules:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import breadth_first_order, connected_components

        if n == 0:
            empty = np.zeros(0, dtype=np.int32)
            return cls(0, empty, empty, empty, empty, empty)
        bonds = bonds.reshape(-1, 2)
        bonds = bonds[bonds[:, 0] != bonds[:, 1]]
        graph = coo_matrix(
            (np.ones(len(bonds), dtype=np.int8), (bonds[:, 0], bonds[:, 1])), shape=(n, n)
        )
        _count, label = connected_components(graph, directed=False)
        root_of = np.full(int(label.max()) + 1, n, dtype=np.int64)
        np.minimum.at(root_of, label, np.arange(n))
        root = root_of[label]
        # one breadth-first search from a node bonded to every root: each molecule's tree is
        # rooted at its lowest atom, and every tree edge is a bond
        roots = np.flatnonzero(root == np.arange(n))
        rows = np.concatenate([bonds[:, 0], bonds[:, 1], np.full(len(roots), n)])
        cols = np.concatenate([bonds[:, 1], bonds[:, 0], roots])
        linked = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n + 1, n + 1))
        _order, before = breadth_first_order(
            linked.tocsr(), n, directed=True, return_predecessors=True
        )
        parent = np.asarray(before[:n], dtype=np.int64)
        parent[roots] = roots
        molecule_roots, molecule, counts = np.unique(root, return_inverse=True, return_counts=True)
        del molecule_roots
        return cls(
            n_atoms=n,
            molecule=molecule.astype(np.int32),
            parent=parent.astype(np.int32),
            depth=_depths(parent).astype(np.int32),
            order=np.argsort(molecule, kind="stable").astype(np.int32),
            counts=counts.astype(np.int32),
        )


def _depths(parent: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
    """Each atom's bonds to its root, by pointer jumping (log2 of the deepest depth passes)."""
    depth: npt.NDArray[np.int64] = (parent != np.arange(len(parent))).astype(np.int64)
    up = parent.copy()
    while True:
        jumped = up[up]
        if np.array_equal(jumped, up):
            return depth
        depth = depth + depth[up]
        up = jumped


# ---------------------------------------------------------------------- the transform


class PeriodicTransform:
    """A stream of frames of one topology shown as `Options` say, on `device`. Keeps what
    spans frames: where each atom was (unwrap) and the fit's reference."""

    def __init__(self, device: str = "cpu", graphs: bool | None = None) -> None:
        """`graphs`: replay repeated frames as CUDA graphs (None: on a CUDA device)."""
        self.device = device
        self._topology: Topology | None = None
        self._molecules: Molecules | None = None
        self._n = 0
        self._images_a: Any = None
        self._images_b: Any = None
        self._up_a: Any = None
        self._up_b: Any = None
        self._parent: Any = None
        self._deep: Any = None
        self._rounds = 0
        self._molecule: Any = None
        self._order: Any = None
        self._mol_counts: Any = None
        self._mol_sums: Any = None
        self._prev: Any = None
        self._out: Any = None
        self._pos: Any = None
        self._small: dict[str, Any] = {}
        self._atoms_cache: dict[bytes, Any] = {}
        self._following = False
        """`unwrap` has a last frame to follow from."""
        self._reference: Any = None
        self._reference_centre = np.zeros(3)
        self._reference_key: tuple[Any, ...] | None = None
        self._cell: npt.NDArray[np.float64] | None = None
        self._loans: HostLoans | None = None
        enabled = device.startswith("cuda") if graphs is None else graphs
        self._graphs = GraphCache(device, GRAPHS, enabled, "periodic steps")
        """Page-locked buffers the displayed frames are read back into (CUDA devices)."""

    @property
    def replays(self) -> int:
        """Frames whose kernels were replayed as a graph."""
        return self._graphs.replays

    # ------------------------------------------------------------------ set-up

    def set_topology(self, topology: Topology) -> None:
        """A new system: its molecules (once), fresh buffers, nothing followed."""
        if topology is self._topology:
            return
        mol = Molecules.of(topology)
        d = self.device
        n = mol.n_atoms
        self._graphs.clear()  # they hold the old buffers' addresses
        self._topology = topology
        self._molecules = mol
        self._n = n
        self._parent = wp.array(mol.parent, dtype=wp.int32, device=d)
        self._up_a = wp.array(mol.parent, dtype=wp.int32, device=d)
        self._up_b = wp.array(mol.parent, dtype=wp.int32, device=d)
        self._deep = wp.array(mol.deep, dtype=wp.int32, device=d)
        self._rounds = mol.rounds
        self._molecule = wp.array(mol.molecule, dtype=wp.int32, device=d)
        self._order = wp.array(mol.order, dtype=wp.int32, device=d)
        self._mol_counts = wp.array(mol.counts, dtype=wp.int32, device=d)
        self._mol_sums = wp.zeros(mol.n_molecules, dtype=wp.vec3d, device=d)
        self._images_a = wp.zeros(n, dtype=wp.vec3i, device=d)
        self._images_b = wp.zeros(n, dtype=wp.vec3i, device=d)
        self._prev = wp.zeros(n, dtype=wp.vec3, device=d)
        self._out = wp.zeros(n, dtype=wp.vec3, device=d)
        self._pos = wp.zeros(n, dtype=wp.vec3, device=d)
        self._small = {
            "centre_sums": wp.zeros(1, dtype=wp.vec3d, device=d),
            "fit_sums": wp.zeros(1, dtype=wp.vec3d, device=d),
            "correlation": wp.zeros(1, dtype=wp.mat33d, device=d),
            "motion": wp.zeros(3, dtype=wp.vec3, device=d),
            "rotation": wp.zeros(1, dtype=wp.mat33, device=d),
        }
        self._atoms_cache = {}
        self.restart()

    @property
    def molecules(self) -> Molecules | None:
        return self._molecules

    def restart(self) -> None:
        """The next frame does not follow the last one (a seek, a new stream): `unwrap` makes
        it whole again. The fit keeps its reference."""
        self._following = False

    def nbytes(self) -> int:
        """Device memory held (for the memory budget)."""
        arrays = [
            self._parent, self._up_a, self._up_b, self._deep, self._molecule, self._order,
            self._mol_counts, self._mol_sums, self._images_a, self._images_b, self._prev,
            self._out, self._pos,
        ]  # fmt: skip
        return sum(int(a.capacity) for a in arrays if a is not None)

    def _atoms(self, atoms: npt.NDArray[np.int32] | None) -> Any:
        key = b"" if atoms is None else np.asarray(atoms, dtype=np.int32).tobytes()
        found = self._atoms_cache.get(key)
        if found is None:
            if len(self._atoms_cache) > 8:
                self._atoms_cache.clear()
            values = np.zeros(0, np.int32) if atoms is None else np.asarray(atoms, np.int32)
            found = self._atoms_cache[key] = wp.array(values, dtype=wp.int32, device=self.device)
        return found

    # ------------------------------------------------------------------ frames

    def apply(
        self,
        positions: npt.ArrayLike,
        box: npt.ArrayLike | None,
        options: Options,
        reference: bool = False,
    ) -> Shown:
        """The frame as displayed. Positions (n, 3) in angstrom; `box` rows are its vectors
        (a box that is no cell, `usable_box`, counts as none: the box steps are skipped).
        The fit's reference is the first frame of these options, or this one (`reference`)."""
        self.upload(positions)
        self.run(box, options, reference)
        return self.result()

    def upload(self, positions: npt.ArrayLike) -> None:
        """Copy a frame's positions to the device."""
        if self._topology is None:
            raise ValueError("set_topology must come before a frame")
        pos = np.ascontiguousarray(positions, dtype=np.float32).reshape(-1, 3)
        if len(pos) != self._n:
            raise ValueError(f"positions have {len(pos)} atoms, the topology has {self._n}")
        if self._n:
            wp.copy(self._pos, wp.array(pos, dtype=wp.vec3, device="cpu", copy=False))

    @property
    def device_positions(self) -> Any:
        """The device buffer `upload` fills (a caller whose frame is on the device already
        copies it here) and `run` reads."""
        return self._pos

    @property
    def device_result(self) -> Any:
        """The displayed positions `run` leaves on the device."""
        return self._out

    def run(self, box: npt.ArrayLike | None, options: Options, reference: bool = False) -> None:
        """Launch the frame's kernels (asynchronous on a CUDA device): the displayed positions
        go to `device_result`. On a CUDA device a frame that launches what one of the last few
        launched (the same steps, box and selections: a trajectory in a box of fixed shape)
        replays them as one CUDA graph, without the host's cost per launch."""
        cell = usable_box(box)
        self._cell = cell
        mode = options.mode if cell is not None else "off"
        if cell is None:
            to_cart = np.eye(3)
            to_frac = np.eye(3)
            target = np.zeros(3)
        else:
            to_cart = cell.T
            to_frac = np.asarray(np.linalg.inv(cell.T), dtype=np.float64)
            target = cell.sum(axis=0) / 2.0
        centre = options.centre if options.centre is not None and len(options.centre) else None
        fit = {"translation": 1, "rotation": 2}.get(options.fit, 0)
        fit_atoms = options.fit_atoms if fit and options.fit_atoms is not None else None
        step = _Step(
            mode=mode,
            start=mode == "unwrap" and not self._following,
            whole=mode in ("whole", "molecules") or (mode == "wrap" and centre is not None),
            wrap={"wrap": 1, "molecules": 2}.get(mode, 0),
            cart=to_cart.astype(np.float32),
            frac=to_frac.astype(np.float32),
            target=target.astype(np.float32),
            centre=self._atoms(centre) if centre is not None else None,
            fit=fit if fit_atoms is not None and len(fit_atoms) else 0,
            fit_atoms=self._atoms(fit_atoms) if fit_atoms is not None and len(fit_atoms) else None,
        )
        self._following = mode == "unwrap"
        take = False
        if step.fit_atoms is not None:
            key = (*options.key(), cell is None)
            take = reference or self._reference_key != key
            self._reference_key = key
        if take or not self._graphs.enabled:
            self._launch(step, take)
            return
        replay_key = (
            self._n, step.mode, step.start, step.whole, step.wrap, step.fit,
            step.cart.tobytes(), step.frac.tobytes(), step.target.tobytes(),
            _address(step.centre), _address(step.fit_atoms), _address(self._reference),
            _length(step.centre), _length(step.fit_atoms),
            self._reference_centre.tobytes(),
        )  # fmt: skip
        self._graphs.run(replay_key, lambda: self._launch(step, False))

    def _launch(self, step: _Step, take_reference: bool) -> None:
        d = self.device
        n = self._n
        images = self._images_a
        wp_cart = wp.mat33(*step.cart.ravel())
        wp_frac = wp.mat33(*step.frac.ravel())
        if step.mode == "unwrap":
            if step.start:
                images = self._whole(wp_frac)
            wp.launch(
                nojump_kernel, n, inputs=[self._pos, wp_frac, self._prev, images, int(step.start)],
                device=d,
            )  # fmt: skip
            if images is not self._images_a:
                wp.copy(self._images_a, images)  # the followed images live in buffer a
                images = self._images_a
        elif step.whole:
            images = self._whole(wp_frac)
        else:
            images.zero_()
        small = self._small
        count = 0 if step.centre is None else len(step.centre)
        small["centre_sums"].zero_()
        if count:
            wp.launch(
                selection_sum_kernel, _chunks(count),
                inputs=[self._pos, images, wp_cart, step.centre, small["centre_sums"]],
                device=d,
            )  # fmt: skip
        wp_target = wp.vec3(*step.target)
        if step.wrap == 2:
            self._mol_sums.zero_()
            wp.launch(
                molecule_sum_kernel, _chunks(n),
                inputs=[self._pos, images, wp_cart, self._order, self._molecule, self._mol_sums],
                device=d,
            )  # fmt: skip
        common = [
            self._pos, images, wp_cart, wp_frac, small["centre_sums"], count, wp_target, step.wrap,
            self._molecule, self._mol_sums, self._mol_counts,
        ]  # fmt: skip
        fit_count = 0 if step.fit_atoms is None else len(step.fit_atoms)
        if fit_count:
            if take_reference:
                self._take_reference(common, step.fit_atoms, fit_count)
            small["fit_sums"].zero_()
            small["correlation"].zero_()
            wp.launch(
                fit_sum_kernel, _chunks(fit_count),
                inputs=[*common, step.fit_atoms, self._reference, small["fit_sums"],
                        small["correlation"]],
                device=d,
            )  # fmt: skip
        ref_centre = wp.vec3(*self._reference_centre.astype(np.float32))
        wp.launch(
            solve_kernel, 1,
            inputs=[small["centre_sums"], count, wp_target, step.fit if fit_count else 0,
                    fit_count, small["fit_sums"], small["correlation"], ref_centre,
                    small["motion"], small["rotation"]],
            device=d,
        )  # fmt: skip
        if n:
            wp.launch(
                apply_kernel, n, inputs=[*common, small["motion"], small["rotation"], self._out],
                device=d,
            )  # fmt: skip

    def result(self) -> Shown:
        """The last `run`'s frame, read back to the host (waits for the device) into an array
        no later frame writes: from a CUDA device into a lent page-locked buffer (`HostLoans`),
        on the CPU a copy."""
        out = self._read_back()
        motion = self._small["motion"].numpy().astype(np.float64)
        rotation = self._small["rotation"].numpy().reshape(3, 3).astype(np.float64)
        shown_cell = None
        cell = self._cell
        if cell is not None:
            origin = (np.zeros(3) - motion[1]) @ rotation.T + motion[2]
            shown_cell = (origin, cell @ rotation.T)
        return Shown(
            positions=out,
            rotation=rotation,
            centre=motion[1],
            reference_centre=motion[2],
            cell=shown_cell,
        )

    def _read_back(self) -> npt.NDArray[np.float32]:
        n = self._n
        if not n:
            return np.zeros((0, 3), np.float32)
        if not self.device.startswith("cuda"):
            return np.array(self._out.numpy().reshape(-1, 3), dtype=np.float32)
        loans = self._loans
        if loans is None or loans.n != n:
            loans = self._loans = HostLoans(n)
        owner, array = loans.lend()
        wp.copy(owner, self._out, count=n)
        wp.synchronize_stream(wp.get_stream(self.device))
        return array

    def _whole(self, to_frac: Any) -> Any:
        """Every molecule whole: each atom's image summed along its tree (returns the buffer
        that holds them)."""
        d = self.device
        n = self._n
        a, b = self._images_a, self._images_b
        wp.launch(bond_images_kernel, n, inputs=[self._pos, to_frac, self._parent, a, b], device=d)
        if self._rounds:
            wp.copy(self._up_a, self._parent)
            wp.copy(self._up_b, self._parent)
            ups = (self._up_a, self._up_b)
            bufs = (a, b)
            deep = len(self._deep)
            for r in range(self._rounds):
                src, dst = r % 2, 1 - r % 2
                wp.launch(
                    jump_kernel, deep,
                    inputs=[self._deep, bufs[src], ups[src], bufs[dst], ups[dst]], device=d,
                )  # fmt: skip
            return bufs[self._rounds % 2]
        return a

    def _take_reference(self, common: list[Any], atoms: Any, count: int) -> None:
        """This frame's fit-selection positions (before the fit) become the reference."""
        got = wp.zeros(count, dtype=wp.vec3, device=self.device)
        wp.launch(gather_kernel, count, inputs=[*common, atoms, got], device=self.device)
        ref = got.numpy().astype(np.float64)
        centre = ref.mean(axis=0)
        self._reference_centre = centre
        self._reference = wp.array(
            (ref - centre).astype(np.float32), dtype=wp.vec3, device=self.device
        )


@dataclass(frozen=True, eq=False)
class _Step:
    """What one frame's kernels do (host values, decided before any launch)."""

    mode: str
    start: bool
    """`unwrap` makes this frame whole (it follows no frame)."""
    whole: bool
    wrap: int
    cart: npt.NDArray[np.float32]
    frac: npt.NDArray[np.float32]
    target: npt.NDArray[np.float32]
    centre: Any
    fit: int
    fit_atoms: Any


def _address(array: Any) -> int:
    return 0 if array is None else int(array.ptr or 0)


def _length(array: Any) -> int:
    return 0 if array is None else len(array)


def _chunks(count: int) -> int:
    return int((count + CHUNK - 1) // CHUNK)
