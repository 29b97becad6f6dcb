"""The runaway guard's judgement (simulation_adapters/runaway.py) on reported temperatures: a
cold start heats to its thermostat without tripping it, densely or sparsely reported, and a
blow-up trips it, with and without the engine's thermostat target."""

from __future__ import annotations

import pytest

from simulation_adapters.runaway import ORDINARY_K, RunawayGuard


def trips(reports: list[float], target_K: float | None = None) -> list[str]:
    guard = RunawayGuard()
    return [why for t in reports if (why := guard.check(t, target_K))]


@pytest.mark.parametrize(
    "reports",
    [
        [3.0, 311.0],  # one report as the run starts, the next once heated
        [0.0, 301.0],
        [2.0, 600.0, 598.0],  # a cold start to a hot thermostat
        [float(t) for t in range(0, 320, 4)] + [310.0] * 10,  # densely reported
        [300.0, 350.0, 290.0, 305.0],
    ],
)
def test_a_cold_or_steady_run_is_no_blow_up(reports: list[float]) -> None:
    assert trips(reports) == []


@pytest.mark.parametrize(
    ("reports", "target_K"),
    [
        ([300.0] * 5 + [5000.0], None),
        ([3.0, 2500.0], None),
        ([300.0] * 5 + [700.0], 300.0),  # past twice the engine's own target
        ([300.0, float("nan")], None),
    ],
)
def test_a_blow_up_trips_the_guard(reports: list[float], target_K: float | None) -> None:
    (why,) = trips(reports, target_K)
    assert "above the guard's" in why or "non-finite" in why


def test_a_user_limit_replaces_the_judgement() -> None:
    guard = RunawayGuard(limit_K=400.0)
    assert guard.check(3.0) == "" and guard.check(401.0) != ""
    assert RunawayGuard().limit() is None  # before the first report nothing trips
    first = RunawayGuard()
    first.check(300.0)
    assert first.limit() == ORDINARY_K and first.limit(300.0) == 600.0
