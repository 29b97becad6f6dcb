"""The visible-bricks count: every walked brick is counted once, and only those near a hit."""

from __future__ import annotations

from benchmarks import visible_bricks


def test_the_bricks_near_a_hit_are_a_part_of_those_walked() -> None:
    row = visible_bricks.measure(300, 48, 36, 1.5)
    assert row["hit_pixels"] > 100
    assert 0 < row["bricks_reached"] <= row["bricks_walked"]
    assert row["reached_share"] == row["bricks_reached"] / row["bricks_walked"]
    # a reach of nothing leaves only the bricks a hit lies in or beside
    none = visible_bricks.measure(300, 48, 36, 1.5, reach_steps=0.0)
    assert none["bricks_walked"] == row["bricks_walked"]
    assert none["bricks_reached"] < row["bricks_reached"]
