"""Figures 5.6, 5.7 and 5.8 of the thesis, redrawn, next to scalesteer's warped density.

``python -m thesis.chapter5 [--out docs/thesis] [--dpi 110]`` writes

- ``fig5_6_three_atoms.png``: the two-bond, three-atom molecule of constant density: classical,
  eq. 5.4, eq. 5.6 and scalesteer's warped density (iso-contours in the molecule's plane);
- ``fig5_7_center_density.png``: the same molecule with a 2.5x denser centre atom;
- ``fig5_8_ring.png``: a six-ring: the classical density fills it, eq. 5.4 creases it and
  leaves artifacts at the projections' seams, the warped density keeps it a ring;
- ``fig5_crease_ratio.png``: second differences along a line through each density as the
  step halves (a smooth field shrinks 4x, a creased one 2x).

Needs matplotlib (``pip install 'scalesteer[thesis]'``).
"""

from __future__ import annotations

import argparse
import importlib
from pathlib import Path
from typing import Any

import numpy as np

import protocol as p
from server.render.skeleton import Skeleton, carved_density
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


def warped_of(graph: BondGraph, strength: float = 1.0) -> Any:
    skeleton = Skeleton.of(topology_of(graph))

    def density(points: Any, sigma: float) -> Any:
        s, _ = carved_density(points, graph.positions, graph.densities, skeleton, sigma, strength)
        return s

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
    gx, gy, pts = plane(3.4, 181)
    fig, axes = plt.subplots(1, len(panels), figsize=(3.0 * len(panels), 3.2))
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
        ("eq. 5.4 (thesis)", lambda pts, s: thesis_density(graph, pts, s)),
    ]
    if squared:
        out.append(
            ("eq. 5.6, squared D (thesis)", lambda pts, s: thesis_density(graph, pts, s, True))
        )
    out.append(("warped (scalesteer)", warped_of(graph)))
    return out


def crease_figure(path: Path, dpi: int) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5.2, 3.2))
    graph = ring()
    origin, direction = np.array([0.0, 0.05, 0.0]), np.array([1.0, 0.1, 0.0])
    steps = [0.08 / 2**k for k in range(5)]
    warped = warped_of(graph)
    for name, fn in (
        ("classical", lambda pts: classical_density(graph, pts, 1.0)),
        ("eq. 5.4", lambda pts: thesis_density(graph, pts, 1.0)),
        ("warped", lambda pts: warped(pts, 1.0)),
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


def make_figures(out: Path, dpi: int = 110) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    three = three_atoms()
    dense = three_atoms(2.5)
    hexagon = ring()
    return [
        figure(three, 1.0, thesis_panels(three), out / "fig5_6_three_atoms.png", dpi),
        figure(dense, 1.0, thesis_panels(dense, False), out / "fig5_7_center_density.png", dpi),
        figure(hexagon, 1.0, thesis_panels(hexagon, False), out / "fig5_8_ring.png", dpi),
        crease_figure(out / "fig5_crease_ratio.png", dpi),
    ]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m thesis.chapter5", description=__doc__)
    ap.add_argument("--out", type=Path, default=Path("docs/thesis"))
    ap.add_argument("--dpi", type=int, default=110)
    args = ap.parse_args(argv)
    for path in make_figures(args.out, args.dpi):
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
