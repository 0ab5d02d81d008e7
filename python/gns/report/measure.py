"""gns report's measuring (see gns.report): the rows of the learned model and of the baselines
(constant velocity, static), each rolled out or extrapolated, timed and scored on the same
frames (`score`), and the ground truth's own deposit. The reference simulator's rows are
gns.report.reference's; the files and words made of the rows, gns.report.render's and
gns.report.conclusion's."""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gns.baselines import constant_velocity_rollout, static_rollout
from gns.config import MODEL_NAMES
from gns.deposit import DEPOSIT_CURVES, DEPOSIT_FIGURES, deposit, deposit_ratios, pile_floor
from gns.metrics import evaluate_rollout
from gns.periodic import period_of

__all__ = ["CONSTANT_VELOCITY", "METRICS", "STATIC", "TIMING_PARTS", "Row", "score"]

METRICS = ("mse", "ot", "mmd")
TIMING_PARTS = ("graph", "features", "model", "integration")
# The baselines' rows (method names).
CONSTANT_VELOCITY, STATIC = "constant velocity", "static"


# ----------------------------------------------------------------------------------- scoring


def score(
    predicted: np.ndarray,
    truth: np.ndarray,
    mask: np.ndarray,
    horizons: Sequence[int | None],
    every: int,
    *,
    floor: float | None = None,
    radius: float | None = None,
    bounds: Sequence[Sequence[float]] | None = None,
    periodic: Sequence[bool] | None = None,
) -> dict[str, Any]:
    """The figures of one rollout, predicted and truth (S, N, D), over the particles in mask
    (N,) bool: {"mse@h", "ot@h", "mmd@h" for each horizon no longer than S; "mse": (S,)
    per-frame MSE; "frames", "ot": the evaluated frames and their W2^2}, and the deposit of
    the last frame (gns.deposit.deposit and deposit_ratios): "runout", "pile_height" (with a
    floor), "neighbours" (with a radius), "runout_ratio", "height_ratio", "density_ratio" (over
    the truth's), "density_ratio_max" (the worst frame's), and the fronts "front_x_p1",
    "front_x_p99" (S,). NaN in `predicted` (a diverged rollout, padded) scores inf, never a
    finite number."""
    m = evaluate_rollout(
        predicted,
        truth,
        mask=mask,
        horizons=horizons,
        distribution_every=every,
        nonfinite="inf",
        period=period_of(bounds, periodic),
    )
    steps = truth.shape[0]
    out: dict[str, Any] = {}
    for metric in METRICS:
        for h in horizons:
            if h is not None and h > steps:
                continue
            key = f"{metric}@{'full' if h is None else h}"
            if metric == "mse":
                out[key] = m[key]
            else:
                # Frame 0 is always evaluated, so every horizon has at least one frame.
                evaluated = m[metric] if h is None else m[metric][m["frames"] < h]
                out[key] = float(np.mean(evaluated))
    out.update(mse=m["mse"], frames=m["frames"], ot=m["ot"])
    ours, theirs = (
        deposit(positions, mask, floor, radius=radius, bounds=bounds, periodic=periodic)
        for positions in (predicted, truth)
    )
    out.update(ours)
    out.update(deposit_ratios(ours, theirs))
    return out


