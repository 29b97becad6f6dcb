"""Temporal scale: every atom's path smoothed over the last frames, on the render device.

The thesis's warped filter (eq. 3.3) applied along time, per atom. Each atom's positions over a
window of W frames (a device ring buffer, `W * 12` bytes per atom) are its signal; the filter
is a normalised Gaussian of width `tau` frames in *warped* time, where the warp is the
arclength of the atom's own path, measured frame by frame:

    gamma(k) = sum_{j <= k} sqrt(1 + (lambda * |x_j - x_{j-1}|)^2)        (frames)

`lambda` (frames per angstrom, the warp strength) says how many frames one angstrom of motion
counts as: with `lambda = 0` the warp is the identity and the filter is the classical Gaussian
over frames; with `lambda > 0` a sudden move (an event: a flip, a jump) stretches warped time
where it happens, so frames on either side of it fall far apart and are not averaged together:
the event stays sharp while thermal jitter, small against `1 / lambda`, is smoothed as before.

The *target* frame is the one shown: the newest for the causal (one-sided) kernel, which never
changes once later frames arrive; a frame `lag` behind the newest for the centred kernel, which
uses frames on both sides and shows the run `lag` frames late. `warp rate` is the per-atom mean
of `gamma'` over the window (1 for an atom at rest), the colour scheme "motion".

The float64 reference `smooth_reference` is what the kernel must compute.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
import warp as wp

from protocol import RenderParams
from server.render.colors import MOTION_RAMP, MOTION_RANGE

TRUNCATE = 4.0
"""Frames farther than TRUNCATE * tau in warped time are left out (weight below 3.4e-4)."""
MAX_WINDOW = 64


@wp.kernel
def smooth_kernel(
    ring: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
    w: int,
    oldest: int,
    count: int,
    target: int,
    causal: int,
    strength: float,
    inv_two_tau2: float,
    cutoff: float,
    rate_strength: float,
    out: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
    rate: wp.array(dtype=float),  # type: ignore[valid-type]
) -> None:
    """One thread per atom: the warped Gaussian of its path at frame `target` (0 = oldest)."""
    i = wp.tid()
    n = out.shape[0]
    # the warped time of the target, walking the path once
    g = float(0.0)
    g_target = float(0.0)
    g_rate = float(0.0)
    prev = ring[(oldest % w) * n + i]
    for k in range(1, count):
        x = ring[((oldest + k) % w) * n + i]
        moved = wp.length(x - prev)
        step = moved * strength
        g = g + wp.sqrt(1.0 + step * step)
        step = moved * rate_strength
        g_rate = g_rate + wp.sqrt(1.0 + step * step)
        if k == target:
            g_target = g
        prev = x
    rate[i] = wp.where(count > 1, g_rate / float(wp.max(count - 1, 1)), 1.0)
    # the normalised Gaussian in warped time around the target
    last = count - 1
    if causal != 0:
        last = target
    acc = wp.vec3(0.0, 0.0, 0.0)
    wsum = float(0.0)
    g = float(0.0)
    prev = ring[(oldest % w) * n + i]
    for k in range(0, last + 1):
        x = ring[((oldest + k) % w) * n + i]
        if k > 0:
            step = wp.length(x - prev) * strength
            g = g + wp.sqrt(1.0 + step * step)
        prev = x
        d = g - g_target
        if wp.abs(d) <= cutoff:
            weight = wp.exp(-d * d * inv_two_tau2)
            acc = acc + weight * x
            wsum = wsum + weight
    out[i] = acc / wsum


def smooth_reference(
    frames: npt.ArrayLike, tau: float, strength: float, target: int, causal: bool
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
    """Float64 reference of `smooth_kernel`: frames (count, n, 3) oldest first -> smoothed
    positions (n, 3) at `target`, and the mean warp rate per atom."""
    x = np.asarray(frames, dtype=np.float64)
    count = x.shape[0]
    steps = np.linalg.norm(np.diff(x, axis=0), axis=2) * strength  # (count-1, n)
    gamma = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(np.sqrt(1 + steps**2), 0)])
    d = gamma - gamma[target]
    weights = np.exp(-(d**2) / (2 * tau * tau)) * (np.abs(d) <= TRUNCATE * tau)
    if causal:
        weights[target + 1 :] = 0.0
    out = (weights[:, :, None] * x).sum(0) / weights.sum(0)[:, None]
    rate = gamma[-1] / max(count - 1, 1) if count > 1 else np.ones(x.shape[1])
    return out, rate


class TemporalSmoother:
    """The ring buffer of one renderer's atoms and the filter over it."""

    def __init__(self, device: str, n_atoms: int, window: int) -> None:
        if not 1 <= window <= MAX_WINDOW:
            raise ValueError(f"time_window must be within 1..{MAX_WINDOW}, got {window}")
        self.device = device
        self.window = window
        self.n = n_atoms
        self.ring = wp.zeros(window * max(n_atoms, 1), dtype=wp.vec3, device=device)
        self.rate = wp.ones(max(n_atoms, 1), dtype=float, device=device)
        self.count = 0
        self.head = 0
        """Where the next frame goes."""

    @property
    def nbytes(self) -> int:
        return int(self.window * max(self.n, 1) * 12 + max(self.n, 1) * 4)

    def reset(self) -> None:
        self.count = 0
        self.head = 0

    def push(self, positions: Any) -> None:
        """Append one frame (a device vec3 array or host (n, 3) float32), dropping the oldest
        when full."""
        src = positions
        if not isinstance(src, wp.array):
            src = wp.array(np.ascontiguousarray(positions, dtype=np.float32), dtype=wp.vec3,
                           device="cpu")  # fmt: skip
        wp.copy(self.ring, src, dest_offset=self.head * max(self.n, 1), count=self.n)
        self.head = (self.head + 1) % self.window
        self.count = min(self.count + 1, self.window)

    def target(self, kernel: str, lag: int) -> int:
        """Index (0 = oldest) of the frame shown: the newest (causal) or `lag` frames before it
        (centred), within what the ring holds."""
        newest = self.count - 1
        return newest if kernel == "causal" else max(0, newest - lag)

    def smooth(
        self,
        out: Any,
        tau: float,
        strength: float,
        kernel: str,
        lag: int,
        rate_strength: float | None = None,
    ) -> int:
        """Write the smoothed frame into `out` (device vec3, n atoms) and each atom's mean warp
        rate (with `rate_strength`, default `strength`) into `rate`; returns the target."""
        if self.count == 0:
            raise ValueError("no frame to smooth")
        t = self.target(kernel, lag)
        oldest = (self.head - self.count) % self.window
        wp.launch(
            smooth_kernel,
            dim=self.n,
            inputs=[
                self.ring,
                self.window,
                oldest,
                self.count,
                t,
                1 if kernel == "causal" else 0,
                float(strength),
                float(0.5 / (tau * tau)),
                float(TRUNCATE * tau),
                float(strength if rate_strength is None else rate_strength),
            ],
            outputs=[out, self.rate],
            device=self.device,
        )
        return t


