"""The demo's simulation paces its frames by its own speed: about FRAMES_PER_S a second."""

from __future__ import annotations

from server.commands.villin import FRAMES_PER_S, MAX_INTERVAL, MIN_INTERVAL, Pace


def test_frames_come_about_as_often_whatever_the_speed() -> None:
    slow = Pace(10)  # a busy 2-core laptop: about 100 villin steps a second
    assert slow.after(50, 0.5) == round(100 / FRAMES_PER_S) > MIN_INTERVAL
    fast = Pace(10)  # a GPU: thousands a second, a frame every 50 steps at most
    assert fast.after(50, 0.005) == MAX_INTERVAL
    crawl = Pace(10)  # a report costs a step or two: never more often than MIN_INTERVAL
    assert crawl.after(50, 10.0) == MIN_INTERVAL


def test_a_stop_or_one_slow_stretch_moves_the_pace_little() -> None:
    pace = Pace(10)
    assert pace.after(50, 0.25) == 17  # 200 steps/s
    assert pace.after(3, 0.01) == 17  # a stop after 3 steps says nothing of the speed
    assert pace.after(85, 4.25) == 12  # a chunk at 20 steps/s (a pause in it): a running mean
