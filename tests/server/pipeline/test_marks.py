"""Steering marks: which logged actions become marks, at which frame."""

from __future__ import annotations

from server.pipeline.marks import active_pulls, frame_at, pull_path, steering_marks

STEPS = [0, 10, 20, 30, 40, 50]


def test_a_mark_sits_at_the_first_frame_at_or_after_its_step() -> None:
    assert frame_at(STEPS, 0) == 0
    assert frame_at(STEPS, 11) == 2
    assert frame_at(STEPS, 30) == 3
    assert frame_at(STEPS, 999) == 5  # past the end: the last frame
    assert frame_at([], 5) == 0


def test_marks_use_the_applied_step_and_leave_out_refused_actions() -> None:
    log = [
        {"id": 1, "event": "sim_params", "sim_step": 5, "changes": {"temperature_K": 400.0}},
        {"id": 2, "event": "applied", "ref": 1, "step": 21, "kind": "sim_params"},
        {"id": 3, "event": "sim_params", "sim_step": 25, "changes": {"timestep_fs": 9.0}},
        {"id": 4, "event": "failed", "ref": 3, "kind": "sim_params"},
        {"id": 5, "event": "render_params", "sim_step": 33, "changes": {"sigma_A": 3.0}},
        {"id": 6, "event": "control", "sim_step": 41, "action": "pause", "n_steps": 1},
        {"id": 7, "event": "sim_event", "sim_step": 44, "step": 47, "code": "guard",
         "message": "rolled back"},
    ]  # fmt: skip
    marks = steering_marks(log, STEPS)
    assert [(m["id"], m["kind"], m["step"], m["frame"]) for m in marks] == [
        (1, "sim_params", 21, 3),
        (5, "render", 33, 4),
        (6, "control", 41, 5),
        (7, "event", 47, 5),
    ]
    assert marks[0]["text"] == "temperature_K 400.0"
    assert marks[1]["changes"] == {"sigma_A": 3.0}  # re-applied while replaying
    assert marks[2]["text"] == "pause"


def test_a_pull_is_one_mark_where_it_starts_and_one_where_it_is_released() -> None:
    log = [
        {"id": 1, "event": "pull", "sim_step": 12, "atom": 7, "target": [1, 2, 3]},
        {"id": 2, "event": "pull", "sim_step": 14, "atom": 7, "target": [1, 2, 4]},
        {"id": 3, "event": "pull", "sim_step": 31, "atom": 7, "target": [1, 2, 5]},
        {"id": 4, "event": "pull", "sim_step": 38, "atom": 7, "release": True},
        {"id": 5, "event": "pull", "sim_step": 39, "atom": 9, "release": True},  # never pulled
    ]
    marks = steering_marks(log, STEPS)
    assert [(m["kind"], m["atom"], m["frame"]) for m in marks] == [
        ("pull", 7, 2),
        ("release", 7, 4),
    ]
    path = pull_path(log, STEPS)
    assert active_pulls(path, 1) == {}
    assert active_pulls(path, 2) == {7: [1, 2, 4]}  # the latest target at that frame
    assert active_pulls(path, 4) == {}  # released