@wp.kernel
def rigid_kernel(
    pos: wp.array(dtype=wp.vec3),  # type: ignore[valid-type]
    rotation: wp.mat33,
    origin: wp.vec3,
    to: wp.vec3,
) -> None:
    """x <- rotation (x - origin) + to: the smoothed frame put back in its own pose."""
    i = wp.tid()
    pos[i] = rotation * (pos[i] - origin) + to


def kabsch(moving: npt.NDArray[Any], fixed: npt.NDArray[Any]) -> npt.NDArray[np.float64]:
    """The rotation R minimising |(moving - mean) R^T - (fixed - mean)| (no reflection)."""
    p = np.asarray(moving, dtype=np.float64)
    q = np.asarray(fixed, dtype=np.float64)
    h = (p - p.mean(0)).T @ (q - q.mean(0))
    u, _s, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    rotation: npt.NDArray[np.float64] = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return rotation


class RigidFit:
    """Frames fitted onto a reference (the first frame after a reset) on a subset of atoms;
    remembers each frame's pose so a smoothed frame can be put back where it was."""

    def __init__(self, mask: npt.NDArray[np.bool_], window: int) -> None:
        self.mask = mask if int(mask.sum()) >= 3 else np.ones_like(mask)
        self.reference: npt.NDArray[np.float64] | None = None
        self.poses: list[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]] = []
        self.window = window

    def align(self, positions: npt.NDArray[Any]) -> npt.NDArray[np.float32]:
        """`positions` in the reference's pose; its own pose is remembered (newest last)."""
        x = np.asarray(positions, dtype=np.float64)
        sub = x[self.mask]
        if self.reference is None:
            self.reference = sub.mean(0)
            self._fixed = sub - self.reference
        centre = sub.mean(0)
        rotation = kabsch(sub, self._fixed + self.reference)
        self.poses.append((rotation, centre))
        del self.poses[: -self.window]
        aligned: npt.NDArray[np.float32] = ((x - centre) @ rotation.T + self.reference).astype(
            np.float32
        )
        return aligned

    def restore(self, pos: Any, index_from_newest: int) -> None:
        """Put the smoothed frame (device, in the reference pose) back in the pose of the frame
        `index_from_newest` frames before the newest."""
        assert self.reference is not None
        rotation, centre = self.poses[-1 - index_from_newest]
        wp.launch(
            rigid_kernel,
            dim=pos.shape[0],
            inputs=[
                pos,
                wp.mat33(*rotation.T.ravel().tolist()),  # the inverse rotation
                wp.vec3(*self.reference.tolist()),
                wp.vec3(*centre.tolist()),
            ],
            device=pos.device,
        )


