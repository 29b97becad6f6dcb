"""Licorice and tube layers: sphere and capsule hits against the analytic oracle, the trace
pieces of a backbone, and golden images of both beside a surface."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from protocol import Layer, RenderParams, Topology, WireArray
from server.render.camera import camera_frame, fit_camera, image_rays, orbit
from server.render.geometry import (
    HELIX_SCALE,
    GeometryRenderer,
    catmull_rom,
    trace_pieces,
    tube_spans,
)
from server.render.layerplan import plan_layers
from server.render.layers import LayeredRenderer
from server.render.renderer import Renderer
from tests.render.conftest import make_topology
from tests.render.golden_images import H, W, check_golden, gramicidin


def _sphere_t(o: np.ndarray, d: np.ndarray, c: np.ndarray, r: float) -> np.ndarray:
    oc = o - c
    b = np.einsum("...k,...k", d, oc)
    h = b * b - (np.einsum("...k,...k", oc, oc) - r * r)
    t = -b - np.sqrt(np.maximum(h, 0.0))
    return np.where((h >= 0) & (t >= 0), t, np.inf)


def _capsule_t(o: np.ndarray, d: np.ndarray, a: np.ndarray, b: np.ndarray, r: float) -> np.ndarray:
    """Brute force: the first point along each ray within r of the segment (fine steps, then
    bisection), an oracle independent of the kernel's closed form."""
    ts = np.linspace(0.0, 200.0, 8001)
    ba = b - a
    best = np.full(o.shape[:-1], np.inf)
    flat_o, flat_d = o.reshape(-1, 3), d.reshape(-1, 3)
    out = best.reshape(-1)

    def dist(t: np.ndarray, i: int) -> np.ndarray:
        p = flat_o[i] + np.multiply.outer(t, flat_d[i])
        s = np.clip((p - a) @ ba / (ba @ ba), 0.0, 1.0)
        return np.linalg.norm(p - (a + np.multiply.outer(s, ba)), axis=-1) - r

    for i in range(len(flat_o)):
        f = dist(ts, i)
        inside = np.flatnonzero(f <= 0)
        if not len(inside) or inside[0] == 0:
            continue
        lo, hi = ts[inside[0] - 1], ts[inside[0]]
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if dist(np.array([mid]), i)[0] <= 0:
                hi = mid
            else:
                lo = mid
        out[i] = hi
    return best


def _render(device: str, top: Topology, pos: np.ndarray, style: str, r: float, size=(40, 30)):
    g = GeometryRenderer(device, style)  # type: ignore[arg-type]
    g.set_topology(top)
    g.set_positions(pos)
    cam = orbit(fit_camera(pos, *size, margin=1.5), 30.0, 25.0)
    g.render(RenderParams(), cam, *size, r)
    return g, cam


def test_a_lone_atom_is_a_sphere(device: str) -> None:
    top = make_topology(1)
    pos = np.array([[1.0, -2.0, 0.5]], np.float32)
    g, cam = _render(device, top, pos, "licorice", 0.8)
    o, d = image_rays(camera_frame(cam, 40, 30))
    want = _sphere_t(o, d, pos[0].astype(np.float64), 0.8)
    got = g.read_depth()
    assert np.isfinite(want).sum() > 20
    assert np.array_equal(np.isfinite(got), np.isfinite(want))
    hit = np.isfinite(want)
    assert np.allclose(got[hit], want[hit], atol=1e-4)
    assert (g.read_atom_ids()[hit] == 0).all() and (g.read_atom_ids()[~hit] == -1).all()


def test_a_bond_is_two_capsules_owned_by_their_atoms(device: str) -> None:
    top = make_topology(2, bonds=np.array([[0, 1]]))
    pos = np.array([[0.0, 0.0, 0.0], [2.4, 0.6, -0.3]], np.float32)
    r = 0.35
    g, cam = _render(device, top, pos, "licorice", r)
    o, d = image_rays(camera_frame(cam, 40, 30))
    a, b = pos[0].astype(np.float64), pos[1].astype(np.float64)
    mid = 0.5 * (a + b)
    t0, t1 = _capsule_t(o, d, a, mid, r), _capsule_t(o, d, mid, b, r)
    want = np.minimum(t0, t1)
    got = g.read_depth()
    hit = np.isfinite(want)
    assert hit.sum() > 30
    # pixels whose ray only grazes the surface may differ in coverage; depths agree elsewhere
    agree = np.isfinite(got) == hit
    assert agree.mean() > 0.98
    both = hit & np.isfinite(got)
    assert np.allclose(got[both], want[both], atol=2e-3)
    ids = g.read_atom_ids()
    gap = np.abs(np.minimum(t0, 1e9) - np.minimum(t1, 1e9))
    clear = both & (gap > 1e-2)
    assert np.array_equal(ids[clear], np.where(t0 <= t1, 0, 1)[clear])


