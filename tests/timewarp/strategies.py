"""Hypothesis strategies shared by the timewarp tests: sampled signals and monotone warps."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st


@st.composite
def sampled_signals(
    draw: st.DrawFn,
    min_n: int = 2,
    max_n: int = 24,
    max_abs: float = 20.0,
    uniform: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """A strictly increasing abscissa ``t`` and signal values ``f`` of the same length."""
    n = draw(st.integers(min_n, max_n))
    vals = st.floats(-max_abs, max_abs, allow_nan=False, allow_infinity=False)
    f = np.array(draw(st.lists(vals, min_size=n, max_size=n)), dtype=np.float64)
    if uniform:
        t = np.arange(n, dtype=np.float64)
    else:
        steps = draw(st.lists(st.floats(0.05, 3.0), min_size=n - 1, max_size=n - 1))
        t0 = draw(st.floats(-10.0, 10.0))
        t = t0 + np.concatenate([[0.0], np.cumsum(steps)])
    return t, f


@st.composite
def increasing_knots(draw: st.DrawFn, n: int) -> np.ndarray:
    """``n`` strictly increasing values with gaps in [0.1, 5]."""
    steps = draw(st.lists(st.floats(0.1, 5.0), min_size=n - 1, max_size=n - 1))
    start = draw(st.floats(-5.0, 5.0))
    return start + np.concatenate([[0.0], np.cumsum(steps)])