@wp.kernel
def motion_color_kernel(
    rate: wp.array(dtype=float),  # type: ignore[valid-type]
    low: float,
    high: float,
    lo: wp.vec3,
    mid: wp.vec3,
    hi: wp.vec3,
    colors: wp.array(dtype=wp.uint32),  # type: ignore[valid-type]
) -> None:
    """Warp rate -> the motion ramp (`colors.MOTION_RAMP` over `colors.MOTION_RANGE`), packed
    like `colors.pack_rgba`."""
    i = wp.tid()
    u = wp.clamp((rate[i] - low) / (high - low), 0.0, 1.0)
    c = wp.where(u < 0.5, lo + (mid - lo) * (2.0 * u), mid + (hi - mid) * (2.0 * u - 1.0))
    r = wp.uint32(wp.floor(c[0] * 255.0 + 0.5))
    g = wp.uint32(wp.floor(c[1] * 255.0 + 0.5))
    b = wp.uint32(wp.floor(c[2] * 255.0 + 0.5))
    colors[i] = r | (g << wp.uint32(8)) | (b << wp.uint32(16)) | (wp.uint32(255) << wp.uint32(24))  # type: ignore[operator]


class TemporalState:
    """A renderer's temporal scale: the ring of recent frames it was fed, the filter that
    writes the shown frame into the renderer's positions, and the motion colours."""

    def __init__(self, device: str, n_atoms: int, heavy: npt.NDArray[np.bool_]) -> None:
        self.device = device
        self.n = n_atoms
        self.heavy = heavy
        self.smoother: TemporalSmoother | None = None
        self.fit: RigidFit | None = None
        self.key: tuple[Any, ...] | None = None
        self.epoch: int | None = None
        self.last_id = -1
        self.version = 0
        """Counts frames pushed; the shown frame is recomputed when it or the filter changes."""
        self.live = True
        self.lag: int | None = None
        self.shown_key: tuple[Any, ...] | None = None
        self.colors_key: tuple[Any, ...] | None = None
        self.scratch: Any = None

    @property
    def nbytes(self) -> int:
        return self.smoother.nbytes if self.smoother is not None else 0

    def feed(
        self,
        frames: Any,
        epoch: int,
        params: RenderParams,
        live: bool,
        lag: int | None,
        uploaded: Any = None,
        device_copy: Any = None,
    ) -> None:
        """Take the frames (id, positions) not seen yet, oldest first; a new epoch (a seek, a
        new topology) or another window or fit empties the ring first. The frame that is
        `uploaded` (the same object) is copied from `device_copy` on the device instead of
        being sent again."""
        self.live, self.lag = live, lag
        key = (params.time_window, params.rigid_fit)
        if key != self.key or self.smoother is None:
            self.smoother = TemporalSmoother(self.device, self.n, params.time_window)
            self.key = key
            self.epoch = None
        if epoch != self.epoch:  # the ring starts again, keeping its memory
            self.smoother.reset()
            self.fit = RigidFit(self.heavy, params.time_window) if params.rigid_fit else None
            self.epoch = epoch
            self.last_id = -1
            self.shown_key = None
        for frame_id, positions in frames:
            if frame_id <= self.last_id:
                continue
            if self.fit is not None:
                self.smoother.push(self.fit.align(positions))
            elif positions is uploaded and device_copy is not None:
                self.smoother.push(device_copy)
            else:
                self.smoother.push(positions)
            self.last_id = frame_id
            self.version += 1

    def kernel(self, params: RenderParams) -> str:
        k = str(params.time_kernel)
        return ("causal" if self.live else "centred") if k == "auto" else k

    def apply(self, pos: Any, params: RenderParams) -> bool:
        """Write the shown frame into `pos` (the renderer's positions) when smoothing is on;
        True when `pos` changed. With smoothing off, only the warp rate is computed."""
        s = self.smoother
        if s is None or s.count == 0:
            return False
        kernel = self.kernel(params)
        lag = (params.time_window - 1) // 2 if self.lag is None else self.lag
        strength = params.time_warp_per_A if params.time_smoothing == "warped" else 0.0
        smoothing = params.time_smoothing != "off"
        rate = params.time_warp_per_A
        key = (self.version, smoothing, params.tau_frames, strength, kernel, lag, rate)
        if key == self.shown_key:
            return False
        self.shown_key = key
        if smoothing:
            out = pos
        else:
            if self.scratch is None:
                self.scratch = wp.zeros(max(self.n, 1), dtype=wp.vec3, device=self.device)
            out = self.scratch
        target = s.smooth(out, params.tau_frames, strength, kernel, lag, params.time_warp_per_A)
        if smoothing and self.fit is not None:
            self.fit.restore(pos, s.count - 1 - target)
        return smoothing

    def newest(self, pos: Any) -> None:
        """Put the newest raw frame back into `pos` (smoothing was turned off)."""
        s = self.smoother
        if s is None or s.count == 0:
            return
        if self.fit is not None:
            s.smooth(pos, 1e-3, 0.0, "causal", 0)  # the newest frame alone, then its pose
            self.fit.restore(pos, 0)
        else:
            newest = (s.head - 1) % s.window
            wp.copy(pos, s.ring, src_offset=newest * max(self.n, 1), count=self.n)

    def colors(self, out: Any) -> bool:
        """Motion colours into `out` when the warp rate changed; False with no history."""
        if self.smoother is None or self.smoother.count == 0:
            return False
        key = (self.version, self.shown_key)
        if key != self.colors_key:
            wp.launch(
                motion_color_kernel,
                dim=self.n,
                inputs=[
                    self.smoother.rate,
                    *MOTION_RANGE,
                    *(wp.vec3(*stop) for stop in MOTION_RAMP),
                ],
                outputs=[out],
                device=self.device,
            )
            self.colors_key = key
        return True
