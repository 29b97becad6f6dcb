"""`scalesteer render`: one structure (PDB, mmCIF, GRO, XYZ, ...) to one image file.

scalesteer render structure.pdb -o out.png --sigma 1.5 --mode iso --size 800x600
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path
from typing import Any

from server.render.errors import RenderError

_EPILOG = (
    "Structures are read through MDAnalysis (pip install 'scalesteer[replay]'); the image "
    "format follows the output suffix (.png, .jpg)."
)


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"size must look like 800x600, got {text!r}") from None
    if w < 1 or h < 1:
        raise argparse.ArgumentTypeError(f"size must be at least 1x1, got {text!r}")
    return w, h


def size_refusal(width: int, height: int) -> str | None:
    """Why `--size` cannot be rendered (None: it can), said before anything is read: a size
    past the renderer's limits had ended in a traceback from warp after reading the file."""
    from server.render.renderer import MAX_PIXELS, MAX_SIDE

    if max(width, height) <= MAX_SIDE and width * height <= MAX_PIXELS:
        return None
    limit = f"at most {MAX_SIDE} px a side and {MAX_PIXELS:,} px (3840x2160)"
    return f"--size {width}x{height}: {limit}"


def device_refusal(device: str) -> str | None:
    """Why `--device` cannot render here (None: it can), said before anything is read."""
    from server.render.device import resolve
    from server.render.errors import RenderError

    try:
        resolve(device)
    except RenderError as exc:
        return f"--device {device}: {exc}"
    return None


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="scalesteer render",
        description="Render the multiscale Gaussian density of one structure to an image.",
        epilog=_EPILOG,
    )
    p.add_argument("structure", help="structure file (pdb, cif, gro, xyz, psf, ...)")
    p.add_argument("trajectory", nargs="*", help="optional trajectory files (dcd, xtc, ...)")
    p.add_argument("-o", "--output", required=True, help="image file to write (.png or .jpg)")
    p.add_argument("--sigma", type=float, default=1.5, help="Gaussian scale in angstrom")
    p.add_argument("--mode", choices=("iso", "volume"), default="iso")
    p.add_argument(
        "--iso",
        type=float,
        default=0.25,
        help="iso level, a fraction of the mean density at the atoms (see --levels)",
    )
    p.add_argument(
        "--levels",
        choices=("mean", "absolute"),
        default="mean",
        help="iso levels relative to the mean density at the atoms, or in atoms of density",
    )
    p.add_argument(
        "--scale-space",
        choices=("classical", "geodesic", "carved"),
        default="classical",
        help="geodesic: the thesis's warped density, distances through the bond graph; carved: "
        "a narrower Gaussian density carved away from the bonds (docs/rendering.md)",
    )
    p.add_argument("--warp-strength", type=float, default=1.0, help="0 (classical) to 1")
    p.add_argument(
        "--geodesic-smoothing",
        type=float,
        default=0.6,
        help="the geodesic density's soft minimum, in sigmas (0.05-2; smaller is creased)",
    )
    p.add_argument(
        "--weights",
        choices=("uniform", "electrons"),
        default="uniform",
        help="atom densities: one per atom or the electron count",
    )
    p.add_argument("--size", type=_size, default=(800, 600), help="WxH in pixels")
    p.add_argument(
        "--color-by",
        choices=("element", "residue", "chain", "uniform", "bfactor", "charge"),
        default="element",
    )
    p.add_argument("--radius-mode", choices=("uniform", "vdw"), default="uniform")
    p.add_argument("--tf-preset", choices=("cloud", "shells", "iso-like"), default="cloud")
    p.add_argument("--projection", choices=("perspective", "orthographic"), default="perspective")
    p.add_argument("--ao", action="store_true", help="density-based ambient occlusion")
    add_layer_options(p)
    p.add_argument("--device", default="auto", help="auto, cpu or cuda:N")
    p.add_argument("--frame", type=int, default=0, help="trajectory frame index")
    add_periodic_options(p)
    return p


def add_layer_options(ap: argparse.ArgumentParser) -> None:
    """--select, --layers, --all-atoms: what part of the system is drawn (the same for
    `render` and `batch`)."""
    ap.add_argument(
        "--select",
        metavar="SELECTION",
        help="draw only these atoms (MDAnalysis selection syntax, e.g. 'protein and not name H*')",
    )
    ap.add_argument(
        "--layers",
        metavar="JSON",
        help='a JSON list of layers, e.g. \'[{"selection": "protein", "opacity": 0.5}, '
        '{"selection": "resname LIG", "mode": "licorice"}]\' (fields: docs/dashboard.md, "Layers")',
    )
    ap.add_argument(
        "--all-atoms",
        action="store_true",
        help="draw every atom; without --select, --layers or --all-atoms a solvated system "
        "opens on its molecule: solvent and ions hidden, a ligand at half the sigma",
    )


