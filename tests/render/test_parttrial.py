"""The renderer's trial of part bounds against whole cells (`server/render/parttrial.py`)."""

from __future__ import annotations

import numpy as np

from protocol import RenderParams
from server.render.camera import fit_camera, orbit
from server.render.cells import WALKED
from server.render.parttrial import FRAMES, KEPT, PartTrial
from server.render.renderer import Renderer
from server.render.tuning import Tuning
from tests.render.molecules import villin


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


def test_a_renderer_on_trial_draws_the_same_image_with_either_choice() -> None:
    """On the CPU device the trial is off unless asked for; asked for, a renderer's frames go by
    turns with every open cell's part bounds and with whole cells, the same image each time,
    and then keep one."""
    mol = villin()
    cam = orbit(fit_camera(mol.positions, 48, 36), 30.0, 20.0)
    assert Renderer("cpu")._part_trial is None
    assert Renderer("cpu", tuning=Tuning(part_trial=True, part_bounds="all"))._part_trial is None
    r = Renderer("cpu", tuning=Tuning(part_trial=True))
    r.set_topology(mol.topology)
    r.set_positions(mol.positions)
    images, parts = [], []
    for _ in range(2 * (FRAMES + 1) + 2):
        r.render(RenderParams(), cam, 48, 36)
        assert r._frame_parts is not None
        parts.append(r._frame_parts[2])
        images.append(r.read_rgba())
        walked = int(np.count_nonzero(r._grid.parts.numpy() & WALKED))
        assert (walked > 0) == (parts[-1] == "all"), (parts[-1], walked)  # the choice holds
    assert parts[: 2 * (FRAMES + 1)] == ["all", "none"] * (FRAMES + 1)
    assert parts[-1] == parts[-2] and parts[-1] in ("all", "none")
    assert all(np.array_equal(images[0], image) for image in images[1:])
    assert np.count_nonzero(images[0][..., 3]) > 100