@dataclass(frozen=True)
class _Scoring:
    """How every row is scored, the same for all: the frames from `history` on, the particles
    not of `kinematic_types`, the horizons, OT and MMD on every `every`-th predicted frame, and
    the dataset's box (the floor of the pile height), connectivity radius and periodic axes
    for the deposit."""

    history: int
    kinematic_types: tuple[int, ...]
    horizons: tuple[int | None, ...]
    every: int
    bounds: tuple[tuple[float, float], ...] | None = None
    radius: float | None = None
    periodic: tuple[bool, ...] | None = None

    def free(self, trajectory: Any) -> np.ndarray:
        """(N,) bool: the particles that count."""
        return ~_kinematic(trajectory.particle_type, self.kinematic_types)

    def truth(self, trajectory: Any) -> np.ndarray:
        """(S, N, D): the frames every row predicts."""
        return np.asarray(trajectory.positions[self.history :])

    def torus(self) -> dict[str, Any]:
        """The box of a baseline that moves particles across periodic axes (bounds, period),
        empty without periodic axes."""
        period = period_of(self.bounds, self.periodic)
        return {} if period is None else {"bounds": self.bounds, "period": period}

    def _scene(self, trajectory: Any) -> dict[str, Any]:
        floor = pile_floor(self.bounds, trajectory.positions[0])
        return {"floor": floor, "radius": self.radius, "bounds": self.bounds}

    def __call__(self, predicted: np.ndarray, trajectory: Any) -> dict[str, Any]:
        """`score` of a prediction (S, N, D) of the trajectory."""
        return score(
            predicted,
            self.truth(trajectory),
            self.free(trajectory),
            self.horizons,
            self.every,
            periodic=self.periodic,
            **self._scene(trajectory),
        )

    def ground_truth(self, trajectory: Any) -> dict[str, Any]:
        """The deposit of the trajectory's own frames (gns.deposit.deposit)."""
        return deposit(
            self.truth(trajectory),
            self.free(trajectory),
            periodic=self.periodic,
            **self._scene(trajectory),
        )


@dataclass
class Row:
    """One method of the table. role: "learned" (a checkpoint), "mpm" (the reference simulator;
    native: at the settings that made the data; same_simulator: gns.mpm made the data, so
    the native row reproduces it) or "baseline" (constant velocity, static).
    values: metric key (and deposit figure, DEPOSIT_FIGURES) -> mean over trajectories (inf:
    diverged; missing: not computed); split: TIMING_PARTS -> seconds per frame (learned rows
    only), whose sum is seconds_per_frame; curve, ot_curve: per-frame means for the
    error-over-time figure; diverged: (trajectory, step) of every rollout whose error stops
    being finite at that step (0-based: the step that predicts frame C + 1 + step); deposits:
    per trajectory, its deposit figures and fronts (DEPOSIT_FIGURES, DEPOSIT_CURVES); rest:
    gns.evaluate.rest_summary of the rest test (learned rows, when asked for)."""

    method: str
    setting: str
    device: str
    seconds_per_frame: float | None = None
    split: dict[str, float] = field(default_factory=dict)
    values: dict[str, float] = field(default_factory=dict)
    trajectories: int = 0
    status: str = "ok"
    curve: np.ndarray | None = None
    ot_curve: tuple[np.ndarray, np.ndarray] | None = None
    short: str = ""  # the label in the figures
    role: str = "learned"
    native: bool = False
    diverged: list[tuple[int, int]] = field(default_factory=list)
    deposits: list[dict[str, Any]] = field(default_factory=list)
    rest: dict[str, Any] | None = None
    # MPM rows: whether this simulator made the data (gns generate), so that the native row is
    # the ground truth itself; False on another simulator's data, where it is a contender.
    same_simulator: bool = True

    def add_scores(self, scores: Sequence[dict[str, Any]], trajectories: Sequence[int]) -> None:
        """Means over the trajectories' scores (score's output, one per trajectory index)."""
        keys = [k for k in dict.fromkeys(k for s in scores for k in s) if _averaged(k)]
        self.values = {k: float(np.mean([s[k] for s in scores])) for k in keys}
        self.deposits = [
            {
                "trajectory": index,
                **{k: s[k] for k in (*DEPOSIT_FIGURES, *DEPOSIT_CURVES) if k in s},
            }
            for index, s in zip(trajectories, scores, strict=True)
        ]
        self.trajectories = len(scores)
        self.curve = np.mean([s["mse"] for s in scores], axis=0)
        self.ot_curve = (scores[0]["frames"], np.mean([s["ot"] for s in scores], axis=0))
        # From the errors themselves rather than from the rollout's exception, so that any
        # non-finite error marks the row, whatever made it.
        self.diverged = [
            (index, int(bad[0]))
            for index, s in zip(trajectories, scores, strict=True)
            if len(bad := np.flatnonzero(~np.isfinite(s["mse"])))
        ]

    @property
    def diverged_at(self) -> int | None:
        """The first step at which some trajectory's rollout diverged, or None."""
        return min((step for _, step in self.diverged), default=None)

    def divergence(self) -> str:
        """Where the rollouts diverged, e.g. "trajectory 0 at step 3, trajectory 2 at step 40
        (2 of 3 trajectories)"; empty when none did."""
        if not self.diverged:
            return ""
        where = ", ".join(f"trajectory {i} at step {k}" for i, k in self.diverged)
        of = _count(self.trajectories, "trajectory", "trajectories")
        return f"{where} ({len(self.diverged)} of {of})"


