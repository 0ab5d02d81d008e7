"""How steps run on this machine: the thread tuner (gns.threads) and a rollout's precision
(gns.rollout.rollout_precision), against a simulated machine whose step times are known."""

from __future__ import annotations

import gns.rollout
import gns.threads
import numpy as np
import pytest
import torch
from gns.config import Config, ModelConfig
from gns.data import Trajectory
from gns.rollout import BF16_SPEEDUP, rollout, rollout_precision
from gns.simulator import LearnedSimulator, Scene
from gns.threads import StepTuner, fix_threads, thread_candidates, threads_fixed


class Machine:
    """Step times per setting under a load that the test switches on and off, a clock that
    only moves when told, and a record of every setting applied."""

    def __init__(self, idle: dict[int, float], loaded: dict[int, float]) -> None:
        self.idle, self.loaded = idle, loaded
        self.load = False
        self.now = 0.0
        self.setting = 2
        self.applied: list[int] = []

    def apply(self, setting: int) -> None:
        self.setting = setting
        self.applied.append(setting)

    def run(self, tuner: StepTuner[int], steps: int) -> list[int]:
        """`steps` steps; returns the setting each one ran with."""
        used = []
        for _ in range(steps):
            used.append(tuner.begin())
            assert used[-1] == self.setting  # begin() put it into effect
            seconds = (self.loaded if self.load else self.idle)[self.setting]
            self.now += seconds
            tuner.end(seconds)
        return used


def tuner_on(machine: Machine, **options) -> StepTuner[int]:
    return StepTuner(
        [2, 1], machine.apply, lambda: machine.setting, clock=lambda: machine.now, **options
    )


def test_the_tuner_keeps_the_fastest_setting_and_follows_the_load():
    # Idle, 2 threads are twice as fast; with a core busy, 2 threads stall (Zen 4: 1,166 ms
    # against 13 ms on one thread).
    machine = Machine(idle={2: 0.004, 1: 0.008}, loaded={2: 1.2, 1: 0.013})
    with tuner_on(machine, probe_steps=3, recheck_seconds=30.0) as tuner:
        # Probing: one warm-up and 3 measured steps of each candidate, in the given order.
        assert machine.run(tuner, 8) == [2] * 4 + [1] * 4
        assert tuner.chosen == 2 and tuner.probes == 1
        assert set(machine.run(tuner, 50)) == {2}
        # Another process takes a core: the steps get 300x slower, so once the median of
        # the last probe_steps steps is slow (2 of 3) the tuner tries one thread and keeps it.
        machine.load = True
        used = machine.run(tuner, 2 + 4 + 20)
        assert used[:2] == [2, 2] and used[2:6] == [1] * 4 and set(used[6:]) == {1}
        assert tuner.chosen == 1 and tuner.probes == 2
        # The core comes free: one thread is not slower than before, so nothing happens
        # until recheck_seconds have passed; then 2 threads are probed and win again.
        machine.load = False
        steps_to_recheck = int((30.0 - 20 * 0.013) / 0.008)  # 20 loaded steps since the probe
        assert set(machine.run(tuner, steps_to_recheck - 10)) == {1}
        used = machine.run(tuner, 30)
        assert 2 in used and used[-1] == 2 and tuner.chosen == 2
    # The setting in effect before the tuner is restored when it is done.
    assert machine.setting == 2 and machine.applied[-1] == 2


def test_a_recheck_that_changes_nothing_waits_twice_as_long_for_the_next():
    machine = Machine(idle={2: 0.01, 1: 0.02}, loaded={2: 0.01, 1: 0.02})
    with tuner_on(machine, probe_steps=2, recheck_seconds=1.0) as tuner:
        probes_at = []
        for _ in range(10_000):
            before = tuner.probes
            machine.run(tuner, 1)
            if tuner.probes > before:
                probes_at.append(machine.now)
        gaps = np.diff(probes_at)
        # 1 s, then 2, 4, 8, 16 s, and never more than 16 times recheck_seconds (a probe
        # round itself takes a few steps of 0.01-0.02 s).
        assert gaps[:7] == pytest.approx([1.0, 2.0, 4.0, 8.0, 16.0, 16.0, 16.0], abs=0.1)
        assert tuner.chosen == 2


def test_a_single_candidate_is_never_switched_and_ties_keep_the_first():
    machine = Machine(idle={2: 0.01, 1: 0.01}, loaded={})
    with StepTuner([2], machine.apply) as tuner:
        machine.run(tuner, 20)
    assert machine.applied == [2] and tuner.probes == 0
    with tuner_on(machine) as tuner:
        machine.run(tuner, 20)
        assert tuner.chosen == 2  # equal times: the first candidate
    with pytest.raises(ValueError, match="at least one candidate"):
        StepTuner([], machine.apply)


def test_threads_fixed_by_the_user_are_not_tuned(monkeypatch):
    monkeypatch.setattr(gns.threads, "_fixed", None)
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert thread_candidates() == (2, 1) and not threads_fixed()
        monkeypatch.setenv("OMP_NUM_THREADS", "2")  # as torchrun sets it
        assert thread_candidates() == (2,) and threads_fixed()
        monkeypatch.delenv("OMP_NUM_THREADS")
        fix_threads(2)  # what --threads 2 does
        assert thread_candidates() == (2,) and torch.get_num_threads() == 2
        for bad in (0, -1, 1.5, True):
            with pytest.raises(ValueError, match="threads must be a whole number >= 1"):
                fix_threads(bad)
    finally:
        torch.set_num_threads(before)


