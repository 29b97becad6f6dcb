"""Figures 5.6, 5.7 and 5.8 of the thesis, redrawn, next to scalesteer's geodesic density.

``python -m thesis.chapter5 [--out docs/thesis] [--dpi 110] [--no-renders]`` writes

- ``fig5_6_three_atoms.png``: the two-bond, three-atom molecule of constant density: classical,
  eq. 5.5 with eq. 5.4's distance (the thesis's field), eq. 5.6 (its squared-D variant), and the
  smooth geodesic density at smoothing 0.1 and 0.6 (iso-contours in the molecule's plane, which
  is the 2-D field as printed: the molecule is flat);
- ``fig5_7_center_density.png``: the same molecule with a 2.5x denser centre atom;
- ``fig5_8_ring.png``: a six-ring: the classical density fills it, eq. 5.4 creases it along the
  spokes where the nearest bond changes (the thesis's ring artifact, section 5.3.3), the
  geodesic density keeps it a ring, smooth;
- ``fig5_crease_ratio.png``: second differences along a line through each density as the
  step halves (a smooth field shrinks 4x, a creased one 2x);
- ``fig5_renders.png`` (unless ``--no-renders``): the same fields in 3-D, ray-cast by the
  renderer on the CPU: the ring, the three-atom molecule and the villin headpiece at three
  scales, classical / geodesic at smoothing 0.05 (the nearest to the thesis's field the
  renderer draws) / geodesic at 0.6.

Needs matplotlib (``pip install 'scalesteer[thesis]'``).
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path
from typing import Any

import numpy as np

import protocol as p
from server.render import geodesic
from thesis.molecular import (
    BondGraph,
    classical_density,
    crease_ratio,
    ring,
    thesis_density,
    three_atoms,
)


def _pyplot() -> Any:
    mpl: Any = importlib.import_module("matplotlib")
    mpl.use("Agg")
    return importlib.import_module("matplotlib.pyplot")


def topology_of(graph: BondGraph) -> p.Topology:
    n = len(graph.positions)
    return p.Topology(
        n_atoms=n,
        elements=["C"] * n,
        names=[f"C{i}" for i in range(n)],
        residue_ids=p.WireArray.from_numpy(np.ones(n, np.int32), "<i4"),
        residue_names=["MOL"] * n,
        chain_ids=["A"] * n,
        bonds=p.WireArray.from_numpy(graph.bonds.astype(np.int32), "<i4"),
    )


def geodesic_of(graph: BondGraph, smoothing: float) -> Any:
    """The smooth geodesic density of a thesis molecule (its own gain, every atom reached)."""
    bonds = geodesic.BondGraph.from_bonds(len(graph.positions), graph.bonds)
    field = geodesic.Geodesic.build(graph.positions, graph.densities, bonds, 50.0, graph.gain)

    def density(points: Any, sigma: float) -> Any:
        return field.density(points, sigma, smoothing=smoothing, cutoff_sigmas=None)

    return density


def plane(extent: float, n: int) -> tuple[Any, Any, Any]:
    x = np.linspace(-extent, extent, n)
    gx, gy = np.meshgrid(x, x)
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1)
    return gx, gy, pts


def panel(ax: Any, graph: BondGraph, values: Any, gx: Any, gy: Any, title: str) -> None:
    v = values.reshape(gx.shape)
    levels = np.linspace(0.05, 0.95, 10) * float(v.max())
    ax.contour(gx, gy, v, levels=levels, cmap="viridis", linewidths=0.9)
    for i, j in graph.bonds:
        a, b = graph.positions[i], graph.positions[j]
        ax.plot([a[0], b[0]], [a[1], b[1]], color="0.55", lw=1.0)
    ax.scatter(graph.positions[:, 0], graph.positions[:, 1], s=14, color="k", zorder=3)
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def figure(
    graph: BondGraph, sigma: float, panels: list[tuple[str, Any]], path: Path, dpi: int
) -> Path:
    plt = _pyplot()
    gx, gy, pts = plane(3.4, 121)
    fig, axes = plt.subplots(1, len(panels), figsize=(2.8 * len(panels), 3.1))
    for ax, (title, fn) in zip(np.atleast_1d(axes), panels, strict=True):
        panel(ax, graph, fn(pts, sigma), gx, gy, title)
    fig.suptitle(f"iso-contours in the molecule's plane, sigma = {sigma} A", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def thesis_panels(graph: BondGraph, squared: bool = True) -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = [
        ("classical", lambda pts, s: classical_density(graph, pts, s)),
        ("eq. 5.5 with 5.4 (thesis)", lambda pts, s: thesis_density(graph, pts, s)),
    ]
    if squared:
        out.append(
            ("eq. 5.6, squared D (thesis)", lambda pts, s: thesis_density(graph, pts, s, True))
        )
    out.append(("geodesic, smoothing 0.1", geodesic_of(graph, 0.1)))
    out.append(("geodesic, smoothing 0.6", geodesic_of(graph, 0.6)))
    return out


def crease_figure(path: Path, dpi: int) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.2, 3.2))
    graph = ring()
    origin, direction = np.array([0.0, 0.05, 0.0]), np.array([1.0, 0.1, 0.0])
    steps = [0.08 / 2**k for k in range(5)]
    fine = geodesic_of(graph, 0.1)
    smooth = geodesic_of(graph, 0.6)
    for name, fn in (
        ("classical", lambda pts: classical_density(graph, pts, 1.0)),
        ("eq. 5.4", lambda pts: thesis_density(graph, pts, 1.0)),
        ("geodesic 0.1", lambda pts: fine(pts, 1.0)),
        ("geodesic 0.6", lambda pts: smooth(pts, 1.0)),
    ):
        ratios = [crease_ratio(fn, origin, direction, 3.0, h) for h in steps]
        ax.plot(steps, ratios, marker="o", label=name)
    ax.axhline(4.0, color="0.6", lw=0.8, ls="--")
    ax.axhline(2.0, color="0.6", lw=0.8, ls=":")
    ax.set_xscale("log")
    ax.set_xlabel("sampling step h (A)")
    ax.set_ylabel("max |2nd difference| at h / at h/2")
    ax.set_title("six-ring, sigma 1 A: 4 = smooth, 2 = creased", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def render_figure(path: Path, dpi: int, size: tuple[int, int] = (220, 165)) -> Path:
    """The fields in 3-D, ray-cast on the CPU device."""
    from protocol import RenderParams
    from server.render import Renderer
    from server.render.camera import fit_camera, orbit

    plt = _pyplot()
    molecules = [
        ("six-ring", topology_of(ring()), ring().positions, (0.9,)),
        ("three atoms", topology_of(three_atoms()), three_atoms().positions, (0.8,)),
        ("villin", *villin(), (0.8, 1.5, 3.0)),
    ]
    columns = [("classical", "classical", 0.6), ("geodesic 0.05", "geodesic", 0.05)]
    columns.append(("geodesic 0.6", "geodesic", 0.6))
    rows = [(name, topo, pos, s) for name, topo, pos, sigmas in molecules for s in sigmas]
    fig, axes = plt.subplots(len(rows), len(columns), figsize=(2.4 * len(columns), 1.9 * len(rows)))
    w, h = size
    for r, (name, topo, pos, sigma) in enumerate(rows):
        cam = orbit(fit_camera(np.asarray(pos, np.float32), w, h), 30.0, 20.0)
        renderer = Renderer("cpu")
        renderer.set_topology(topo)
        renderer.set_positions(np.asarray(pos, np.float32))
        for c, (title, space, smoothing) in enumerate(columns):
            params = RenderParams(sigma_A=sigma, scale_space=space, geodesic_smoothing=smoothing)
            renderer.render(params, cam, w, h)
            ax = axes[r, c]
            ax.imshow(renderer.read_rgba())
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(title, fontsize=9)
            if c == 0:
                ax.set_ylabel(f"{name}\nsigma {sigma} A", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return path


def villin() -> tuple[p.Topology, Any]:
    """The villin headpiece the demo simulates (582 atoms with hydrogens and bonds), as the
    render tests keep it."""
    d = np.load(Path(__file__).resolve().parents[1] / "tests" / "render" / "data" / "villin.npz")
    elements = [str(e) for e in d["elements"]]
    n = len(elements)
    topology = p.Topology(
        n_atoms=n,
        elements=elements,
        names=[str(x) for x in d["names"]],
        residue_ids=p.WireArray.from_numpy(d["residue_ids"].astype(np.int32), "<i4"),
        residue_names=[str(r) for r in d["residues"]],
        chain_ids=["A"] * n,
        bonds=p.WireArray.from_numpy(d["bonds"].astype(np.int32), "<i4"),
    )
    return topology, d["positions"].astype(np.float32)


def make_figures(out: Path, dpi: int = 110, renders: bool = True) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    three = three_atoms()
    dense = three_atoms(2.5)
    hexagon = ring()
    paths = [
        figure(three, 1.0, thesis_panels(three), out / "fig5_6_three_atoms.png", dpi),
        figure(dense, 1.0, thesis_panels(dense, False), out / "fig5_7_center_density.png", dpi),
        figure(hexagon, 1.0, thesis_panels(hexagon, False), out / "fig5_8_ring.png", dpi),
        crease_figure(out / "fig5_crease_ratio.png", dpi),
    ]
    if renders:
        paths.append(render_figure(out / "fig5_renders.png", dpi))
    return paths


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m thesis.chapter5", description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("docs/thesis"))
    ap.add_argument("--dpi", type=int, default=110)
    ap.add_argument("--no-renders", action="store_true", help="skip the ray-cast figure")
    args = ap.parse_args(argv)
    for path in make_figures(args.out, args.dpi, not args.no_renders):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
