"""The renderer's trial of part bounds against whole cells (`server/render/parttrial.py`)."""

from __future__ import annotations

import numpy as np
import pytest

from protocol import RenderParams
from server.render import renderer as renderer_module
from server.render.camera import fit_camera, orbit
from server.render.cells import WALKED
from server.render.parttrial import FRAMES, KEPT, PartTrial
from server.render.renderer import Renderer
from server.render.tuning import Tuning
from tests.render.molecules import Mol, villin


def run(trial: PartTrial, key: object, rule: str, ms: dict[str, float], frames: int) -> list[str]:
    """The choices of `frames` frames of set-up `key`, each timed as `ms` says for its choice."""
    seen = []
    for _ in range(frames):
        mode = trial.mode(key, rule)  # type: ignore[arg-type]
        seen.append(mode)
        trial.timed(ms[mode])
    return seen


def test_whole_cells_replace_the_rule_only_when_faster_by_the_margin() -> None:
    trial = PartTrial()
    frames = 2 * (FRAMES + 1)
    seen = run(trial, "a", "all", {"all": 1.0, "none": 0.9}, frames)
    assert seen == ["all", "none"] * (FRAMES + 1)  # by turns, one unmeasured of each
    assert trial.chosen("a") == "none"
    assert run(trial, "a", "all", {"all": 1.0, "none": 0.9}, 3) == ["none"] * 3
    # within the margin the rule stays; the rule's own "visible" is what is tried
    run(trial, "b", "visible", {"visible": 1.0, "none": 0.98}, frames)
    assert trial.chosen("b") == "visible"
    run(trial, "c", "all", {"all": 0.5, "none": 0.9}, frames)
    assert trial.chosen("c") == "all"


def test_whole_cells_must_win_by_their_least_time_too() -> None:
    """Other work on the device only adds time to a frame: turns of the rule slowed by it
    (median 3 ms, least 1 ms) do not make whole cells (2 ms each) the faster."""
    trial = PartTrial()
    times = {"all": iter([9.0, 1.0, 3.0, 3.0, 3.0]), "none": iter([9.0] + [2.0] * FRAMES)}
    for _ in range(2 * (FRAMES + 1)):
        mode = trial.mode("a", "all")
        trial.timed(next(times[mode]))
    assert trial.chosen("a") == "all"


def test_the_first_frame_of_each_is_not_counted() -> None:
    trial = PartTrial()
    times = iter([50.0, 0.5] + [1.0, 0.99] * FRAMES)  # "none"'s first frame built its kernels
    for _ in range(2 * (FRAMES + 1)):
        trial.mode("a", "all")
        trial.timed(next(times))
    assert trial.chosen("a") == "all"


def test_a_new_rule_a_stale_choice_and_too_many_set_ups_start_again() -> None:
    trial = PartTrial(expires=30)
    faster = {"all": 1.0, "none": 0.5, "visible": 1.0}
    run(trial, "a", "all", faster, 2 * (FRAMES + 1))
    assert trial.chosen("a") == "none"
    assert trial.mode("a", "visible") == "visible"  # the rule changed: tried again
    trial.timed(1.0)
    assert trial.chosen("a") is None
    run(trial, "a", "visible", faster, 2 * FRAMES + 1)
    assert trial.chosen("a") == "none"
    run(trial, "a", "visible", faster, 30)  # kept while fresh ...
    assert trial.mode("a", "visible") == "visible"  # ... then tried again
    assert trial.mode("z", "none") == "none" and trial.chosen("z") is None  # nothing to try
    for key in range(KEPT + 1):
        run(trial, key, "all", faster, 2 * (FRAMES + 1))
    assert trial.chosen(0) is None and trial.chosen(KEPT) == "none"


def test_a_time_for_no_trial_frame_is_ignored() -> None:
    trial = PartTrial()
    trial.timed(1.0)
    run(trial, "a", "all", {"all": 1.0, "none": 2.0}, 2 * (FRAMES + 1))
    trial.timed(0.0)  # a frame after the choice: no trial frame pending
    assert trial.chosen("a") == "all"


def on_trial(mol: Mol) -> Renderer:
    r = Renderer("cpu", tuning=Tuning(part_trial=True))
    r.set_topology(mol.topology)
    return r


def walked(r: Renderer) -> int:
    """Cells of the last grid that walked for their part bounds."""
    return int(np.count_nonzero(r._grid.parts.numpy() & WALKED))


