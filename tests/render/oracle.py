"""Brute-force numpy references (float64) for the render kernels: every atom against every
point, no grid, no skipping. They restate the documented formulas, not the kernels' code."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from server.render.segments import ramp_integral
from server.render.transfer import TransferTable

F = npt.NDArray[np.float64]


@dataclass(frozen=True)
class Molecule:
    positions: F  # (n, 3)
    weights: F  # (n,)
    sigmas: F  # (n,) Gaussian width per atom
    k: float  # truncation in sigmas
    colors: F  # (n, 3)


def _kernel(e: F, k: float) -> tuple[F, F]:
    """K(e) = exp(-e) (1 - (e / ek)^16)^2 inside e < ek = k^2 / 2 (0 outside), and -dK/de."""
    ek = 0.5 * k * k
    inside = e < ek
    u = np.where(inside, e / ek, 1.0)
    w = (1.0 - u**16) ** 2
    dw = -32.0 * (1.0 - u**16) * u**15 / ek
    x = np.exp(-e)
    return np.where(inside, x * w, 0.0), np.where(inside, x * (w - dw), 0.0)


def contributions(mol: Molecule, points: npt.ArrayLike) -> tuple[F, F]:
    """(m, n) terms w_i K(d^2 / 2 s_i^2) (zero beyond k s_i) and (m, n, 3) offsets a - p."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    off = mol.positions[None, :, :] - p[:, None, :]
    d2 = (off**2).sum(axis=-1)
    e = d2 / (2.0 * mol.sigmas[None, :] ** 2)
    term = mol.weights[None, :] * _kernel(e, mol.k)[0]
    return term, off


