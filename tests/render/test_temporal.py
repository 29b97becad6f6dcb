"""Temporal scale (server/render/temporal.py): the device filter against its float64 reference,
and the thesis's chapter 3-4 claim in time: the arclength warp keeps an event sharp while it
smooths thermal jitter about as well as the classical filter."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from server.render.temporal import TemporalSmoother, smooth_reference

JITTER_A = 0.3
JUMP_A = 5.0


def smoother_with(device: str, frames: np.ndarray, window: int) -> TemporalSmoother:
    s = TemporalSmoother(device, frames.shape[1], window)
    for f in frames:
        s.push(f)
    return s


@pytest.mark.parametrize("kernel", ["causal", "centred"])
@pytest.mark.parametrize("strength", [0.0, 1.0, 4.0])
def test_the_device_filter_equals_the_reference(device: str, kernel: str, strength: float) -> None:
    rng = np.random.default_rng(3)
    frames = (rng.normal(size=(20, 64, 3)) * 0.4 + rng.normal(size=(1, 64, 3)) * 10).astype(
        np.float32
    )
    s = smoother_with(device, frames, 12)  # the ring wrapped: it holds the last 12
    out = wp.zeros(64, dtype=wp.vec3, device=device)
    target = s.smooth(out, 2.5, strength, kernel, lag=5)
    ref, rate = smooth_reference(frames[-12:], 2.5, strength, target, kernel == "causal")
    assert target == (11 if kernel == "causal" else 6)
    np.testing.assert_allclose(out.numpy(), ref, atol=2e-5)
    np.testing.assert_allclose(s.rate.numpy(), rate, rtol=1e-5)


def test_strength_zero_is_the_classical_filter_and_one_frame_is_no_smoothing(device: str) -> None:
    rng = np.random.default_rng(4)
    frames = rng.normal(size=(9, 10, 3)).astype(np.float32)
    out = wp.zeros(10, dtype=wp.vec3, device=device)
    smoother_with(device, frames, 9).smooth(out, 2.0, 0.0, "centred", lag=4)
    d = np.arange(9) - 4.0
    w = np.exp(-(d**2) / 8.0)
    np.testing.assert_allclose(out.numpy(), np.tensordot(w / w.sum(), frames, 1), atol=1e-5)
    smoother_with(device, frames[:1], 1).smooth(out, 2.0, 1.0, "causal", lag=0)
    np.testing.assert_array_equal(out.numpy(), frames[0])


def test_a_causal_frame_never_changes_when_later_frames_arrive(device: str) -> None:
    rng = np.random.default_rng(5)
    frames = rng.normal(size=(30, 16, 3)).astype(np.float32)
    shown = []
    s = TemporalSmoother(device, 16, 64)
    out = wp.zeros(16, dtype=wp.vec3, device=device)
    for f in frames:
        s.push(f)
        s.smooth(out, 3.0, 1.0, "causal", lag=0)
        shown.append(out.numpy().copy())
    # recomputed with every frame present: each causal output is the same as when it was shown
    for t in range(len(frames)):
        again, _ = smooth_reference(frames[: t + 1], 3.0, 1.0, t, causal=True)
        np.testing.assert_allclose(shown[t], again, atol=2e-5)


def jump_trajectory(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """240 frames of one atom: at rest with thermal jitter, one 5 A jump at frame 120."""
    true = np.zeros((240, 1, 3))
    true[120:, 0, 0] = JUMP_A
    noisy = true + np.random.default_rng(seed).normal(scale=JITTER_A, size=true.shape)
    return true, noisy


def offline(
    noisy: np.ndarray, strength: float, tau: float, warp_from: np.ndarray | None = None
) -> np.ndarray:
    """The centred filter at every frame over a 33-frame window (what a replay shows)."""
    out = np.zeros((len(noisy), 3))
    for t in range(len(noisy)):
        lo, hi = max(0, t - 16), min(len(noisy), t + 17)
        if warp_from is None:
            out[t] = smooth_reference(noisy[lo:hi], tau, strength, t - lo, False)[0][0]
        else:  # the warp of the noise-free path, applied to the noisy one
            steps = np.linalg.norm(np.diff(warp_from[lo:hi], axis=0), axis=2) * strength
            g = np.concatenate([[0.0], np.cumsum(np.sqrt(1 + steps[:, 0] ** 2))])
            w = np.exp(-((g - g[t - lo]) ** 2) / (2 * tau * tau))
            out[t] = (w[:, None] * noisy[lo:hi, 0]).sum(0) / w.sum()
    return out


def width_10_90(x: np.ndarray) -> int:
    return int(np.argmax(x[:, 0] > 0.9 * JUMP_A) - np.argmax(x[:, 0] > 0.1 * JUMP_A))


def plateau_rms(x: np.ndarray, true: np.ndarray) -> float:
    rows = np.r_[20:100, 140:220]
    return float(np.sqrt(((x[rows] - true[rows, 0]) ** 2).sum(1).mean()))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_warped_filter_keeps_an_event_sharp_and_smooths_the_jitter(seed: int) -> None:
    tau, strength = 4.0, 1.0  # one angstrom of motion counts as one frame
    true, noisy = jump_trajectory(seed)
    classical = offline(noisy, 0.0, tau)
    warped = offline(noisy, strength, tau)
    ideal = offline(noisy, strength, tau, warp_from=true)
    assert width_10_90(warped) <= width_10_90(classical) / 2
    assert plateau_rms(warped, true) <= 1.25 * plateau_rms(classical, true)
    # table 4.3 in time: the warp of the true path smooths the plateaus as the classical filter
    # does (there the warp is the identity) and keeps the jump as sharp; the warp of the noisy
    # path pays for the noise it sees with a little plateau error
    assert plateau_rms(ideal, true) == pytest.approx(plateau_rms(classical, true), rel=1e-9)
    assert plateau_rms(ideal, true) < plateau_rms(warped, true)
    assert width_10_90(ideal) <= width_10_90(classical) / 2


def test_the_window_is_bounded() -> None:
    with pytest.raises(ValueError, match="time_window"):
        TemporalSmoother("cpu", 4, 65)


# ---------------------------------------------------------------------------- in the renderer


def _villin_frames(n: int, jitter: float, seed: int = 0) -> tuple[object, np.ndarray]:
    from tests.render.molecules import villin

    mol = villin()
    rng = np.random.default_rng(seed)
    frames = mol.positions[None] + rng.normal(scale=jitter, size=(n, *mol.positions.shape))
    return mol.topology, frames.astype(np.float32)


def _render(r: object, params: object) -> np.ndarray:
    from server.render.camera import fit_camera

    cam = fit_camera(r.host_positions(), 96, 72)  # type: ignore[attr-defined]
    r.render(params, cam, 96, 72)  # type: ignore[attr-defined]
    return r.read_rgba().astype(np.int32)  # type: ignore[attr-defined]


def test_the_renderer_draws_the_smoothed_frame_and_the_raw_one_when_turned_off(
    device: str,
) -> None:
    from protocol import RenderParams
    from server.render import Renderer

    topo, frames = _villin_frames(8, jitter=0.6)
    r = Renderer(device)
    r.set_topology(topo)
    history = []
    for i, f in enumerate(frames):
        r.set_positions(f)
        history.append((i + 1, f))
    raw = RenderParams()
    smooth = RenderParams(time_smoothing="warped", tau_frames=3.0, time_window=8)
    r.set_history(history, 0, smooth)
    r.render(smooth, _camera_for(frames[-1]), 96, 72)
    smoothed = r.read_rgba().astype(np.int32)
    r.set_history(history, 0, raw)
    r.render(raw, _camera_for(frames[-1]), 96, 72)
    again_raw = r.read_rgba().astype(np.int32)
    fresh = Renderer(device)
    fresh.set_topology(topo)
    fresh.set_positions(frames[-1])
    fresh.render(raw, _camera_for(frames[-1]), 96, 72)
    assert np.array_equal(again_raw, fresh.read_rgba().astype(np.int32))  # the newest, exactly
    assert np.abs(smoothed - again_raw).mean() > 1.0  # the jitter averaged away shows
    # the smoothed positions are the filter's output
    expected, _ = smooth_reference(frames, 3.0, 1.0, 7, True)
    positions = r._pos.numpy()[: topo.n_atoms].copy()
    r.set_history(history, 0, smooth)
    r.render(smooth, _camera_for(frames[-1]), 96, 72)
    np.testing.assert_allclose(r._pos.numpy()[: topo.n_atoms], expected, atol=2e-4)
    assert not np.allclose(positions, expected, atol=1e-3)  # off: it was the raw frame


def _camera_for(positions: np.ndarray) -> object:
    from server.render.camera import fit_camera

    return fit_camera(positions, 96, 72)


def test_motion_colours_follow_the_warp_rate(device: str) -> None:
    from protocol import RenderParams
    from server.render import Renderer
    from server.render.colors import unpack_rgba

    topo, frames = _villin_frames(6, jitter=0.0)
    frames[:, 0] += np.arange(6)[:, None] * np.float32(2.0)  # atom 0 moves 2 A a frame
    r = Renderer(device)
    r.set_topology(topo)
    r.set_positions(frames[-1])
    params = RenderParams(color_by="motion", time_warp_per_A=1.0)
    r.set_history([(i + 1, f) for i, f in enumerate(frames)], 0, params)
    r.render(params, _camera_for(frames[-1]), 64, 48)
    rgb = unpack_rgba(r._colors.numpy()[: topo.n_atoms])
    assert rgb[0, 0] > 0.6 and rgb[0, 2] < 0.2  # gamma' = sqrt(5): red
    assert rgb[1, 2] > 0.7 and rgb[1, 0] < 0.3  # at rest: blue
    np.testing.assert_array_equal(r._pos.numpy()[: topo.n_atoms], frames[-1])


def test_rigid_fit_keeps_a_tumbling_molecule_sharp(device: str) -> None:
    """A rigid molecule turning 6 degrees a frame: with the fit, the smoothed frame is the
    newest frame itself; without it, the average of turned copies shrinks the molecule."""
    from protocol import RenderParams
    from server.render import Renderer

    topo, base = _villin_frames(1, jitter=0.0)
    centre = base[0].mean(0)
    frames = []
    for k in range(10):
        a = np.radians(6.0 * k)
        rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
        frames.append(((base[0] - centre) @ rot.T + centre + k * 0.5).astype(np.float32))
    history = [(i + 1, f) for i, f in enumerate(frames)]
    results = {}
    for fit in (False, True):
        r = Renderer(device)
        r.set_topology(topo)
        r.set_positions(frames[-1])
        params = RenderParams(time_smoothing="classical", tau_frames=3.0, time_window=10,
                              rigid_fit=fit)  # fmt: skip
        r.set_history(history, 0, params)
        r.render(params, _camera_for(frames[-1]), 48, 36)
        results[fit] = r._pos.numpy()[: topo.n_atoms].copy()
    assert np.abs(results[True] - frames[-1]).max() < 1e-3
    assert np.abs(results[False] - frames[-1]).max() > 1.0


def test_smoothing_a_real_trajectory_keeps_its_bonds(device: str) -> None:
    """adk (PSF/DCD, 3341 atoms; a coarse transition path): bond lengths of the smoothed
    structure (warped, tau 2 frames, centred over 9) stay within 0.05 A of the raw frame's on
    average, 0.25 A for 99 % of bonds and 1 A for all (averaging positions shortens bonds that
    turn, most of all those to hydrogens)."""
    pytest.importorskip("MDAnalysisTests")
    from MDAnalysisTests.datafiles import DCD, PSF

    from structures.reader import load

    s = load(PSF, [DCD])
    frames = np.stack([s.positions(i) for i in range(20, 29)]).astype(np.float32)
    bonds = s.topology.bonds.to_numpy().reshape(-1, 2)
    sm = smoother_with(device, frames, 9)
    out = wp.zeros(frames.shape[1], dtype=wp.vec3, device=device)
    sm.smooth(out, 2.0, 1.0, "centred", lag=4)
    x = out.numpy()

    def lengths(p: np.ndarray) -> np.ndarray:
        return np.linalg.norm(p[bonds[:, 0]] - p[bonds[:, 1]], axis=1)

    drift = np.abs(lengths(x) - lengths(frames[4]))
    p99 = float(np.percentile(drift, 99))
    assert drift.mean() < 0.05 and p99 < 0.25 and drift.max() < 1.0, (drift.mean(), p99)


@pytest.mark.gpu
def test_the_gpu_filter_equals_the_cpu_filter() -> None:
    from server.render import device as render_device

    if render_device.cuda_count() == 0:
        pytest.skip("no CUDA device")
    rng = np.random.default_rng(9)
    frames = (rng.normal(size=(40, 5000, 3)) * 0.5 + rng.normal(size=(1, 5000, 3)) * 20).astype(
        np.float32
    )
    got = {}
    for device in ("cpu", "cuda:0"):
        s = smoother_with(device, frames, 32)
        out = wp.zeros(5000, dtype=wp.vec3, device=device)
        s.smooth(out, 4.0, 1.0, "centred", lag=15)
        got[device] = out.numpy()
    # float32 round-off: within 1e-5 A plus a few ulp of coordinates up to ~80 A
    np.testing.assert_allclose(got["cuda:0"], got["cpu"], atol=1e-5, rtol=1e-6)