def _averaged(key: str) -> bool:
    """Whether a key of score's output is a figure that Row.values holds the mean of."""
    return "@" in key or key in DEPOSIT_FIGURES


def _count(n: int, noun: str, plural: str | None = None) -> str:
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


# ----------------------------------------------------------------------------------- methods


def _kinematic(particle_type: np.ndarray, kinematic_types: Sequence[int]) -> np.ndarray:
    return np.isin(particle_type, list(kinematic_types))


def _device_label(device: Any, ran: Sequence[dict[str, Any]]) -> str:
    """Where a learned row ran and how: the device, and the torch threads and precision its
    rollouts chose (gns.rollout records them; they may differ between rollouts under load)."""
    import torch

    threads = sorted({int(r["torch_threads"]) for r in ran if "torch_threads" in r})
    precisions = sorted({str(r["precision"]) for r in ran if "precision" in r})
    if device.type == "cuda":
        where = f"{device} ({torch.cuda.get_device_name(device)})"
    else:
        counts = "-".join(str(t) for t in threads) or str(torch.get_num_threads())
        where = f"cpu, {counts} torch thread{'' if counts == '1' else 's'}"
    return ", ".join([where, *precisions])


def _trained_for(state: Mapping[str, Any]) -> str | None:
    """How a checkpoint was trained, for its row: "step 4000", or for an export that averages
    checkpoints (gns export --average) "mean of steps 6000-10000"."""
    averaged = state.get("averaged_steps")
    if averaged:
        return f"mean of steps {averaged[0]}-{averaged[-1]}"
    step = state.get("step")
    return None if step is None else f"step {step}"


def _learned_row(
    checkpoint: Path,
    label: str,
    simulator: Any,
    trained_for: str | None,
    trajectories: list[Any],
    indices: list[int],
    scoring: _Scoring,
    device: Any,
    rollouts_dir: Path,
    split: str,
    recorded: Mapping[str, Any],
    rest_steps: int,
    say: Callable[[str], None],
) -> tuple[Row, list[np.ndarray]]:
    """Roll the simulator of the file `checkpoint` (label: a name for its row or ""; trained_for:
    e.g. "step 4000") out on every trajectory (timed), score the rollouts, save them with their
    deposit (Rollout.metrics) and `recorded` (what they ran on: dataset, split, frame stride)
    in their metadata, and with rest_steps > 0 run the rest test on every trajectory. Returns
    the row and the predictions (S, N, D) per trajectory, NaN after a divergence."""
    from gns.evaluate import rest_summary, rest_test
    from gns.rollout import RolloutDiverged, rollout, rollout_path, save_rollout

    setting = f"{checkpoint.name} ({trained_for})" if trained_for else checkpoint.name
    if label:
        setting = f"{label}: {setting}"
    say(f"rolling out {setting} on {len(trajectories)} trajectories")
    # One short untimed rollout first: the first call pays for lazy initialisation (allocator,
    # kernels), which is not the cost of simulating a frame.
    first = trajectories[0]
    rollout(simulator, first, num_steps=min(2, first.num_frames - scoring.history))
    scores, predictions, seconds, ran = [], [], [], []
    rollouts_dir.mkdir(parents=True, exist_ok=True)
    for index, trajectory in zip(indices, trajectories, strict=True):
        info = {**recorded, "checkpoint": str(checkpoint)}
        try:
            result = rollout(simulator, trajectory, metadata=info)
        except RolloutDiverged as err:
            # Its steps before the divergence; the NaN padding below scores the rest as inf.
            result = err.rollout
        ran.append(result.metadata)
        say(f"  trajectory {index}: {result.num_steps} steps rolled out; scoring")
        predicted = np.full(scoring.truth(trajectory).shape, np.nan, dtype=np.float64)
        predicted[: result.num_steps] = result.predicted_rollout
        scores.append(scoring(predicted, trajectory))
        # Its deposit travels with the saved rollout; the fronts of the frames it has.
        result.metrics.update({k: scores[-1][k] for k in DEPOSIT_FIGURES if k in scores[-1]})
        result.metrics.update(
            {k: scores[-1][k][: result.num_steps] for k in DEPOSIT_CURVES if k in scores[-1]}
        )
        save_rollout(rollout_path(rollouts_dir, split, index), result)
        predictions.append(predicted)
        seconds.append(np.stack([result.timings[part] for part in TIMING_PARTS]))
    timings = np.concatenate(seconds, axis=1)  # (parts, all steps of all trajectories)
    name = MODEL_NAMES[simulator.config.model.kind]
    how = setting
    if any(r["enforce_walls"] for r in ran):
        # A model kept in the box by its walls says so, with what they changed.
        moved = sum(r["wall_corrections"] for r in ran)
        largest = max(r["wall_correction_max"] for r in ran)
        how += (
            f"; walls enforced: {moved} particle-steps put back on a wall (at most {largest:.2g})"
        )
    row = Row(name, how, _device_label(device, ran), short=f"{name} {setting}")
    if timings.shape[1]:
        # Means, not medians: the parts' means add up to the mean total.
        row.split = {part: float(timings[i].mean()) for i, part in enumerate(TIMING_PARTS)}
        row.seconds_per_frame = float(timings.sum(axis=0).mean())
    row.add_scores(scores, indices)
    if row.diverged:
        # gns.rollout stops at a non-finite position or at a particle far outside the domain.
        row.status = "diverged (non-finite or escaped particles): " + row.divergence()
    if rest_steps:
        say(f"  rest test: the last frames held still for {rest_steps} steps")
        held = [rest_test(simulator, t, rest_steps, device=device) for t in trajectories]
        row.rest = rest_summary(held, rest_steps)
    return row, predictions


