"""The steps of a session's frames: whether a frame continues its run or jumps (a replay
seeked, a simulation reset), and how fast the steps go."""

from __future__ import annotations

from collections import deque

RATE_WINDOW_S = 3.0


def is_jump(last_step: int, delta: int, step: int) -> bool:
    """Whether `step` does not continue a run whose steps grew by `delta`: it goes back (a
    replay seeked or a simulation was reset) or skips ahead by more than 4 usual increments."""
    return step <= last_step or (delta > 0 and step - last_step > 4 * delta)


class StepRun:
    """The steps of a run of frames, to tell a frame that continues it from a jump (`is_jump`).
    The session keeps two: frames as they arrive (a jump starts the unwrapping across the box
    again) and frames as displayed (a jump starts the smoothing window again)."""

    def __init__(self) -> None:
        self.last: int | None = None
        self.delta = 0

    def advance(self, step: int) -> bool:
        """Take `step`; whether it jumped (the first step of a run never does)."""
        jumped = self.last is not None and is_jump(self.last, self.delta, step)
        if self.last is not None and not jumped:
            self.delta = step - self.last
        self.last = step
        return jumped

    def reset(self) -> None:
        """The next step starts a new run."""
        self.last = None


class StepRate:
    """Simulation steps per second over the frames of the last few seconds."""

    def __init__(self, window_s: float = RATE_WINDOW_S) -> None:
        self.window_s = window_s
        self._frames: deque[tuple[float, int]] = deque()

    def add(self, now: float, step: int) -> float:
        frames = self._frames
        while frames and now - frames[0][0] >= self.window_s:
            frames.popleft()
        frames.append((now, step))
        (t0, s0), (t1, s1) = frames[0], frames[-1]
        return max(0.0, (s1 - s0) / (t1 - t0)) if t1 > t0 else 0.0
