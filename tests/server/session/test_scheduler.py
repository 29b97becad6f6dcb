"""The image scheduler's policy, with time passed in: who shares a render, when a view is due,
what an interactive view costs and when the still follows."""

from __future__ import annotations

from dataclasses import replace

import pytest

import protocol as p
from server.session.scheduler import FINAL, MAGNIFIED_JPEG_QUALITY, RenderScheduler
from server.settings import ServerSettings
from tests.server.session.fakes import client

SETTINGS = ServerSettings(
    token="t",
    default_size=(200, 100),
    interactive_idle_s=0.15,
    interactive_scale=0.5,
    viewer_views_per_pass=64,
)


def viewer(cid: str, camera: p.Camera | None = None, size: tuple[int, int] = (200, 100)):  # type: ignore[no-untyped-def]
    c = client(cid, "viewer")
    if camera is not None:
        c.view = p.View(camera=camera, width=size[0], height=size[1])
    return c


def test_viewers_with_the_same_view_share_one_render() -> None:
    s = RenderScheduler(SETTINGS)
    cam = p.Camera(distance=30.0)
    a, b, c = viewer("a", cam), viewer("b", cam), viewer("c", p.Camera(distance=60.0))
    plan = s.plan([a, b, c], now=10.0, version=1, default_camera=None)
    assert sorted(len(members) for _, members in plan.groups) == [1, 2]
    assert plan.come_back_in is None


def test_a_view_without_a_camera_shares_the_sessions_camera() -> None:
    s = RenderScheduler(SETTINGS)
    session_camera = p.Camera(distance=720.0)
    a = client("a", "viewer")
    a.view = p.View(width=200, height=100)  # a script that names only its canvas
    b = viewer("b", session_camera)
    ((key, members),) = s.plan([a, b], 10.0, 1, default_camera=session_camera).groups
    assert key.camera == session_camera and len(members) == 2  # one render for both
    assert s.view_of(a, session_camera)[0] == session_camera


def test_a_group_renders_a_version_once_unless_a_member_asks_again() -> None:
    s = RenderScheduler(SETTINGS)
    a = viewer("a")
    ((key, _),) = s.plan([a], 10.0, 1, None).groups
    s.rendered(key, 1)
    assert s.plan([a], 10.1, 1, None).groups == []
    assert len(s.plan([a], 10.2, 2, None).groups) == 1  # a new frame
    s.rendered(key, 2)
    a.needs_image = True  # e.g. a new view message
    assert len(s.plan([a], 10.3, 2, None).groups) == 1
    assert not a.needs_image
    s.forget(key)  # its image was lost (encode failed)
    assert len(s.plan([a], 10.4, 2, None).groups) == 1


def test_interaction_renders_small_and_fast_then_a_still_follows() -> None:
    s = RenderScheduler(SETTINGS)
    a = viewer("a")
    s.interacting(now=100.0)
    plan = s.plan([a], 100.05, 1, None)
    ((key, _),) = plan.groups
    assert key.interactive
    assert s.image_size(key, quality=1.0) == (100, 50)
    assert s.jpeg_quality(key, p.RenderParams()) == SETTINGS.interactive_jpeg_quality
    assert plan.come_back_in is not None and plan.come_back_in > SETTINGS.interactive_idle_s
    s.rendered(key, 1)
    later = s.plan([a], 100.05 + plan.come_back_in, 1, None)  # same version, now a still
    ((still_key, _),) = later.groups
    assert not still_key.interactive and later.come_back_in is None
    assert s.image_size(still_key, quality=1.0) == (200, 100)
    assert s.jpeg_quality(still_key, p.RenderParams(jpeg_quality=92)) == 92


def test_an_image_the_browser_scales_up_keeps_its_blocks_small() -> None:
    """A budget image on the CPU is drawn 2-5 times its size; at the parameters' quality 85
    (4:2:0) its chroma blocks showed as tiles of colour."""
    s = RenderScheduler(SETTINGS)
    key = s.plan([viewer("a", p.Camera(), (880, 449))], 1.0, 1, None).groups[0][0]
    params = p.RenderParams()
    assert s.jpeg_quality(key, params, (880, 449)) == params.jpeg_quality  # drawn as it is
    assert s.jpeg_quality(key, params, (500, 255)) == params.jpeg_quality  # 1.76x: as it is
    assert s.jpeg_quality(key, params, (198, 101)) == MAGNIFIED_JPEG_QUALITY >= 90  # 4:4:4
    assert s.jpeg_quality(key, p.RenderParams(jpeg_quality=97), (198, 101)) == 97


def test_one_client_interacting_leaves_the_others_at_full_quality() -> None:
    s = RenderScheduler(SETTINGS)
    a, b = viewer("a"), viewer("b")
    a.interacting_until = 50.0
    groups = s.plan([a, b], 49.9, 1, None).groups
    assert {(k.interactive, len(m)) for k, m in groups} == {(True, 1), (False, 1)}