# ---------------------------------------------------------------------------------- precision


def small_simulator(precision: str = "auto") -> tuple[LearnedSimulator, Trajectory]:
    rng = np.random.default_rng(0)
    n = 60
    start = rng.uniform(0.3, 0.7, (n, 2))
    positions = start + 1e-3 * np.arange(12)[:, None, None] * rng.normal(size=(1, n, 2))
    scene = Scene(2, 0.08, (5,), bounds=((0.0, 1.0), (0.0, 1.0)), walls=True)
    model = ModelConfig(latent_size=16, mlp_hidden_size=16, message_passing_steps=2)
    torch.manual_seed(0)
    simulator = LearnedSimulator(
        scene, Config(model=ModelConfig(**{**model.__dict__, "precision": precision}))
    )
    trajectory = Trajectory(positions.astype(np.float32), np.full(n, 5))
    # Statistics from the data, so that the untrained network's outputs are of the data's
    # size and the rollout stays in the box.
    window = torch.from_numpy(trajectory.positions[:7].transpose(1, 0, 2).copy())
    acceleration = torch.from_numpy(rng.normal(0.0, 1e-5, (n, 2)))
    simulator.update_statistics(window[:, :6], acceleration, torch.full((n,), 5))
    return simulator, trajectory


def first_features(simulator: LearnedSimulator, trajectory: Trajectory) -> dict:
    window = torch.from_numpy(trajectory.positions[:6].transpose(1, 0, 2).copy())
    types = torch.from_numpy(trajectory.particle_type.copy())
    with torch.inference_mode():
        return simulator.features(window, types)


def clock_of(durations: list[float]):
    """A clock whose successive start/end readings give these durations, in turn."""
    # Readings 0, d1, d1, d1 + d2, d1 + d2, ...: each (start, end) pair spans one duration.
    ticks = iter(np.cumsum([0.0] + [x for d in durations for x in (d, 0.0)]))
    return lambda: float(next(ticks))


@pytest.mark.parametrize(("fp32", "bf16", "expected"), [(1.0, 0.5, "bf16"), (1.0, 0.95, "fp32"),
                                                        (1.0, 1.5, "fp32")])  # fmt: skip
def test_auto_precision_takes_bf16_only_when_measured_faster(monkeypatch, fp32, bf16, expected):
    monkeypatch.setattr(gns.rollout, "native_bf16", lambda device: True)
    simulator, trajectory = small_simulator()
    f = first_features(simulator, trajectory)
    # rollout_precision times fp32 then bf16, `repeats` times.
    clock = clock_of([fp32, bf16] * 3)
    with torch.inference_mode():
        chosen = rollout_precision(simulator.model, f, torch.device("cpu"), clock, repeats=3)
    assert chosen == expected
    assert (fp32 >= BF16_SPEEDUP * bf16) == (expected == "bf16")
    assert simulator.model.precision == "auto"  # measuring left the model as it was


def test_auto_precision_is_fp32_where_bf16_is_emulated_or_too_far_off(monkeypatch):
    simulator, trajectory = small_simulator()
    f = first_features(simulator, trajectory)
    never = lambda: pytest.fail("nothing should be timed")  # noqa: E731
    monkeypatch.setattr(gns.rollout, "native_bf16", lambda device: False)
    with torch.inference_mode():
        assert rollout_precision(simulator.model, f, torch.device("cpu"), never) == "fp32"
    monkeypatch.setattr(gns.rollout, "native_bf16", lambda device: True)
    monkeypatch.setattr(gns.rollout, "BF16_TOLERANCE", 0.0)  # any rounding is too much
    with torch.inference_mode():
        assert rollout_precision(simulator.model, f, torch.device("cpu"), never) == "fp32"
    for asked in ("fp32", "bf16"):  # asked for by name: used as it is, nothing measured
        simulator.model.precision = asked
        with torch.inference_mode():
            assert rollout_precision(simulator.model, f, torch.device("cpu"), never) == asked


def test_bf16_difference_is_the_rms_of_bf16_minus_fp32():
    simulator, trajectory = small_simulator()
    f = first_features(simulator, trajectory)
    args = [f[k] for k in gns.rollout.FEATURE_KEYS]
    with torch.inference_mode():
        simulator.model.precision = "fp32"
        reference = simulator.model(*args)
        simulator.model.precision = "bf16"
        low = simulator.model(*args)
        simulator.model.precision = "auto"
        difference = gns.rollout.bf16_difference(simulator.model, f)
    expected = float(np.sqrt(np.mean((low.double() - reference.double()).numpy() ** 2)))
    assert difference == pytest.approx(expected, rel=1e-5)
    assert 0 < difference < gns.rollout.BF16_TOLERANCE  # bf16 rounds, but not by much


def test_rollouts_are_the_same_whatever_thread_count_the_tuner_picks():
    """The tuner may switch threads between steps: a rollout must not depend on it."""
    simulator, trajectory = small_simulator("fp32")
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2, 1):
            torch.set_num_threads(threads)
            results.append(rollout(simulator, trajectory).predicted_rollout)
    finally:
        torch.set_num_threads(before)
    np.testing.assert_array_equal(results[0], results[1])
    np.testing.assert_array_equal(results[0], results[2])


def test_a_rollout_records_the_threads_and_precision_it_ran_with():
    simulator, trajectory = small_simulator()
    result = rollout(simulator, trajectory)
    assert result.metadata["precision"] == "fp32"  # bf16 is not native in tests (conftest)
    assert result.metadata["torch_threads"] in thread_candidates()
    assert simulator.model.precision == "auto"