def test_the_backbone_trace_breaks_at_chains_and_gaps() -> None:
    n = 14
    chains = ["A"] * 7 + ["B"] * 7
    resids = np.arange(1, n + 1)
    resids[3:7] += 5  # residues 4-7 of chain A are missing: a gap after the third
    top = make_topology(n, chains=chains).model_copy(
        update={"names": ["CA"] * n, "residue_ids": WireArray.from_numpy(resids, "<i4")}
    )
    pos = np.zeros((n, 3), np.float32)
    pos[:, 0] = np.arange(n) * 3.8
    pos[11:, 1] = 20.0  # chain B stretched apart after its fourth residue
    pieces = trace_pieces(top, pos)
    assert [p.tolist() for p in pieces] == [[0, 1, 2], [3, 4, 5, 6], [7, 8, 9, 10], [11, 12, 13]]
    curve = catmull_rom(pos[:4].astype(np.float64), 4)
    assert len(curve) == 13
    assert np.allclose(curve[::4], pos[:4])  # through every trace atom


GOLDEN = {
    "layers_licorice": RenderParams(
        sigma_A=1.6,
        color_by="chain",
        layers=[
            Layer(name="sticks", selection="ALL", mode="licorice", color_by="element"),
        ],
    ),
    "layers_tube_surface": RenderParams(
        sigma_A=1.6,
        color_by="chain",
        layers=[
            Layer(name="tube", selection="ALL", mode="tube", radius_A=0.8),
            Layer(name="surface", selection="ALL", opacity=0.35),
        ],
    ),
}


@pytest.mark.parametrize("name", sorted(GOLDEN))
def test_golden_shapes(device: str, name: str, regen_golden: bool) -> None:
    top, pos = gramicidin()
    n = top.n_atoms
    plans = plan_layers(GOLDEN[name], n, lambda t: (np.arange(n, dtype=np.int32), t))
    assert plans is not None
    lr = LayeredRenderer(lambda: Renderer(device))
    cam = orbit(fit_camera(pos, W, H, margin=2.0), 35.0, 20.0)
    lr.render(plans, top, 1, pos, 1, cam, W, H)
    check_golden(lr.read_rgba()[..., :3], name, device, regen_golden)
    assert (lr.read_atom_ids() >= 0).mean() > 0.05


def _ideal_helix(n: int) -> np.ndarray:
    """CA positions of an ideal alpha helix along z: radius 2.3 A, 100 degrees and 1.5 A a
    residue."""
    k = np.arange(n)
    a = np.radians(100.0) * k
    return np.stack([2.3 * np.cos(a), 2.3 * np.sin(a), 1.5 * k], axis=1).astype(np.float32)


def test_a_helix_is_a_cylinder_along_its_axis_and_the_coil_joins_it() -> None:
    helix = _ideal_helix(12)
    coil = helix[-1] + np.array([[3.8 * (i + 1), 0.0, 0.0] for i in range(4)], np.float32)
    pos = np.concatenate([helix, coil])
    codes = np.array([1] * 12 + [0] * 4, np.uint8)
    piece = np.arange(len(pos), dtype=np.int32)
    p0, p1, owner, scale = tube_spans([piece], pos, codes)
    cyl = scale == HELIX_SCALE
    assert cyl.sum() == 12 - 4  # one capsule between consecutive axis points
    ends = np.concatenate([p0[cyl], p1[cyl]])
    # on the helix's own axis (z) within 0.3 A: four residues turn 400 degrees, not 360
    assert np.linalg.norm(ends[:, :2], axis=1).max() < 0.3
    assert np.all(np.diff(p0[cyl][:, 2]) > 0)
    # the coil runs from the helix's last CA through the coil atoms, at the plain radius
    plain = scale == 1.0
    assert np.allclose(p0[plain][0], helix[-1]) and np.allclose(p1[plain][-1], coil[-1])
    assert set(owner[cyl]) <= set(range(12)) and set(owner[plain]) <= set(range(11, 16))
    # without codes: one spline through every atom
    q0, _q1, _o, s = tube_spans([piece], pos, None)
    assert (s == 1.0).all() and len(q0) == (len(pos) - 1) * 4


def test_villin_secondary_structure_tube(device: str, regen_golden: bool) -> None:
    """Villin's three helices as cylinders, the loops as a thin tube (DSSP by MDAnalysis)."""
    pytest.importorskip("MDAnalysis")
    from structures.selection import Selector

    d = np.load(Path(__file__).parent / "data" / "villin.npz")
    pos = d["positions"].astype(np.float32)
    top = make_topology(
        len(pos),
        elements=[str(e) for e in d["elements"]],
        residues=[str(r) for r in d["residues"]],
        chains=["A"] * len(pos),
        bonds=d["bonds"],
    ).model_copy(
        update={
            "names": [str(x) for x in d["names"]],
            "residue_ids": WireArray.from_numpy(d["residue_ids"], "<i4"),
        }
    )
    codes = Selector(top).secondary(pos)
    ca = np.array([str(x) == "CA" for x in d["names"]])
    assert (codes[ca] == 1).sum() >= 15  # three short helices
    n = top.n_atoms
    params = RenderParams(
        color_by="residue",
        layers=[Layer(name="cartoon", selection="all", mode="tube")],
    )
    plans = plan_layers(params, n, lambda t: (np.arange(n, dtype=np.int32), t), lambda: codes)
    assert plans is not None and plans[0].secondary is not None
    lr = LayeredRenderer(lambda: Renderer(device))
    cam = orbit(fit_camera(pos, W, H, margin=1.5), 20.0, 10.0)
    lr.render(plans, top, 1, pos, 1, cam, W, H)
    check_golden(lr.read_rgba()[..., :3], "layers_tube_secondary", device, regen_golden)
