"""A frame's positions sent to sort-last's parts by the devices themselves.

Sort-last (`sortlast.py`) gives each device the atoms of its slab and halo. Gathering them on
the host reads the whole frame there once per part (230 ms at 100M atoms). Here each device
uploads one contiguous 1/N of the frame (by atom index) and picks from it, with a kernel,
the atoms each part holds; the picks for the other parts go to their devices device to
device (peer copies where the devices have peer access). The same pass over a device's share
measures the frame's box, its largest move along the split's axis since the split, and
whether any coordinate is not finite: the checks the host made before.

A part's atoms are kept in ascending whole-system order (the order its topology and the
blend's id map use): the atoms of share 0 first, then of share 1, and so on, which is that
order because the shares are contiguous and ascending.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, no_type_check

import numpy as np
import numpy.typing as npt
import warp

from server.render.multi import enable_peer_access

wp: Any = warp  # warp's host API is unannotated

STAT_THREADS = 1 << 15
"""Threads that measure a share (each a strided run of atoms, then one atomic per value)."""
STATS = 8
"""Per share: largest move along the axis, the box's low and high corners, bad coordinates."""


@wp.kernel(enable_backward=False)
@no_type_check
def share_stats_kernel(
    share: wp.array(dtype=wp.vec3),
    reference: wp.array(dtype=float),
    n: int,
    axis: int,
    stats: wp.array(dtype=float),
):
    """The largest |x[axis] - reference| of the share, its box, and its count of atoms with a
    coordinate that is not finite (stats[7])."""
    t = wp.tid()
    moved = float(0.0)
    lo = wp.vec3(wp.inf, wp.inf, wp.inf)
    hi = wp.vec3(-wp.inf, -wp.inf, -wp.inf)
    bad = float(0.0)
    i = t
    while i < n:
        p = share[i]
        if wp.isfinite(p[0]) and wp.isfinite(p[1]) and wp.isfinite(p[2]):
            moved = wp.max(moved, wp.abs(p[axis] - reference[i]))
            lo = wp.min(lo, p)
            hi = wp.max(hi, p)
        else:
            bad += 1.0
        i += STAT_THREADS
    wp.atomic_max(stats, 0, moved)
    for c in range(3):
        wp.atomic_min(stats, 1 + c, lo[c])
        wp.atomic_max(stats, 4 + c, hi[c])
    if bad > 0.0:
        wp.atomic_add(stats, 7, bad)


@wp.kernel(enable_backward=False)
@no_type_check
def pick_kernel(
    share: wp.array(dtype=wp.vec3),
    picks: wp.array(dtype=wp.int32),
    out: wp.array(dtype=wp.vec3),
    offset: int,
):
    """out[offset + i] = share[picks[i]]: a part's atoms out of one device's share."""
    i = wp.tid()
    out[offset + i] = share[picks[i]]


@dataclass
class FrameStats:
    """What the devices measured of one frame."""

    moved: float
    """The largest move of an atom along the split's axis since the split (A)."""
    lo: npt.NDArray[np.float64]
    hi: npt.NDArray[np.float64]
    bad: int
    """Atoms with a coordinate that is not finite."""