def layer_option(args: argparse.Namespace) -> list[Any] | None:
    """The layers --select, --layers or --all-atoms name (None: none of them, so the default
    layers apply); ValueError naming the option when one is wrong."""
    from protocol import Layer
    from protocol.fields import unknown_keys

    if sum(x is not None for x in (args.select, args.layers)) + args.all_atoms > 1:
        raise ValueError("give at most one of --select, --layers and --all-atoms")
    if args.select is not None:
        return [Layer(name="selection", selection=args.select)]
    if args.all_atoms:
        return []
    if args.layers is None:
        return None
    try:
        raw = json.loads(args.layers)
    except json.JSONDecodeError as exc:
        raise ValueError(f"--layers is not valid JSON: {exc.msg}") from None
    if not isinstance(raw, list):
        raise ValueError("--layers must be a JSON list of layers")
    for i, item in enumerate(raw):
        unknown = unknown_keys(Layer, item, f"layers.{i}")
        if unknown:
            raise ValueError(f"{unknown}: unknown field")
    return [Layer.model_validate(item) for item in raw]


def add_periodic_options(p: argparse.ArgumentParser) -> None:
    """The periodic options (protocol `render_params`), shared with `scalesteer batch`."""
    p.add_argument(
        "--periodic",
        choices=("off", "whole", "wrap", "molecules", "unwrap"),
        default=None,
        help="a periodic box's frames: molecules made whole (whole), also put in the box "
        "(molecules, the default), atoms put in the box (wrap), followed across it (unwrap), "
        "or as read (off)",
    )
    p.add_argument(
        "--center",
        default=None,
        metavar="SELECTION",
        help="centre the box on these atoms ('auto', the default: protein and nucleic acids; "
        "'off': none)",
    )
    p.add_argument(
        "--fit",
        default=None,
        metavar="SELECTION",
        help="superpose each frame on the first one by these atoms (rotation and translation)",
    )
    p.add_argument(
        "--fit-translation", action="store_true", help="--fit translates only (needs --fit)"
    )
    p.add_argument("--show-cell", action="store_true", help="draw the periodic box's outline")


def periodic_fields(args: argparse.Namespace) -> dict[str, object]:
    """The render parameters the periodic options set (those given; they win over the same
    fields of a `--params`)."""
    if args.fit_translation and args.fit is None:
        raise ValueError("--fit-translation needs --fit SELECTION (the atoms to superpose)")
    out: dict[str, object] = {}
    if args.periodic is not None:
        out["periodic"] = args.periodic
    if args.center is not None:
        if args.center in ("off", "auto"):
            out["center"] = args.center
        else:
            out.update(center="selection", center_selection=args.center)
    if args.fit is not None:
        out.update(fit="translation" if args.fit_translation else "rotation")
        out["fit_selection"] = args.fit
    if args.show_cell:
        out["show_cell"] = True
    return out


