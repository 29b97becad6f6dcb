"""Pre-integrated transfer function: the colour and opacity of a whole ray segment.

Volume mode composites the segments between consecutive samples, not the samples: along a
segment the density is taken to run linearly from the value at its front sample to the value at
its back one, and the segment's colour and opacity are the emission-absorption integral of the
transfer function along that ramp (pre-integration, Engel, Kraus and Ertl 2001). A sample-by-
sample sum treats the density as constant over each step and misses what a transfer function
does between two samples (a thin shell the density passes through in one step); the integral
along the ramp does not, so a step twice as long is more accurate than the sum was.

`table[i, j]` is the segment from table entry i (front) to entry j (back), premultiplied colour
and opacity; the caster interpolates it bilinearly at fractional entries. The diagonal (a
constant density) is one sample of the sum it replaces: alpha' = 1 - (1 - alpha)^(L/ref).
"""

from typing import Any, no_type_check

import numpy as np
import numpy.typing as npt
import warp as wp

from server.render import device as _device  # noqa: F401  (initialises warp)
from server.render.transfer import REFERENCE_LENGTH, TransferTable

wp.set_module_options({"enable_backward": False})


ALPHA_MAX = 1.0 - 1.0e-7
"""An entry's alpha is taken as at most this: its extinction, -ln(1 - alpha), stays finite and
a segment through it as opaque as float32 tells."""
_ALPHA_MAX = wp.constant(ALPHA_MAX)  # type: ignore[no-untyped-call]
ENTRIES_PER_SUBSTEP = 2
"""The ramp through the table is integrated in midpoint substeps of at most this many table
intervals (the 1D table is linear within each interval). On warp's CPU device, where a table
is made again with every new sigma while a slider moves, it took 82 ms with one interval a
substep and a power per substep, and takes 27-31 ms with two and the entries' extinctions
computed once; it stays within 2e-4 of the float64 integral."""
_PER_SUBSTEP = wp.constant(ENTRIES_PER_SUBSTEP)  # type: ignore[no-untyped-call]


@wp.kernel
@no_type_check
def extinction_kernel(table: wp.array[wp.vec4], ext: wp.array[float]):
    """Each entry's extinction per reference length, -ln(1 - alpha)."""
    k = wp.tid()
    ext[k] = -wp.log(1.0 - wp.clamp(table[k][3], 0.0, _ALPHA_MAX))


@wp.kernel
@no_type_check
def segment_table_kernel(
    table: wp.array[wp.vec4],
    ext: wp.array[float],
    last: int,
    length_ref: float,
    out: wp.array2d[wp.vec4],
):
    """Entry (i, j): front to back along the ramp u = i -> j in midpoint substeps of at most
    ENTRIES_PER_SUBSTEP table intervals, at least one; colour and extinction linear between
    entries. A constant density (i = j) is one substep at the entry itself."""
    i, j = wp.tid()
    m = wp.abs(j - i) // _PER_SUBSTEP + 1
    inv_m = 1.0 / float(m)
    acc = wp.vec3(0.0, 0.0, 0.0)
    alpha = float(0.0)
    for q in range(m):
        u = float(i) + float(j - i) * (float(q) + 0.5) * inv_m
        i0 = wp.min(int(wp.floor(u)), last)
        i1 = wp.min(i0 + 1, last)
        fr = u - float(i0)
        k = ext[i0] * (1.0 - fr) + ext[i1] * fr
        if k > 0.0:
            e = table[i0] * (1.0 - fr) + table[i1] * fr
            a_s = 1.0 - wp.exp(-k * length_ref * inv_m)
            acc += wp.vec3(e[0], e[1], e[2]) * ((1.0 - alpha) * a_s)
            alpha += (1.0 - alpha) * a_s
    out[i, j] = wp.vec4(acc[0], acc[1], acc[2], alpha)


@wp.func
@no_type_check
def segment(seg: wp.array2d[wp.vec4], last: int, uf: float, ub: float) -> wp.vec4:
    """The segment from fractional entry uf (front) to ub (back), both in [0, last]."""
    i0 = wp.min(int(wp.floor(uf)), last)
    j0 = wp.min(int(wp.floor(ub)), last)
    i1 = wp.min(i0 + 1, last)
    j1 = wp.min(j0 + 1, last)
    fi = uf - float(i0)
    fj = ub - float(j0)
    front = seg[i0, j0] * (1.0 - fj) + seg[i0, j1] * fj
    back = seg[i1, j0] * (1.0 - fj) + seg[i1, j1] * fj
    return front * (1.0 - fi) + back * fi


@wp.func
@no_type_check
def part(e: wp.vec4, fraction: float) -> wp.vec4:
    """Segment e shortened to `fraction` of its length (exact for a constant density)."""
    out = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if e[3] > 0.0:
        a = 1.0 - wp.pow(wp.max(1.0 - e[3], 0.0), fraction)
        out = wp.vec4(e[0], e[1], e[2], e[3]) * (a / e[3])
    return out


@wp.func
@no_type_check
def ramp(seg: wp.array2d[wp.vec4], last: int, uf: float, ub: float) -> wp.vec4:
    """The segment from entry uf (front) to ub (back), both >= 0. Beyond the last entry the
    transfer function holds its last value: the part of the ramp past it is that constant
    medium, composited in front of or behind the part inside the table."""
    lim = float(last)
    out = wp.vec4(0.0, 0.0, 0.0, 0.0)
    if uf <= lim and ub <= lim:
        out = segment(seg, last, uf, ub)
    elif uf > lim and ub > lim:
        out = seg[last, last]
    else:
        inside = (lim - wp.min(uf, ub)) / wp.abs(ub - uf)
        near = part(segment(seg, last, wp.min(uf, lim), wp.min(ub, lim)), inside)
        top = part(seg[last, last], 1.0 - inside)
        front = near
        back = top
        if uf > lim:
            front = top
            back = near
        out = front + back * (1.0 - front[3])
    return out


def build(table: Any, length_A: float, out: Any) -> None:
    """Fill `out` (size x size vec4) with the segments of length `length_A` through the 1D
    `table` (size vec4, on the same device)."""
    size = table.shape[0]
    ext = wp.empty(size, dtype=float, device=out.device)
    wp.launch(extinction_kernel, size, (table, ext), device=out.device)
    wp.launch(
        segment_table_kernel,
        (size, size),
        (table, ext, size - 1, float(length_A) / REFERENCE_LENGTH, out),
        device=out.device,
    )


def ramp_integral(
    tf: TransferTable, x_front: float, x_back: float, length_A: float, substeps: int = 512
) -> npt.NDArray[np.float64]:
    """Reference (float64): premultiplied colour and opacity of a segment of `length_A` along
    which x (density / iso level) runs linearly from `x_front` to `x_back`, integrated with
    `substeps` midpoint steps of the transfer function itself."""
    xs = x_front + (x_back - x_front) * (np.arange(substeps) + 0.5) / substeps
    rgba = tf.lookup(xs)
    a = 1.0 - np.power(1.0 - np.clip(rgba[:, 3], 0.0, 1.0), length_A / substeps / REFERENCE_LENGTH)
    acc = np.zeros(3)
    alpha = 0.0
    for k in range(substeps):
        acc += rgba[k, :3] * (1.0 - alpha) * a[k]
        alpha += (1.0 - alpha) * a[k]
    return np.array([*acc, alpha])
