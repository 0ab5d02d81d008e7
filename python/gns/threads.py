"""How a loop of like steps runs on this machine: torch's CPU thread count (and, for inference
where bfloat16 is native, the precision), chosen by timing the steps themselves.

Why measure: on a 2-core machine with another process on one core, torch's OpenMP workers
wait for a thread that is not running. A GNS-3-32 rollout step took 1,166 ms on 2 threads and
13 ms on one (Zen 4, issue 22); idle, 2 threads were 2x faster than one. OpenMP's passive wait
policy (OMP_WAIT_POLICY=passive) avoided that stall there, but on a Zen 5 VM it made idle steps
2-7x slower (GNS-3-32 5.2 -> 34.9 ms, GNS-10-128 92 -> 170 ms), and bfloat16 is 2.1x faster
than fp32 for GNS-10-128 there but 1.2x slower for GNS-3-32. No fixed choice is right on every
machine, model and load, so `StepTuner` tries the candidates on real steps (no work is thrown
away), keeps the fastest, and tries again when the steps get slower or a while has passed.

    tuner = StepTuner(candidates, apply)      # e.g. thread_candidates() and set_threads
    with tuner:                               # restores the settings it found on exit
        for step in ...:
            tuner.begin()                     # applies the setting this step runs with
            ...                               # the step
            tuner.end(seconds)                # how long it took

The thread count is left alone when the user fixed it: OMP_NUM_THREADS in the environment (as
torchrun sets it) or `fix_threads(n)` (what `--threads N` calls). Results can differ in the
last bits between thread counts (reductions are split differently), so a run that must be
bit-for-bit reproducible, such as training resumed exactly, should fix its threads.
"""

from __future__ import annotations

import os
import statistics
import time
from collections import deque
from collections.abc import Callable, Hashable, Sequence
from typing import Any, Generic, TypeVar

__all__ = [
    "StepTuner",
    "fix_threads",
    "thread_candidates",
    "thread_tuner",
    "threads_fixed",
]

Setting = TypeVar("Setting", bound=Hashable)

# Set by fix_threads (the command line's --threads N): the user chose, nothing is tuned.
_fixed: int | None = None


def fix_threads(threads: int) -> None:
    """Use exactly `threads` torch CPU threads from now on; StepTuners leave them alone."""
    global _fixed
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"threads must be a whole number >= 1, got {threads!r}")
    import torch

    torch.set_num_threads(threads)
    _fixed = threads


def threads_fixed() -> bool:
    """Whether the user fixed the thread count (fix_threads or OMP_NUM_THREADS)."""
    return _fixed is not None or bool(os.environ.get("OMP_NUM_THREADS"))


def thread_candidates() -> tuple[int, ...]:
    """The torch thread counts worth trying: torch's current count (by default one per
    physical core) and one, unless the user fixed the count."""
    import torch

    current = torch.get_num_threads()
    if threads_fixed() or current == 1:
        return (current,)
    return (current, 1)


class StepTuner(Generic[Setting]):
    """Chooses among `candidates` the setting under which a repeated step runs fastest.

    apply(setting) puts a setting into effect; `current()` reads back what is in effect (it is
    restored when the tuner's `with` block ends). The first candidate is used on ties and
    while nothing has been measured.

    Probing: each candidate runs `probe_steps` steps after one warm-up step (the first step
    after a switch pays for waking threads or converting weights), and the one with the lowest
    median wins. The running choice is timed all along; all candidates are probed again when
    its median over the last `probe_steps` steps exceeds `slowdown` times what it was chosen at
    (another process took a core, or the work grew), or when `recheck_seconds` have passed
    (a core may have come free). A re-probe that keeps the same choice doubles the interval
    before the next one, up to 16 times, because probing a bad setting under load is costly.
    """

    def __init__(
        self,
        candidates: Sequence[Setting],
        apply: Callable[[Setting], None],
        current: Callable[[], Setting] | None = None,
        *,
        probe_steps: int = 3,
        recheck_seconds: float = 30.0,
        slowdown: float = 2.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not candidates:
            raise ValueError("StepTuner needs at least one candidate setting")
        if probe_steps < 1:
            raise ValueError(f"probe_steps must be at least 1, got {probe_steps}")
        self.candidates = tuple(dict.fromkeys(candidates))
        self._apply, self._current = apply, current
        self.probe_steps, self.slowdown = probe_steps, slowdown
        self.recheck_seconds = recheck_seconds
        self._clock = clock
        self._saved: Any = None
        self.chosen: Setting = self.candidates[0]
        self._chosen_time = float("inf")
        self._active: Setting | None = None
        # Probing state: the candidates still to measure and the times of the one being run.
        self._queue: list[Setting] = list(self.candidates) if len(self.candidates) > 1 else []
        self._probe_times: list[float] = []
        self._results: dict[Setting, float] = {}
        self._recent: deque[float] = deque(maxlen=probe_steps)
        self._interval = recheck_seconds
        self._last_probe = clock()
        self.probes = 0  # completed rounds of probing (for tests and logs)

    # ------------------------------------------------------------------ context

    def __enter__(self) -> StepTuner[Setting]:
        self._saved = self._current() if self._current is not None else None
        return self

    def __exit__(self, *exc: object) -> None:
        if self._saved is not None and self._active is not None and self._saved != self._active:
            self._apply(self._saved)
        self._active = None

    # ------------------------------------------------------------------ steps

    def _use(self, setting: Setting) -> None:
        if setting != self._active:
            self._apply(setting)
            self._active = setting

    def begin(self) -> Setting:
        """Put the setting of the next step into effect and return it."""
        setting = self._queue[0] if self._queue else self.chosen
        self._use(setting)
        return setting

    def end(self, seconds: float) -> None:
        """Record how long the step started by begin() took."""
        if self._queue:
            self._probe_times.append(seconds)
            # One warm-up step, then probe_steps measured ones.
            if len(self._probe_times) > self.probe_steps:
                self._results[self._queue.pop(0)] = statistics.median(self._probe_times[1:])
                self._probe_times = []
                if not self._queue:
                    self._decide()
            return
        self._recent.append(seconds)
        if len(self.candidates) == 1 or len(self._recent) < self.probe_steps:
            return
        slower = statistics.median(self._recent) > self.slowdown * self._chosen_time
        if slower or self._clock() - self._last_probe > self._interval:
            if slower:
                self._interval = self.recheck_seconds
            # The running choice's time is known from its recent steps; probe the others.
            self._results = {self.chosen: statistics.median(self._recent)}
            self._queue = [c for c in self.candidates if c != self.chosen]

    def _decide(self) -> None:
        previous = self.chosen
        # min() keeps the first of equal times: candidates are listed in order of preference.
        self.chosen = min(self.candidates, key=lambda c: self._results.get(c, float("inf")))
        self._chosen_time = self._results[self.chosen]
        self._recent.clear()
        self._last_probe = self._clock()
        self.probes += 1
        if self.probes > 1 and self.chosen == previous:
            self._interval = min(2 * self._interval, 16 * self.recheck_seconds)
        else:
            self._interval = self.recheck_seconds


def thread_tuner(**options: Any) -> StepTuner[int]:
    """A StepTuner of torch's CPU thread count over thread_candidates() (one candidate, so
    nothing is tuned, when the user fixed the count); options go to StepTuner."""
    import torch

    return StepTuner(thread_candidates(), torch.set_num_threads, torch.get_num_threads, **options)