def _baseline_row(
    method: str,
    setting: str,
    extrapolate: Callable[..., np.ndarray],
    trajectories: list[Any],
    indices: list[int],
    scoring: _Scoring,
) -> Row:
    """A baseline's row: `extrapolate` (gns.baselines' constant_velocity_rollout or
    static_rollout) from the input frames of every trajectory, timed and scored."""
    scores, elapsed, frames = [], 0.0, 0
    for trajectory in trajectories:
        truth = scoring.truth(trajectory)
        kinematic = ~scoring.free(trajectory)
        start = time.perf_counter()
        predicted = extrapolate(
            trajectory.positions[: scoring.history],
            len(truth),
            kinematic_mask=kinematic,
            ground_truth=truth,
        )
        elapsed += time.perf_counter() - start
        frames += len(truth)
        scores.append(scoring(predicted, trajectory))
    row = Row(method, setting, "cpu, numpy", role="baseline", short=method)
    row.seconds_per_frame = elapsed / frames
    row.add_scores(scores, indices)
    return row


def _constant_velocity_row(trajectories: list[Any], indices: list[int], scoring: _Scoring) -> Row:
    return _baseline_row(
        CONSTANT_VELOCITY,
        "x(t+1) = 2 x(t) - x(t-1)",
        functools.partial(constant_velocity_rollout, **scoring.torus()),
        trajectories,
        indices,
        scoring,
    )


def _static_row(trajectories: list[Any], indices: list[int], scoring: _Scoring) -> Row:
    return _baseline_row(
        STATIC,
        "x(t+1) = x(t): the last input frame held",
        static_rollout,
        trajectories,
        indices,
        scoring,
    )


def _truth_deposits(
    trajectories: list[Any], indices: list[int], scoring: _Scoring
) -> dict[str, Any]:
    """The ground truth's own deposit: {"mean": scalars over the trajectories, "trajectories":
    [figures and fronts of each]}."""
    deposits = [
        {"trajectory": index, **scoring.ground_truth(t)}
        for index, t in zip(indices, trajectories, strict=True)
    ]
    scalars = [k for k in DEPOSIT_FIGURES if k in deposits[0]]
    mean = {k: float(np.mean([d[k] for d in deposits])) for k in scalars}
    return {"mean": mean, "trajectories": deposits}
