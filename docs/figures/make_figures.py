"""The figures of docs/rendering.md, drawn by the renderer itself (on the CPU device).

    python docs/figures/make_figures.py [--out docs/figures] [--device cpu]

`warped_scales.png`: villin (the demo's protein, hydrogens included), a nucleic-acid fragment
(the first eight nucleotides of RNA 1K5I, MDAnalysisTests) and a ring-rich ligand
(MDAnalysisTests' Molecule.mol2, three rings) at three scales, classical (top of each pair) and
warped (below), iso-surfaces at the default relative level. Needs MDAnalysis and
MDAnalysisTests for the last two molecules.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from protocol import RenderParams  # noqa: E402
from server.render.camera import fit_camera, orbit  # noqa: E402
from server.render.renderer import Renderer  # noqa: E402
from structures.reader import load  # noqa: E402


def villin() -> tuple[object, np.ndarray]:
    from tests.render.molecules import villin as mol

    m = mol()
    return m.topology, m.positions


def from_file(path: str, residues: slice | None = None) -> tuple[object, np.ndarray]:
    """A structure read the way users' files are (structures.reader), optionally only some
    residues of it (written to a temporary PDB first)."""
    import tempfile

    import MDAnalysis as mda

    if residues is not None:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            u = mda.Universe(path)
            tmp = Path(tempfile.mkdtemp()) / "part.pdb"
            u.residues[residues].atoms.write(str(tmp))
        path = str(tmp)
    structure = load(path)
    return structure.topology, structure.positions(0)


def molecules() -> list[tuple[str, object, np.ndarray, list[float]]]:
    from MDAnalysisTests.datafiles import RNA_PDB, mol2_molecule

    top_v, pos_v = villin()
    top_r, pos_r = from_file(RNA_PDB, slice(0, 8))
    top_l, pos_l = from_file(mol2_molecule)
    return [
        ("villin (582 atoms)", top_v, pos_v, [1.0, 2.0, 4.0]),
        ("RNA fragment (8 nt)", top_r, pos_r, [1.0, 2.0, 4.0]),
        ("ring-rich ligand", top_l, pos_l, [0.7, 1.2, 2.0]),
    ]


def draw(
    renderer: Renderer, top: object, pos: np.ndarray, params: RenderParams, w: int, h: int
) -> np.ndarray:
    renderer.set_topology(top)  # type: ignore[arg-type]
    renderer.set_positions(pos)
    cam = orbit(fit_camera(pos, w, h, margin=1.5), 30.0, 15.0)
    renderer.render(params, cam, w, h)
    return renderer.read_rgba()[..., :3]


def warped_scales(out: Path, device: str) -> Path:
    from PIL import Image, ImageDraw

    w, h = 240, 200
    mols = molecules()
    renderer = Renderer(device)
    rows = []
    for _name, top, pos, sigmas in mols:
        for space in ("classical", "warped"):
            tiles = [
                draw(
                    renderer,
                    top,
                    pos,
                    RenderParams(sigma_A=s, scale_space=space, color_by="element"),  # type: ignore[arg-type]
                    w,
                    h,
                )
                for s in sigmas
            ]
            rows.append(np.concatenate(tiles, axis=1))
    sheet = Image.fromarray(np.concatenate(rows, axis=0))
    pen = ImageDraw.Draw(sheet)
    for m, (name, _top, _pos, sigmas) in enumerate(mols):
        for row, space in enumerate(("classical", "warped")):
            y = (2 * m + row) * h
            for c, s in enumerate(sigmas):
                pen.text((c * w + 6, y + 4), f"{name}  {space}  sigma {s} A", fill=(230, 230, 230))
    path = out / "warped_scales.png"
    sheet.save(path)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "figures")
    ap.add_argument("--device", default="cpu")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    print(warped_scales(args.out, args.device))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
