"""How a one-off image is cut into bands of rows, and when its bands refuse the rest
(`server.pipeline.bands`): pure arithmetic on the times the bands report."""

from __future__ import annotations

import pytest

from server.pipeline import bands
from server.pipeline.bands import BandPlan, TooCostlyError
from server.render.errors import CapacityError


def draw(plan: BandPlan, seconds_a_row: float, first_s: float = 0.0) -> list[int]:
    """Every band's rows, each taking `seconds_a_row` a row (the first `first_s` more)."""
    rows, out = plan.first(), []
    while rows:
        out.append(rows)
        extra = first_s if len(out) == 1 else 0.0
        rows = plan.drawn(rows, rows * seconds_a_row + extra)
    return out


def test_the_bands_cover_the_image_once_each_sized_to_a_tenth_of_a_second() -> None:
    plan = BandPlan(1920, 1080, limit_s=60.0)
    got = draw(plan, seconds_a_row=0.001)  # 1.08 s in all
    assert sum(got) == 1080 and plan.y == 1080
    assert got[0] == 9  # 1/128 of the rows
    assert got[1] == 72 and all(r == 100 for r in got[2:-1])  # 8x, then 0.1 s / 1 ms a row
    assert plan.spent_s == pytest.approx((1080 - 9) * 0.001)


def test_a_cheap_image_takes_few_bands_growing_at_most_eightfold() -> None:
    got = draw(BandPlan(500, 500, limit_s=60.0), seconds_a_row=1e-6)
    assert got == [4, 32, 256, 208]


def test_a_band_slowed_by_compiling_is_not_judged_and_only_shrinks_the_next() -> None:
    """The first band builds the grids and may compile kernels for seconds."""
    plan = BandPlan(640, 480, limit_s=5.0)
    got = draw(plan, seconds_a_row=0.001, first_s=30.0)
    assert sum(got) == 480 and got[1] == 1  # 30 s over 4 rows: a band of one row next
    assert plan.spent_s == pytest.approx((480 - 4) * 0.001)


def test_an_image_past_the_limit_is_refused_after_its_second_band() -> None:
    plan = BandPlan(1920, 1080, limit_s=60.0)
    rows = plan.first()
    rows = plan.drawn(rows, rows * 0.25)  # 0.25 s a row: about 270 s in all
    assert rows == 1
    with pytest.raises(TooCostlyError) as err:
        plan.drawn(rows, 0.25)
    assert isinstance(err.value, CapacityError)
    text = str(err.value)
    assert "1920x1080" in text and "about 268 s" in text and "limit of 60 s" in text
    assert "one_off_render_seconds" in text and "250.0 ms a row" in text
    assert plan.y == 10  # nothing more is drawn


def test_one_that_slows_down_part_way_is_refused_when_it_does() -> None:
    plan = BandPlan(1000, 1000, limit_s=2.0)
    rows = plan.drawn(plan.first(), 0.01)
    while plan.y < 500:  # empty rows at half a millisecond each
        rows = plan.drawn(rows, rows * 0.0005)
    with pytest.raises(TooCostlyError):
        plan.drawn(rows, rows * 0.01)  # the molecule's rows: 20x dearer


def test_a_one_row_image_is_one_band() -> None:
    plan = BandPlan(4096, 1, limit_s=0.001)
    assert plan.first() == 1 and plan.drawn(1, 100.0) == 0


def test_the_constants_say_what_the_docs_say() -> None:
    assert bands.FIRST_SHARE == 1 / 128 and bands.BAND_SECONDS == 0.1