def density(mol: Molecule, points: npt.ArrayLike) -> tuple[F, F]:
    """S and its gradient at points."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    off = mol.positions[None, :, :] - p[:, None, :]
    e = (off**2).sum(axis=-1) / (2.0 * mol.sigmas[None, :] ** 2)
    value, slope = _kernel(e, mol.k)
    term = mol.weights[None, :] * value
    grad = ((mol.weights[None, :] * slope)[:, :, None] * off / mol.sigmas[None, :, None] ** 2).sum(
        axis=1
    )
    return term.sum(axis=1), grad


def density_chunked(mol: Molecule, points: npt.ArrayLike, chunk: int = 4096) -> F:
    return density_of(mol, points, chunk)


def density_of(mol: Molecule, points: npt.ArrayLike, chunk: int = 4096) -> F:
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.empty(len(p))
    for i in range(0, len(p), chunk):
        out[i : i + chunk] = contributions(mol, p[i : i + chunk])[0].sum(axis=1)
    return out


def top_atom(mol: Molecule, points: npt.ArrayLike) -> tuple[npt.NDArray[np.int64], F]:
    """Index of the largest contribution (lowest index on ties) and its margin over the
    runner-up (relative), to tell clear cases from near ties."""
    term, _ = contributions(mol, points)
    best = np.argmax(term, axis=1)
    top = np.take_along_axis(term, best[:, None], axis=1)[:, 0]
    second = np.sort(term, axis=1)[:, -2] if term.shape[1] > 1 else np.zeros(len(term))
    return best, (top - second) / np.maximum(top, 1e-300)


def blended_color(mol: Molecule, points: npt.ArrayLike) -> F:
    term, _ = contributions(mol, points)
    s = term.sum(axis=1, keepdims=True)
    out: F = (term @ mol.colors) / np.where(s > 0, s, 1.0)
    return out


@dataclass(frozen=True)
class IsoResult:
    t: F  # (rays,) refined hit distance, inf for none
    # a lattice sample lies within 1e-4 of the iso level, or the hit bracket crosses it
    # more than once
    ambiguous: npt.NDArray[np.bool_]


def first_crossings(
    mol: Molecule | Callable[[F], F],
    origins: F,
    dirs: F,
    t_range: tuple[float, float],
    dt: float,
    iso: float,
) -> IsoResult:
    """First sign change of S - iso on the lattice t_k = k dt (k dt in t_range, t >= 0),
    relative to the sign at the first sample, refined to 1e-9 by bisection. `mol` is the
    Gaussian molecule, or any density as a function of (m, 3) points."""
    if isinstance(mol, Molecule):
        molecule = mol

        def density_chunked(_: object, pts: F) -> F:
            return density_of(molecule, pts)

    else:
        fn = mol

        def density_chunked(_: object, pts: F) -> F:
            return np.asarray(fn(np.asarray(pts, dtype=np.float64).reshape(-1, 3)))

    o = origins.reshape(-1, 3)
    d = dirs.reshape(-1, 3)
    lo_t = max(t_range[0], 0.0)
    k0 = int(np.ceil(lo_t / dt))
    k1 = int(np.ceil(t_range[1] / dt))
    ts = np.arange(k0, k1) * dt
    out = np.full(len(o), np.inf)
    amb = np.zeros(len(o), dtype=bool)
    for r in range(len(o)):
        pts = o[r] + ts[:, None] * d[r]
        v = density_chunked(mol, pts)
        above = v >= iso
        near = np.abs(v - iso) < 1e-4 * iso
        change = np.nonzero(above != above[0])[0]
        if len(change) == 0:
            amb[r] = bool(near.any())
            continue
        j = change[0]
        a, b = ts[j] - dt, ts[j]
        inside = above[0]
        # the cutoff makes S jump where an atom enters reach, so a bracket can hold several
        # crossings; which one a refinement lands on is then a matter of method
        fine = density_chunked(mol, o[r] + np.linspace(a, b, 257)[:, None] * d[r]) >= iso
        amb[r] = bool(near[: j + 1].any()) or int(np.count_nonzero(fine[1:] != fine[:-1])) > 1
        for _ in range(60):
            m = 0.5 * (a + b)
            vm = density_chunked(mol, (o[r] + m * d[r])[None, :])[0]
            if (vm >= iso) == inside:
                a = m
            else:
                b = m
        out[r] = 0.5 * (a + b)
    return IsoResult(t=out, ambiguous=amb)


@dataclass(frozen=True)
class Light:
    ambient: float
    diffuse: float
    specular: float
    shininess: float
    head_weight: float
    key_weight: float
    key_dir: F
    background: F
    depth_cue: float
    fog_near: float
    fog_far: float


def facing_normal(grad: F, d: F) -> F:
    g = np.linalg.norm(grad, axis=-1, keepdims=True)
    n = np.where(g > 1e-30, -grad / np.where(g > 0, g, 1.0), -d)
    flip = (n * d).sum(axis=-1, keepdims=True) > 0
    return np.where(flip, -n, n)


def lit(light: Light, base: F, n: F, v: F, ao: float = 1.0) -> F:
    dh = np.maximum((n * v).sum(-1), 0.0)
    diff = light.head_weight * dh
    spec = light.head_weight * dh**light.shininess
    if light.key_weight > 0:
        dk = np.maximum(n @ light.key_dir, 0.0)
        hk = light.key_dir + v
        hk = hk / np.linalg.norm(hk, axis=-1, keepdims=True)
        sk = np.maximum((n * hk).sum(-1), 0.0) ** light.shininess
        diff = diff + np.where(dk > 0, light.key_weight * dk, 0.0)
        spec = spec + np.where(dk > 0, light.key_weight * sk, 0.0)
    c = base * (light.ambient * ao + light.diffuse * diff * (0.5 + 0.5 * ao))[..., None]
    out: F = np.clip(c + (light.specular * spec * ao)[..., None], 0.0, 1.0)
    return out


def fog(light: Light, t: F, c: F) -> F:
    if light.depth_cue <= 0:
        return c
    span = max(light.fog_far - light.fog_near, 1e-6)
    f = light.depth_cue * np.clip((t - light.fog_near) / span, 0.0, 1.0)
    out: F = c * (1.0 - f[..., None]) + light.background * f[..., None]
    return out


def pixel_jitter(x: int, y: int) -> float:
    """The documented per-pixel lattice offset (lowbias32 hash of the pixel)."""
    h = np.array([x * 1973 + y * 9277 + 26699], dtype=np.uint64).astype(np.uint32)
    h = (h ^ (h >> np.uint32(16))) * np.uint32(0x7FEB352D)
    h = (h ^ (h >> np.uint32(15))) * np.uint32(0x846CA68B)
    h = h ^ (h >> np.uint32(16))
    return float(h[0] >> np.uint32(8)) / 16777216.0


def composite(
    mol: Molecule,
    origin: F,
    direction: F,
    t_range: tuple[float, float],
    dt: float,
    iso: float,
    table: TransferTable,
    light: Light,
    shade: bool,
    jitter: float = 0.0,
    stop_alpha: float = 0.99,
    depth_alpha: float = 0.5,
) -> tuple[F, float]:
    """Front-to-back emission-absorption of one ray over `t_range`: (rgb over the background,
    depth). The ray's lattice samples (`(k + jitter) dt`) and its two ends divide it into
    segments, each the transfer function integrated along the density's linear ramp between
    its ends (float64, `segments.ramp_integral`); densities where the transfer function is
    clear count as its clear level. The first segment runs from the ray's start, the last to
    its end (placed midway along it); the others are one step long."""
    t0, t1 = max(t_range[0], 0.0), t_range[1]
    flat = -1.0 if table.clear_below < 0 else table.clear_below * iso
    if not np.isfinite(flat):  # nothing is visible
        return light.background.astype(np.float64), np.inf
    k0 = int(np.ceil(t0 / dt - jitter))
    ts = (np.arange(k0, int(np.ceil(t1 / dt - jitter)) + 1) + jitter) * dt
    at = np.concatenate([[t0], ts[ts < t1], [t1]])
    val, grad = density(mol, origin + at[:, None] * direction)
    val = np.maximum(val, flat)
    above = (val > flat)[:, None]
    acc = np.zeros(3)
    alpha = 0.0
    depth = np.inf
    last = len(at) - 2
    for i in range(last + 1):
        length = at[i + 1] - at[i]
        if length <= 0:
            continue
        seg = ramp_integral(table, val[i] / iso, val[i + 1] / iso, length, substeps=64)
        a_s = float(np.clip(seg[3], 0.0, 1.0))
        if a_s <= 0:
            continue
        col = seg[:3] / a_s
        t = at[i + 1] if i < last else 0.5 * (at[i] + at[i + 1])
        if shade:
            # the normal: the gradients of the segment's ends above the clear level
            n = facing_normal(grad[i] * above[i] + grad[i + 1] * above[i + 1], direction)
            col = lit(light, col[None, :], n[None, :], -direction[None, :])[0]
        col = fog(light, np.array([t]), col[None, :])[0]
        acc += col * (1.0 - alpha) * a_s
        alpha += (1.0 - alpha) * a_s
        if depth == np.inf and alpha >= depth_alpha:
            depth = float(t)
        if alpha >= stop_alpha:
            break
    return acc + light.background * (1.0 - alpha), depth