@pytest.mark.parametrize(
    "params",
    [RenderParams(), RenderParams(mode="volume"), RenderParams(scale_space="geodesic")],
    ids=["iso", "volume", "geodesic"],
)
def test_a_renderer_on_trial_draws_what_whole_cells_draw(params: RenderParams) -> None:
    """On the CPU device the trial is off unless asked for. Asked for, the frames of a moving
    molecule go by turns with every open cell's part bounds and with whole cells, then keep
    one; every frame's image is that of whole cells, bit for bit."""
    mol = villin()
    cam = orbit(fit_camera(mol.positions, 48, 36), 30.0, 20.0)
    assert Renderer("cpu")._part_trial is None
    assert Renderer("cpu", tuning=Tuning(part_trial=True, part_bounds="all"))._part_trial is None
    r = on_trial(mol)
    ref = Renderer("cpu", tuning=Tuning(part_bounds="none"))
    ref.set_topology(mol.topology)
    rng = np.random.default_rng(3)
    parts = []
    for _ in range(2 * (FRAMES + 1) + 2):
        pos = mol.positions + rng.normal(0.0, 0.05, mol.positions.shape).astype(np.float32)
        for renderer in (r, ref):
            renderer.set_positions(pos)
            renderer.render(params, cam, 48, 36)
        parts.append(r.last_parts)
        assert (walked(r) > 0) == (parts[-1] == "all"), (parts[-1], walked(r))
        np.testing.assert_array_equal(r.read_rgba(), ref.read_rgba())
        np.testing.assert_array_equal(r.read_depth(), ref.read_depth())
    assert parts[: 2 * (FRAMES + 1)] == ["all", "none"] * (FRAMES + 1)
    assert parts[-1] == parts[-2] and parts[-1] in ("all", "none")
    assert np.count_nonzero(r.read_rgba()[..., 3]) > 100


def test_large_molecules_take_the_rule_untried(monkeypatch: pytest.MonkeyPatch) -> None:
    """From `TRIAL_ATOMS` atoms whole cells have never won: no turns there."""
    monkeypatch.setattr(renderer_module, "TRIAL_ATOMS", 100)
    mol = villin()
    cam = fit_camera(mol.positions, 40, 30)
    r = on_trial(mol)
    for k in range(4):
        r.set_positions(mol.positions + np.float32(0.01 * k))
        r.render(RenderParams(), cam, 40, 30)
        assert r.last_parts == "all" and walked(r) > 0


def test_still_positions_keep_their_grid_and_take_no_turn() -> None:
    """A turn on positions whose grid holds would rebuild it only to time a build the frames
    after it do not pay (a paused molecule, a turning camera): such frames keep the grid."""
    mol = villin()
    cam = fit_camera(mol.positions, 40, 30)
    r = on_trial(mol)
    r.set_positions(mol.positions)
    r.render(RenderParams(), cam, 40, 30)
    key = r._grid_key
    for yaw in range(10, 80, 10):
        r.render(RenderParams(), orbit(cam, float(yaw), 0.0), 40, 30)
        assert r._grid_key == key and r.last_parts == "all"
    assert r._part_trial is not None and r._part_trial._pending is None  # no turn taken
    r.set_positions(mol.positions + np.float32(0.01))  # moving again: the next turn
    r.render(RenderParams(), cam, 40, 30)
    assert r.last_parts == "none"


def test_a_build_that_fails_part_way_leaves_no_grid_to_reuse(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The grid's key was kept while another set-up's build failed half done, so the next
    frame of the first set-up drew from the broken grid."""
    mol = villin()
    cam = fit_camera(mol.positions, 40, 30)
    wide = RenderParams(sigma_A=2.5)
    r = Renderer("cpu")
    r.set_topology(mol.topology)
    r.set_positions(mol.positions)
    r.render(RenderParams(), cam, 40, 30)
    build = r._build_grid

    def fails(*args: object, **kw: object) -> None:
        build(*args, **kw)  # type: ignore[arg-type]
        raise RuntimeError("interrupted")

    monkeypatch.setattr(r, "_build_grid", fails)
    with pytest.raises(RuntimeError, match="interrupted"):
        r.render(wide, cam, 40, 30)
    monkeypatch.undo()
    r.render(RenderParams(), cam, 40, 30)
    fresh = Renderer("cpu")
    fresh.set_topology(mol.topology)
    fresh.set_positions(mol.positions)
    fresh.render(RenderParams(), cam, 40, 30)
    np.testing.assert_array_equal(r.read_rgba(), fresh.read_rgba())