def _fail(msg: str) -> int:
    print(f"scalesteer render: error: {msg}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    out = Path(args.output)
    if out.suffix.lower() not in (".png", ".jpg", ".jpeg"):
        return _fail(f"output must end in .png or .jpg: {args.output}")
    width, height = args.size
    if (refusal := size_refusal(width, height) or device_refusal(args.device)) is not None:
        return _fail(refusal)

    from pydantic import ValidationError

    from protocol import Lighting, RenderParams
    from protocol.fields import error_location
    from server.pipeline.periodic import PeriodicError, check_periodic
    from server.pipeline.selections import check_layers, opening_params
    from server.render.camera import fit_camera
    from structures.errors import StructureError
    from structures.reader import load

    try:
        layers = layer_option(args)
        named: dict[str, Any] = {} if layers is None else {"layers": layers}
        params = RenderParams(
            **named,
            mode=args.mode,
            sigma_A=args.sigma,
            iso_level=args.iso,
            level_scale=args.levels,
            scale_space=args.scale_space,
            warp_strength=args.warp_strength,
            geodesic_smoothing=args.geodesic_smoothing,
            density_weights=args.weights,
            color_by=args.color_by,
            radius_mode=args.radius_mode,
            tf_preset=args.tf_preset,
            lighting=Lighting(ambient_occlusion=args.ao),
            **periodic_fields(args),
        )
    except ValidationError as exc:
        loc, msg = error_location(exc.errors(include_url=False)[0])
        return _fail(f"invalid {'.'.join(loc)}: {msg}")
    except ValueError as exc:
        return _fail(str(exc))
    try:
        check_layers(params)  # a user's own files on their own machine: no cost limits
    except ValueError as exc:
        # --select is drawn as the one layer: say which option the text came from
        return _fail(f"--select: {exc}" if args.select is not None else str(exc))
    try:
        check_periodic(params)
    except PeriodicError as exc:
        return _fail(periodic_refusal(exc.path, exc.reason, args))
    try:
        structure = load(args.structure, args.trajectory)
    except StructureError as exc:
        return _fail(str(exc))
    params = opening_params(params, structure.topology)  # as every entry point opens a system
    if not 0 <= args.frame < structure.n_frames:
        return _fail(f"frame {args.frame} out of range: the input has {structure.n_frames} frames")

    from PIL import Image

    from server.pipeline.overlay import draw_cell
    from server.pipeline.periodic import displayed_cell
    from server.pipeline.selections import FrameLayers, LayerError
    from server.render.layerplan import visible_atoms
    from server.render.layers import LayeredRenderer
    from server.render.renderer import Renderer
    from structures.selection_pool import InProcess

    try:
        with warnings.catch_warnings():
            # re-reading a frame repeats the reader's format notes (e.g. placeholder CRYST1)
            warnings.simplefilter("ignore")
            raw, box = structure.frame(args.frame)
        topology = structure.topology
        n = topology.n_atoms
        selections = InProcess(topology)
        plans = FrameLayers(params, topology, selections).plans(raw, args.frame, box)
        positions, how = _displayed(structure, params, selections, raw, box, args.device)
        shown = visible_atoms(plans, n)
        if not len(shown):
            return _fail("the selection takes no atoms: nothing to draw")
        camera = fit_camera(positions[shown], width, height, args.projection)
        renderer = Renderer(args.device, max_atoms=max(n, 1))
        t0 = time.perf_counter()
        if plans is None:
            renderer.set_topology(topology)
            renderer.set_positions(positions)
            renderer.render(params, camera, width, height)
            rgba = renderer.read_rgba()
        else:
            layered = LayeredRenderer(lambda: Renderer(args.device, max_atoms=max(n, 1)))
            layered.render(plans, topology, 1, positions, 1, camera, width, height)
            rgba = layered.read_rgba()
        ms = (time.perf_counter() - t0) * 1e3
        cell = displayed_cell(how, box) if params.show_cell else None
        if cell is not None:
            rgba = draw_cell(rgba, camera, cell)
    except RenderError as exc:
        return _fail(str(exc))
    except LayerError as exc:
        return _fail(str(exc.error))
    except PeriodicError as exc:
        return _fail(periodic_refusal(exc.path, exc.reason, args))
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rgba[..., :3]).save(out)
    except OSError as exc:
        return _fail(f"cannot write {args.output}: {exc}")
    drawn = f"{len(shown)} of {n} atoms" if len(shown) < n else f"{n} atoms"
    print(f"{out}: {width}x{height}, {drawn}, {args.mode}, {renderer.device}, {ms:.1f} ms")
    return 0


def _displayed(
    structure: Any, params: Any, selections: Any, raw: Any, box: Any, device: str
) -> tuple[Any, Any]:
    """The frame as the periodic options display it (the fit's reference: the first frame),
    and how (None: as read)."""
    from server.pipeline.periodic import REFERENCE_FRAME, PeriodicOptions, needs_display
    from server.render import device as render_device
    from server.render.periodic import PeriodicTransform

    if not needs_display(params, box):
        return raw, None
    options = PeriodicOptions(params, selections)
    how = options.get(box)
    transform = PeriodicTransform(render_device.resolve(device))
    transform.set_topology(structure.topology)
    if how.fit != "off":
        ref_raw, ref_box = structure.frame(REFERENCE_FRAME)
        transform.apply(ref_raw, ref_box, options.get(ref_box), reference=True)
        transform.restart()
    shown = transform.apply(raw, box, how)
    return shown.positions, shown


def periodic_refusal(field: str, reason: str, args: argparse.Namespace) -> str:
    """A centre or fit selection's refusal (`field` names its render parameter), named by the
    option that gave the selection, or as `params.<field>` when the render parameters did."""
    from server.pipeline.periodic import TRANSLATION_FIT

    if field == "fit_selection" and args.fit is not None:
        return f"--fit: {reason.replace(TRANSLATION_FIT, '--fit-translation')}"
    if field == "center_selection" and args.center not in (None, "off", "auto"):
        return f"--center: {reason}"
    return f"params.{field}: {reason}"


if __name__ == "__main__":
    raise SystemExit(main())