def test_image_sizes_respect_quality_and_the_server_limits() -> None:
    small = replace(SETTINGS, limits=p.Limits(max_image_side=128, max_image_pixels=128 * 64))
    s = RenderScheduler(small)
    key = s.plan([viewer("a", p.Camera(), (400, 200))], 1.0, 1, None).groups[0][0]
    w, h = s.image_size(key, quality=1.0)
    assert w <= 128 and w * h <= 128 * 64 and abs(w / h - 2.0) < 0.05
    assert s.image_size(key, quality=0.1) == (40, 20)


def test_the_histogram_comes_with_stills_at_most_once_a_second() -> None:
    s = RenderScheduler(SETTINGS)
    a = viewer("a")
    ((key, _),) = s.plan([a], 5.0, 1, None).groups
    assert s.histogram_due(key, 5.0)
    assert not s.histogram_due(key, 5.5)
    assert s.histogram_due(key, 6.1)
    s.interacting(7.0)
    ((moving, _),) = s.plan([a], 7.01, 2, None).groups
    assert not s.histogram_due(moving, 8.5)


def test_a_final_image_is_shrunk_to_what_renders_within_its_budget() -> None:
    """A final image of the geodesic density at crease rounding 2 took 53 s on two CPU cores,
    and every change waited behind it; it now renders what fits in `final_budget_ms`."""
    settings = replace(SETTINGS, default_size=(800, 600), final_budget_ms=5000.0)
    s = RenderScheduler(settings)
    a = viewer("a", p.Camera(distance=30.0), (800, 600))
    ((key, _),) = s.plan([a], 10.0, 1, None).groups
    final = replace(key, refine=FINAL)
    s.note_render(key, 1, (400, 300), 30_000.0, now=10.0)  # 0.25 ms a pixel
    w, h = s.image_size(final, 1.0)
    assert 19_000 < w * h <= 20_000 and abs(w / h - 800 / 600) < 0.02
    assert s.note_render(final, 1, (w, h), 5000.0, now=20.0) is False  # no level after it
    off = RenderScheduler(replace(settings, final_budget_ms=0.0))
    off.note_render(key, 1, (400, 300), 30_000.0, now=10.0)
    assert off.image_size(final, 1.0) == (800, 600)  # the budget off: whatever it costs


def test_the_frame_budget_shrinks_images_on_a_slow_device_and_refines_them_when_still() -> None:
    settings = replace(
        SETTINGS,
        default_size=(800, 600),
        frame_budget_ms=80.0,
        refine_budget_ms=240.0,
        refine_after_s=0.3,
        final_after_s=1.5,
    )
    s = RenderScheduler(settings)
    a = viewer("a", p.Camera(distance=30.0), (800, 600))
    ((key, _),) = s.plan([a], 10.0, 1, None).groups
    assert s.image_size(key, 1.0) == (800, 600)  # nothing measured yet: the full size
    # 2 us a pixel (a CPU): 800x600 took 960 ms; 80 ms afford 40,000 pixels
    assert s.note_render(key, 1, (800, 600), 960.0, now=10.0) is False
    s.rendered(key, 1)
    ((key, _),) = s.plan([a], 10.1, 2, None).groups
    w, h = s.image_size(key, 1.0)
    assert 38_000 < w * h <= 40_000 and abs(w / h - 800 / 600) < 0.02
    assert s.note_render(key, 2, (w, h), 80.0, now=10.2) is True
    s.rendered(key, 2)
    plan = s.plan([a], 10.3, 2, None)  # unchanged, but not for long enough yet
    assert plan.groups == [] and plan.come_back_in is not None and plan.come_back_in < 0.25
    ((refine, _),) = s.plan([a], 10.55, 2, None).groups
    assert refine.refine
    rw, rh = s.image_size(refine, 1.0)
    assert 115_000 < rw * rh <= 120_000  # the refine budget: three times the pixels
    assert s.note_render(refine, 2, (rw, rh), 240.0, now=10.8) is True  # still not full size
    s.rendered(refine, 2)
    plan = s.plan([a], 11.5, 2, None)  # the final level waits for final_after_s
    assert plan.groups == [] and plan.come_back_in is not None
    ((final, _),) = s.plan([a], 12.4, 2, None).groups
    assert final.refine == 2 and s.image_size(final, 1.0) == (800, 600)  # within 5 s
    assert s.note_render(final, 2, (800, 600), 960.0, now=13.4) is False
    s.rendered(final, 2)
    assert s.plan([a], 20.0, 2, None).groups == []  # at full size, then quiet
    # a new frame renders within the budget again
    ((key, _),) = s.plan([a], 20.1, 3, None).groups
    assert not key.refine and s.image_size(key, 1.0)[0] < 800