class Scatter:
    """For one split: the shares each device uploads and the picks that make every part."""

    peer = False
    """Every pair of the devices copies device to device (where they are distinct CUDA
    devices)."""

    def __init__(
        self,
        devices: Sequence[str],
        members: Sequence[npt.NDArray[np.int32]],
        axis: int,
        reference: npt.NDArray[np.float32],
    ) -> None:
        n = len(reference)
        parts = len(devices)
        self.devices = list(devices)
        if len(set(devices)) > 1 and all(wp.get_device(d).is_cuda for d in devices):
            # picks go straight over NVLink or PCIe where they can (else through the host)
            self.peer = enable_peer_access(devices)
        self.axis = axis
        bounds = [n * j // parts for j in range(parts + 1)]
        self.shares = [(bounds[j], bounds[j + 1]) for j in range(parts)]
        self.n = n
        self._share = [
            wp.empty(max(b - a, 1), dtype=wp.vec3, device=d)
            for d, (a, b) in zip(devices, self.shares, strict=True)
        ]
        self._reference = [
            wp.array(np.ascontiguousarray(reference[a:b]), dtype=float, device=d)
            for d, (a, b) in zip(devices, self.shares, strict=True)
        ]
        self._stats = [wp.empty(STATS, dtype=float, device=d) for d in devices]
        self.inbox = [
            wp.empty(max(len(m), 1), dtype=wp.vec3, device=d)
            for d, m in zip(devices, members, strict=True)
        ]
        """Each part's positions, on its device, once `send` has run."""
        # picks[j][k]: the atoms of part k in share j (indices within the share), the offset
        # they start at in part k, and (k != j) a buffer on device j they are picked into
        self._picks: list[list[tuple[Any, int, Any]]] = []
        for j, (dev, (a, b)) in enumerate(zip(devices, self.shares, strict=True)):
            row = []
            for k, m in enumerate(members):
                lo, hi = np.searchsorted(m, [a, b])
                local = (m[lo:hi] - a).astype(np.int32)
                picks = wp.array(local, dtype=wp.int32, device=dev) if len(local) else None
                staging = (
                    wp.empty(len(local), dtype=wp.vec3, device=dev)
                    if k != j and len(local) and devices[k] != dev
                    else None
                )
                row.append((picks, int(lo), staging))
            self._picks.append(row)

    def device_bytes(self) -> list[int]:
        """What the shares, picks and inboxes hold on each device, beside its renderer."""
        out = []
        for j, _dev in enumerate(self.devices):
            held = self._share[j].capacity + self._reference[j].capacity + self.inbox[j].capacity
            for picks, _off, staging in self._picks[j]:
                held += 0 if picks is None else picks.capacity
                held += 0 if staging is None else staging.capacity
            out.append(int(held))
        return out

    def send(self, positions: npt.NDArray[np.float32]) -> FrameStats:
        """Upload each device's share of `positions` (n, 3) float32 (page-locked memory
        uploads asynchronously), measure it and pick every part's atoms out of it; returns
        when every part's inbox holds its atoms."""
        lows = np.array([np.inf, np.inf, np.inf, -np.inf, -np.inf, -np.inf], dtype=np.float32)
        start = np.concatenate([[0.0], lows, [0.0]]).astype(np.float32)
        for j, dev in enumerate(self.devices):
            a, b = self.shares[j]
            self._stats[j].assign(start)
            if b <= a:
                continue
            host = wp.array(positions[a:b], dtype=wp.vec3, device="cpu", copy=False)
            wp.copy(self._share[j], host, count=b - a)
            args = (self._share[j], self._reference[j], b - a, self.axis, self._stats[j])
            wp.launch(share_stats_kernel, STAT_THREADS, args, device=dev)
            for k, (picks, offset, staging) in enumerate(self._picks[j]):
                if picks is None:
                    continue
                out, at = (staging, 0) if staging is not None else (self.inbox[k], offset)
                wp.launch(pick_kernel, len(picks), (self._share[j], picks, out, at), device=dev)
        for dev in dict.fromkeys(self.devices):
            wp.synchronize_device(dev)
        copied = False
        for row in self._picks:  # the picks for parts on other devices, device to device
            for k, (picks, offset, staging) in enumerate(row):
                if staging is not None:
                    wp.copy(self.inbox[k], staging, dest_offset=offset, count=len(picks))
                    copied = True
        if copied:
            for dev in dict.fromkeys(self.devices):
                wp.synchronize_device(dev)
        stats = np.stack([s.numpy().astype(np.float64) for s in self._stats])
        return FrameStats(
            moved=float(stats[:, 0].max()),
            lo=stats[:, 1:4].min(axis=0),
            hi=stats[:, 4:7].max(axis=0),
            bad=int(stats[:, 7].sum()),
        )