def test_on_a_fast_device_the_budget_shrinks_nothing() -> None:
    s = RenderScheduler(replace(SETTINGS, frame_budget_ms=80.0))
    a = viewer("a", p.Camera(distance=30.0), (1920, 1080))
    ((key, _),) = s.plan([a], 10.0, 1, None).groups
    assert s.note_render(key, 1, (1920, 1080), 4.0, now=10.0) is False  # a GPU: 4 ms
    assert s.image_size(key, 1.0) == (1920, 1080)
    assert s.pick_size(1920, 1080) == (1920, 1080)


def test_a_stream_keeps_its_steering_size_through_a_burst_of_changes() -> None:
    s = RenderScheduler(replace(SETTINGS, video_steer_hold_s=1.0))
    a, b = viewer("a"), viewer("b")
    assert not s.steering([a, b], 10.0)  # nobody has steered yet
    s.interacting(now=10.0)  # a shared parameter changed: every view steers
    assert s.steering([a], 10.9) and not s.steering([a], 11.0)
    # between two changes the view is no longer interactive, but the stream keeps its size
    ((key, _),) = s.plan([a], 10.5, 1, None).groups
    assert not key.interactive
    assert s.stream_size(key, 1.0) == (200, 100)
    assert s.stream_size(key, 1.0, steering=True) == (100, 50)  # the interactive image's
    b.interacted_at = 20.0  # b drags its camera: its group steers, a's does not
    assert s.steering([b], 20.5) and not s.steering([a], 20.5)
    # a render at the steering size is reduced only when the budget would have shrunk it:
    # the refinements toward the still at rest then follow as they would have
    assert not s.note_render(key, 1, (100, 50), 1.0, 20.5, budget_size=(200, 100))
    assert s.note_render(key, 1, (100, 50), 1.0, 20.5, budget_size=(150, 75))
    assert s.note_render(key, 1, (100, 50), 1.0, 20.5)


def test_no_steering_size_when_the_hold_is_zero() -> None:
    s = RenderScheduler(replace(SETTINGS, video_steer_hold_s=0.0))
    s.interacting(now=10.0)
    assert not s.steering([viewer("a")], 10.0)


def test_a_hold_that_is_not_a_duration_is_refused_by_name() -> None:
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="video_steer_hold_s"):
            replace(SETTINGS, video_steer_hold_s=bad)


def test_viewers_with_cameras_of_their_own_take_turns_and_never_hold_up_the_steerer() -> None:
    """40 viewers, each with its own camera, made every frame of their session wait for 40
    renders: its steerer went from 9.5 to 0.27 images/s. A pass now renders the steerer's view
    and `viewer_views_per_pass` others, the viewers in turn."""
    s = RenderScheduler(replace(SETTINGS, viewer_views_per_pass=2))
    steerer = client("steerer", "steerer")
    crowd = [viewer(f"v{i}", p.Camera(distance=100.0 + i)) for i in range(40)]
    everyone = [*crowd, steerer]
    served: dict[str, int] = {}
    for version in range(1, 21):  # twenty frames, one pass each
        plan = s.plan(everyone, float(version), version, default_camera=None)
        assert len(plan.groups) == 3
        assert plan.come_back_in == 0.0  # others are still due: the next pass comes at once
        assert steerer in plan.groups[0][1]  # every frame: the steerer's view first
        for key, members in plan.groups:
            s.rendered(key, version)
            for c in members:
                served[c.client_id] = served.get(c.client_id, 0) + 1
    assert served["steerer"] == 20
    # the viewers in turn: 40 images over 20 passes, each viewer one, none twice
    assert sorted(served.get(c.client_id, 0) for c in crowd) == [1] * 40
    # two steerers on cameras of their own are both in every pass
    other = client("other", "steerer")
    other.view = p.View(camera=p.Camera(distance=7.0), width=200, height=100)
    plan = s.plan([*everyone, other], 30.0, 30, default_camera=None)
    assert {steerer, other} <= {c for _, members in plan.groups for c in members}
    assert len(plan.groups) == 4
    # without a steerer, a pass renders every due view from one frame
    viewers_only = RenderScheduler(replace(SETTINGS, viewer_views_per_pass=2))
    assert len(viewers_only.plan(crowd, 1.0, 1, None).groups) == 40
    # the control: with room for every view, one pass serves all 41
    everyone_at_once = RenderScheduler(replace(SETTINGS, viewer_views_per_pass=64))
    assert len(everyone_at_once.plan(everyone, 1.0, 1, None).groups) == 41


def test_the_views_a_pass_renders_must_be_at_least_one() -> None:
    with pytest.raises(ValueError, match="viewer_views_per_pass"):
        replace(SETTINGS, viewer_views_per_pass=0)
