"""`gns report`: rollout error against wall time per simulated frame, measured on this machine.

    report("runs/sand", "data/sand", split="test", checkpoints=["best", "latest"])

One row per method, each scored on the same frames of the same held-out trajectories:
  GNS / CConv         each checkpoint given, rolled out from the first C + 1 ground-truth frames
                      (the row is named after the checkpoint's model.kind, so GNS and CConv
                      checkpoints can be compared side by side);
                      its time split into graph building, features, model and integration
                      (gns.rollout times every step) and the device it ran on
  MPM                 the reference simulator (gns.mpm), re-run at the data's native settings
                      and at cheaper ones (a coarser grid, a larger CFL number, i.e. fewer
                      substeps). For datasets written by `gns generate`, whose metadata names
                      the preset, seed and draw of every trajectory: the scenes that made them.
                      For manifest folders (another simulator's data, e.g. sand2d-taichi), whose
                      manifest gives every trajectory's block, velocity and friction angle: the
                      runs start from the data's own frame-0 particles, so particle i is the
                      data's particle i, and even the native row differs from the data (two
                      simulators). For any other dataset these rows are left out and the report
                      says why
  constant velocity   every particle keeps its last velocity (gns.metrics)
  static              every particle stays where the last input frame has it (gns.metrics):
                      for sand that comes to rest, much harder to beat late in a rollout
Errors are gns.metrics' (MSE per frame, optimal transport W2^2, MMD^2 with bandwidth 0.1) over
the non-kinematic particles, at the horizons asked for: the mean over the first h predicted
frames, then over trajectories. OT and MMD cost O(N^2) or more per frame, so they are evaluated
on every k-th predicted frame only (k = `every`), and "@h" for them is the mean over those
evaluated frames among the first h. Time is wall-clock seconds per simulated frame, the mean
over every frame of every trajectory.

Frames are those the models step between: a model trained on frames k times farther apart than
the dataset's (its checkpoint records its spacing; gns.data.frame_stride) is rolled out on every
k-th frame of each trajectory from frame 0 (gns.data.at_frame_stride), and so is every other row
scored: the baselines extrapolate those frames, the MPM re-runs simulate the frames between and
are scored on the same ones, and every time per frame is per such frame (one step of the model,
k dt; the report's context states the stride). Data whose spacing does not divide the models'
step is refused before any work.

Where the sand stops (gns.metrics.deposit), from the last frame's non-kinematic particles:
runout (the 99th minus the 1st percentile of x), pile height (the 99th percentile of y above the
box's floor) and the mean neighbour count within the dataset's connectivity radius; the table
has each over the ground truth's (runout_ratio, height_ratio, density_ratio: per trajectory,
then the mean), table.json the values per trajectory, the truth's own, and the fronts (the 1st
and 99th percentile of x) of every frame. With rest_steps, every learned row also holds each
trajectory's last frame still and rolls out from it (gns.evaluate.rest_test).

A learned rollout that diverges (gns.rollout stops it) scores inf from there on: its row says
where (status, diverged_at_step), the figures mark its last finite point with an x, and the
animation and VTK files show it up to that frame. The report opens with a conclusion computed
from the table (`conclusion`).

Output folder (written under a temporary name beside it and renamed when complete, replacing an
earlier report there; nothing is written before every argument has been checked):
  report.md, report.html      the report, embedding the figures below
  table.md, table.csv, table.json
                              the table (CSV and JSON parse back to the same rows)
  error_vs_time.png           error at each horizon against ms per frame, one marker per row
  error_over_time.png         MSE per frame and OT at the evaluated frames, per row
  fronts.png                  the fronts of the first trajectory over time, per row and truth
  rollout_{split}_{i}.gif     ground truth and prediction side by side (and .mp4 with ffmpeg)
  vtk/                        ground_truth.pvd, prediction.pvd + one .vtp per frame (ParaView)
  rollouts/{checkpoint}/      the learned rollouts (gns.rollout's npz schema, for `gns eval`)
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import datetime
import html
import io
import json
import math
import os
import platform
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gns.config import MODEL_NAMES
from gns.data.atomic import write_bytes_atomic
from gns.data.stride import describe_frame_stride, frame_stride, spacing_text
from gns.machine import cpu_name
from gns.metrics import (
    DEPOSIT_CURVES,
    DEPOSIT_FIGURES,
    constant_velocity_rollout,
    deposit,
    deposit_ratios,
    evaluate_rollout,
    pile_floor,
    static_rollout,
)

__all__ = [
    "DEFAULT_EVERY",
    "DEFAULT_HORIZONS",
    "MpmVariant",
    "Row",
    "machine",
    "parse_horizons",
    "parse_mpm_variants",
    "report",
    "score",
    "table_columns",
]

DEFAULT_HORIZONS: tuple[int | None, ...] = (1, 10, 50, None)
# OT and MMD on every 10th predicted frame: exact OT takes 0.05 s per frame at 1000 particles
# when the prediction is close and ~1.7 s at 1400 particles when it is far off (this project's
# 2-core CPU), so a 155-frame rollout of a poor model costs ~25 s per row and trajectory.
DEFAULT_EVERY = 10
METRICS = ("mse", "ot", "mmd")
# The deposit's columns (gns.metrics.deposit_ratios): the last frame's over the truth's.
DEPOSIT_COLUMNS = ("runout_ratio", "height_ratio", "density_ratio")
TIMING_PARTS = ("graph", "features", "model", "integration")
# The baselines' rows (method names).
CONSTANT_VELOCITY, STATIC = "constant velocity", "static"


def _say(enabled: bool) -> Callable[[str], None]:
    """Progress lines on stderr, each with the seconds since the report started."""
    started = time.perf_counter()

    def say(message: str) -> None:
        if enabled:
            elapsed = time.perf_counter() - started
            sys.stderr.write(f"gns report [{elapsed:5.0f} s] {message}\n")
            sys.stderr.flush()

    return say


# ----------------------------------------------------------------------------------- arguments


def parse_horizons(values: Sequence[str | int | None]) -> tuple[int | None, ...]:
    """Horizons from the command line: positive integers (frames) or "full" (None)."""
    horizons: list[int | None] = []
    for value in values:
        if value is None or str(value).lower() == "full":
            horizons.append(None)
            continue
        try:
            h = int(value)
        except (TypeError, ValueError):
            h = 0
        if h < 1 or str(h) != str(value).strip():
            raise ValueError(f"a horizon must be a positive whole number or 'full', got {value!r}")
        horizons.append(h)
    if not horizons:
        raise ValueError("at least one horizon is needed")
    return tuple(dict.fromkeys(horizons))


@dataclass(frozen=True)
class MpmVariant:
    """Settings of the reference simulator that differ from the dataset's own: grid (cells
    per unit length) and cfl (the substep bound); None keeps the native value. A coarser grid
    keeps the particles where they are (same lattice spacing, so more particles per cell):
    otherwise particle i would not be particle i and the MSE would compare nothing."""

    grid: int | None = None
    cfl: float | None = None

    def apply(self, scene: Any) -> Any:
        grid = scene.grid if self.grid is None else self.grid
        per_cell = scene.particles_per_cell * (scene.grid / grid) ** 2
        cfl = scene.cfl if self.cfl is None else self.cfl
        return dataclasses.replace(scene, grid=grid, particles_per_cell=per_cell, cfl=cfl)

    @property
    def native(self) -> bool:
        return self.grid is None and self.cfl is None


def parse_mpm_variants(
    specs: Sequence[str], native_grid: int, native_cfl: float
) -> list[MpmVariant]:
    """MPM settings from the command line: "native", "grid=20", "cfl=0.8", "grid=20,cfl=0.8",
    "auto" (native; 0.6 and 0.5 of the grid; twice the CFL number; 0.6 of the grid with twice
    the CFL number) or "none" (no MPM rows)."""
    variants: list[MpmVariant] = []
    for spec in specs:
        text = spec.strip().lower()
        if text == "none":
            if len(specs) > 1:
                raise ValueError(f"MPM setting 'none' cannot be combined with others: {specs}")
            return []
        if text == "auto":
            # At half the grid the generated scenes lose particles through the walls (which
            # sit 0.1 from the domain's edge: two cells at grid 20): kept as the honest limit,
            # with 0.6 of the grid as the coarse setting that holds.
            coarse, half = max(2, round(0.6 * native_grid)), max(2, native_grid // 2)
            variants += [
                MpmVariant(),
                MpmVariant(grid=coarse),
                MpmVariant(grid=half),
                MpmVariant(cfl=2 * native_cfl),
                MpmVariant(grid=coarse, cfl=2 * native_cfl),
            ]
            continue
        if text == "native":
            variants.append(MpmVariant())
            continue
        settings: dict[str, Any] = {}
        for part in text.split(","):
            key, _, value = (x.strip() for x in part.partition("="))
            if key == "grid" and value.isdigit() and int(value) >= 2:
                settings["grid"] = int(value)
                continue
            try:
                number = float(value)
            except ValueError:
                number = math.nan
            if key == "cfl" and math.isfinite(number) and number > 0:
                settings["cfl"] = number
            else:
                raise ValueError(
                    f"MPM setting {spec!r}: expected 'native', 'auto', 'none' or comma-separated "
                    "grid=<whole number >= 2> and cfl=<positive number>"
                )
        variants.append(MpmVariant(**settings))
    return list(dict.fromkeys(variants))


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
    the last frame (gns.metrics.deposit and deposit_ratios): "runout", "pile_height" (with a
    floor), "neighbours" (with a radius), "runout_ratio", "height_ratio", "density_ratio" (over
    the truth's), and the fronts "front_x_p1", "front_x_p99" (S,). NaN in `predicted` (a
    diverged rollout, padded) scores inf, never a finite number."""
    m = evaluate_rollout(
        predicted,
        truth,
        mask=mask,
        horizons=horizons,
        distribution_every=every,
        nonfinite="inf",
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
        """The deposit of the trajectory's own frames (gns.metrics.deposit)."""
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


def table_columns(horizons: Sequence[int | None], steps: int) -> list[str]:
    """The table's columns; horizons longer than the rollout (steps frames) have none. The
    deposit's ratios are of the last frame, so of the full horizon."""
    keys = [
        f"{metric}@{'full' if h is None else h}"
        for metric in METRICS
        for h in horizons
        if h is None or h <= steps
    ]
    parts = [f"{part}_ms" for part in TIMING_PARTS]
    return [
        "method",
        "setting",
        "device",
        "ms_per_frame",
        *parts,
        *keys,
        *DEPOSIT_COLUMNS,
        "trajectories",
        "diverged_at_step",
        "status",
    ]


def _record(row: Row, columns: Sequence[str]) -> dict[str, Any]:
    """A row as plain values: numbers in ms or metric units, None where there is no finite
    number (the status says why)."""

    def finite(value: float | None, scale: float = 1.0) -> float | None:
        return None if value is None or not math.isfinite(value) else value * scale

    out: dict[str, Any] = {}
    for column in columns:
        if column in ("method", "setting", "device", "status"):
            out[column] = getattr(row, column)
        elif column == "trajectories":
            out[column] = row.trajectories
        elif column == "diverged_at_step":
            out[column] = row.diverged_at
        elif column == "ms_per_frame":
            out[column] = finite(row.seconds_per_frame, 1e3)
        elif column.endswith("_ms"):
            out[column] = finite(row.split.get(column.removesuffix("_ms")), 1e3)
        else:
            out[column] = finite(row.values.get(column))
    return out


# ----------------------------------------------------------------------------------- machine


def machine() -> dict[str, Any]:
    """What the timings were measured on."""
    import torch

    cores = os.cpu_count() or 1
    rayon = os.environ.get("RAYON_NUM_THREADS")
    info = {
        "cpu": cpu_name(),
        "logical_cpus": cores,
        "torch_threads": torch.get_num_threads(),
        # The Rust core (MPM, radius graphs) runs on rayon's global pool.
        "rust_threads": int(rayon) if rayon and rayon.isdigit() and int(rayon) > 0 else cores,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cuda": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
        # Other work on the machine slows every row; the timings mean little without it.
        "load_average": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }
    return info


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
    """Roll the simulator of the file `checkpoint` (trained_for: e.g. "step 4000") out on every
    trajectory (timed), score the rollouts, save them with their deposit (Rollout.metrics) and
    `recorded` (what they ran on: dataset, split, frame stride) in their metadata, and with
    rest_steps > 0 run the rest test on every trajectory. Returns the row and the predictions
    (S, N, D) per trajectory, NaN after a divergence."""
    from gns.evaluate import rest_summary, rest_test
    from gns.rollout import RolloutDiverged, rollout, rollout_path, save_rollout

    setting = f"{checkpoint.name} ({trained_for})" if trained_for else checkpoint.name
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
        result.metrics.update({k: scores[-1][k][: result.num_steps] for k in DEPOSIT_CURVES})
        save_rollout(rollout_path(rollouts_dir, split, index), result)
        predictions.append(predicted)
        seconds.append(np.stack([result.timings[part] for part in TIMING_PARTS]))
    timings = np.concatenate(seconds, axis=1)  # (parts, all steps of all trajectories)
    name = MODEL_NAMES[simulator.config.model.kind]
    row = Row(name, setting, _device_label(device, ran), short=f"{name} {setting}")
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
    """A baseline's row: `extrapolate` (gns.metrics' constant_velocity_rollout or
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
        constant_velocity_rollout,
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


def _dataset_name(data: Path, metadata: Any) -> str:
    generator = _generator(metadata)
    if generator is None:
        return data.name
    return f"{data.name} (gns generate preset {generator['preset']}, seed {generator['seed']})"


def _generator(metadata: Any) -> dict[str, Any] | None:
    entry = dict(metadata.extra).get("generator")
    return entry if isinstance(entry, dict) and "preset" in entry and "seed" in entry else None


@dataclass(frozen=True)
class _MpmRun:
    """How to re-run one trajectory: its scene, filled either with the scene's own lattice
    (seed: the lattice's jitter seed, as `gns generate` made it) or with `positions`, the
    data's frame 0 (margin: how far outside its block a point may lie, see gns.mpm.particles)."""

    scene: Any
    seed: int | None = None
    positions: np.ndarray | None = None
    margin: float = 0.0


@dataclass(frozen=True)
class _MpmPlan:
    """The MPM rows to make: the run of every trajectory and the settings to re-run them at,
    or no rows and the reason."""

    runs: list[_MpmRun]
    variants: list[MpmVariant]
    reason: str | None = None
    # Frames the simulator makes per frame of the table: their spacings' ratio (at a frame
    # stride, or on data converted to one, the table's frames are farther apart than its own).
    stride: int = 1
    # Whether gns.mpm made the data (gns generate): then the native row reproduces it exactly.
    # Otherwise (a manifest folder, another simulator's data) the runs start from the data's
    # particles, `made_by` names that simulator, and the native row is a contender.
    same_simulator: bool = True
    made_by: str = ""


def _mpm_plan(
    dataset: Any,
    split: str,
    trajectories: list[Any],
    indices: list[int],
    specs: Sequence[str],
    frame_dt: float,
) -> _MpmPlan:
    """Check the MPM settings and find the scenes to re-run, before any rollout: a bad --mpm
    must be refused at once, not after minutes of learned rollouts. `trajectories` are the
    dataset's `indices` of `split` (at the table's frames); frame_dt: the seconds between the
    frames every row predicts."""
    from gns import mpm

    manifest = dataset.layout == "manifest"
    if manifest:
        runs, reason = _manifest_runs(dataset.source, trajectories, indices)
    else:
        runs, reason = _generated_runs(dataset.metadata, split, trajectories, indices)
    # The settings are checked even when there is nothing to run (against the defaults).
    native = runs[0].scene if runs else mpm.MpmScene([])
    variants = parse_mpm_variants(specs, native.grid, native.cfl)
    if not variants:
        return _MpmPlan([], [])
    if reason is not None:
        return _MpmPlan([], [], reason)
    own_dt = native.frame_dt
    try:
        stride = frame_stride(frame_dt, own_dt)
    except ValueError:
        return _MpmPlan(
            [],
            [],
            f"MPM rows: the reference simulator's frames are {spacing_text(own_dt)} apart, "
            f"which does not divide the {spacing_text(frame_dt)} between the frames every row "
            "predicts",
        )
    if not manifest:
        return _MpmPlan(runs, variants, stride=stride)
    # "Taichi-Elements MLS-MPM (2D), Drucker-Prager sand": the simulator, not its material.
    made_by = str(dataset.source.manifest.get("simulator") or "another simulator")
    made_by = made_by.split(",")[0].strip()
    return _MpmPlan(runs, variants, stride=stride, same_simulator=False, made_by=made_by)


def _generated_runs(
    metadata: Any, split: str, trajectories: list[Any], indices: list[int]
) -> tuple[list[_MpmRun], str | None]:
    """The scenes and lattice seeds that made a `gns generate` dataset's trajectories, or why
    there are none: the metadata names no generator, or the preset no longer gives the data's
    initial particles."""
    from gns import mpm
    from gns.generate import preset_scene

    generator = _generator(metadata)
    if generator is None:
        return [], (
            "MPM rows: this dataset was not written by `gns generate` (its metadata.json has no "
            "generator entry naming preset, seed and draws) nor is it a manifest folder giving "
            "every trajectory's block, so the scenes that made it cannot be re-run"
        )
    draws = generator.get("draws", {}).get(split) or [0] * (max(indices) + 1)
    runs = []
    for index, trajectory in zip(indices, trajectories, strict=True):
        scene, _, lattice_seed = preset_scene(
            generator["preset"], int(generator["seed"]), split, index, int(draws[index])
        )
        runs.append(_MpmRun(scene, lattice_seed))
        start = mpm.particles(scene, lattice_seed)["positions"].astype(np.float32)
        if start.shape != trajectory.positions[0].shape or not np.allclose(
            start, trajectory.positions[0], rtol=0, atol=1e-6
        ):
            return runs, (
                f"MPM rows: preset {generator['preset']!r} (seed {generator['seed']}) no longer "
                f"gives the initial particles of {split} trajectory {index} "
                f"({start.shape[0]} particles vs {trajectory.n_particles}); this dataset was "
                "made by another version of the presets and cannot be re-run"
            )
    return runs, None


def _manifest_scene(manifest: Mapping[str, Any], entry: Mapping[str, Any]) -> Any:
    """The gns.mpm scene of one manifest entry: one block of sand with the entry's friction
    angle, `cube` [x, y, width, height] and `initial_velocity` [vx, vy], in the manifest's box
    with its wall friction, gravity, frame spacing, grid and material constants where it gives
    them (gns.mpm's defaults, those of sand2d-taichi, otherwise). KeyError, TypeError or
    ValueError when the entry lacks or mangles one."""
    from gns import mpm

    x, y, width, height = (float(v) for v in entry["cube"])
    vx, vy = (float(v) for v in entry["initial_velocity"])
    sand = mpm.Sand(friction_angle_deg=float(entry["friction_angle_deg"]))
    if "rho" in manifest:
        sand = dataclasses.replace(sand, density=float(manifest["rho"]))
    if "elastic_modulus" in manifest:
        sand = dataclasses.replace(sand, youngs_modulus=float(manifest["elastic_modulus"]))
    if "poisson_ratio" in manifest:
        sand = dataclasses.replace(sand, poisson_ratio=float(manifest["poisson_ratio"]))
    if not (width > 0 and height > 0):
        raise ValueError(f"cube {entry['cube']} has no area")
    scene = mpm.MpmScene([mpm.Block(sand, (x, y), (width, height), (vx, vy))])
    changes: dict[str, Any] = {}
    if "bounds" in manifest:
        (x0, x1), (y0, y1) = manifest["bounds"]
        changes["bounds"] = ((float(x0), float(x1)), (float(y0), float(y1)))
    if "wall_friction" in manifest:
        changes["wall_friction"] = float(manifest["wall_friction"])
    if "gravity" in manifest:
        gx, gy = manifest["gravity"]
        changes["gravity"] = (float(gx), float(gy))
    if "frame_dt_s" in manifest:
        changes["frame_dt"] = float(manifest["frame_dt_s"])
    if "grid" in manifest:
        grid = manifest["grid"]
        cells = {int(g) for g in grid} if isinstance(grid, list) else {int(grid)}
        if len(cells) != 1:
            raise ValueError(f"grid {grid}: gns.mpm's cells are square")
        changes["grid"] = cells.pop()
    return dataclasses.replace(scene, **changes)


def _manifest_runs(
    source: Any, trajectories: list[Any], indices: list[int]
) -> tuple[list[_MpmRun], str | None]:
    """For a manifest folder's trajectories (gns.data.manifest.ManifestSource, one split): the
    scene of each from its own manifest entry, started from the trajectory's frame 0, or why
    there are none (an entry without its block or velocity, a trajectory that is not its
    entry's file, points outside the block)."""
    from gns import mpm

    runs = []
    for index, trajectory in zip(indices, trajectories, strict=True):
        entry = source.entries[index]
        name = str(entry.get("file"))
        if Path(trajectory.source) != source.folder / name:
            return [], (
                f"MPM rows: trajectory {index} was read from {trajectory.source}, not from "
                f"{name}, the manifest entry it would be re-run from"
            )
        try:
            scene = _manifest_scene(source.manifest, entry)
        except KeyError as err:
            return [], (
                f"MPM rows: {source.manifest_path}'s entry for {name} has no {err} (the block "
                "`cube` [x, y, width, height], `initial_velocity` [vx, vy] and "
                "`friction_angle_deg` are needed to re-run it)"
            )
        except (TypeError, ValueError) as err:
            return [], f"MPM rows: {source.manifest_path}'s entry for {name} is unusable: {err}"
        # The data's frame 0 may be a step after the block was placed (sand2d-taichi's is:
        # thrown blocks have moved |v| dt, up to 2.5 mm); a grid cell is what MPM resolves.
        run = _MpmRun(scene, positions=trajectory.positions[0], margin=1.0 / scene.grid)
        try:
            mpm.particles(scene, positions=run.positions, margin=run.margin)
        except ValueError as err:
            return [], f"MPM rows: the frame 0 of {name} does not fill its block: {err}"
        runs.append(run)
    return runs, None


def _mpm_rows(
    plan: _MpmPlan,
    trajectories: list[Any],
    indices: list[int],
    scoring: _Scoring,
    say: Callable[[str], None],
) -> list[Row]:
    """The reference simulator's rows: each of the plan's settings on every trajectory."""
    from gns import mpm

    threads = machine()["rust_threads"]
    rows = []
    for variant in plan.variants:
        changed = [variant.apply(run.scene) for run in plan.runs]
        grid, cfl = changed[0].grid, changed[0].cfl
        native = " (native)" if variant.native else ""
        setting = f"grid {grid} (dx {1 / grid:.3g}), cfl {cfl:g}{native}"
        if not plan.same_simulator:
            setting += f", from the data's particles ({plan.made_by}'s)"
        device = f"cpu, {_count(threads, 'rust thread')}"
        short = f"MPM grid {grid}, cfl {cfl:g}{native}"
        row = Row("MPM", setting, device, short=short, role="mpm", native=variant.native)
        row.same_simulator = plan.same_simulator
        say(f"MPM {setting}")
        scores, seconds, substeps, failures = [], [], [], []
        for run, new, index, trajectory in zip(
            plan.runs, changed, indices, trajectories, strict=True
        ):
            if run.positions is None:
                start = mpm.particles(run.scene, run.seed)["positions"]
                moved = mpm.particles(new, run.seed)["positions"]
                if moved.shape != start.shape or not np.allclose(moved, start, rtol=0, atol=1e-9):
                    failures.append(
                        f"trajectory {index}: grid {new.grid} puts the particles elsewhere "
                        f"({len(moved)} vs {len(start)}), so MSE would compare different "
                        "particles"
                    )
                    continue
            k = plan.stride
            try:
                result = mpm.simulate(
                    new,
                    (trajectory.num_frames - 1) * k + 1,
                    seed=run.seed,
                    positions=run.positions,
                    margin=run.margin,
                )
            except ValueError as err:
                failures.append(f"trajectory {index}: {err}")
                continue
            say(f"  trajectory {index}: simulated; scoring")
            # Its every k-th frame is a frame of the table, and costs the k frames up to it.
            scores.append(scoring(result.positions[::k][scoring.history :], trajectory))
            seconds.append(result.seconds.reshape(-1, k).sum(axis=1))
            substeps.append(result.substeps.reshape(-1, k).sum(axis=1))
        if failures:
            row.status = "failed: " + "; ".join(failures)
        else:
            row.seconds_per_frame = float(np.concatenate(seconds).mean())
            row.setting += f", {np.concatenate(substeps).mean():.1f} substeps/frame"
            row.add_scores(scores, indices)
        rows.append(row)
    return rows


# ----------------------------------------------------------------------------------- writing


def _format(value: Any) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, float):
        if value == 0:
            return "0"
        return f"{value:.3g}"
    return str(value)


def _grid(header: Sequence[str], lines: Sequence[Sequence[str]]) -> str:
    """A markdown table of the cells (strings) under `header`."""
    text = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    text += ["| " + " | ".join(cell.replace("|", "/") for cell in line) + " |" for line in lines]
    return "\n".join(text) + "\n"


def _cell(value: float | None) -> str:
    """A figure in a table: 3 significant digits, "inf" (diverged) or "n/a" (not computed)."""
    if value is not None and math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return _format(value if value is None or math.isfinite(value) else None)


def _markdown_table(rows: Sequence[Row], columns: Sequence[str], frame: str = "frame") -> str:
    """The table for humans: the time split in one column, numbers to 3 figures; the times
    are per `frame` (_frame_name)."""
    fixed = {"method", "setting", "device", "ms_per_frame", "trajectories", "diverged_at_step"}
    fixed |= {"status", *(f"{p}_ms" for p in TIMING_PARTS)}
    figures = [c for c in columns if c not in fixed]
    per = "ms/frame" if frame == "frame" else f"ms per {frame}"
    header = ["method", "setting", "device", per, "graph / features / model / integr. ms"]
    header += [c.replace("@", " @").replace("_", " ") for c in figures] + ["status"]
    lines = []
    for row in rows:
        record = _record(row, columns)
        split = " / ".join(_format(record[f"{p}_ms"]) for p in TIMING_PARTS) if row.split else ""
        cells = [row.method, row.setting, row.device, _format(record["ms_per_frame"]), split]
        cells += [_cell(row.values.get(c)) for c in figures]
        lines.append([*cells, row.status])
    return _grid(header, lines)


def _rest_table(rows: Sequence[Row]) -> str:
    """The rest test of every learned row that ran it (Row.rest), as a markdown table."""
    header = ["method", "setting", "density ratio (mean)", "largest displacement (worst)"]
    header += ["outside box (worst)", "data's last step (worst)"]
    keys = ("density_ratio", "max_displacement", "outside_box", "truth_speed")
    lines = [
        [row.method, row.setting, *(_cell(row.rest["mean"].get(k)) for k in keys)]
        for row in rows
        if row.rest is not None
    ]
    return _grid(header, lines)


def _csv_text(records: Sequence[dict[str, Any]], columns: Sequence[str]) -> str:
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    for record in records:
        writer.writerow(
            {
                k: ("" if v is None else repr(v) if isinstance(v, float) else v)
                for k, v in record.items()
            }
        )
    return buffer.getvalue()


@dataclass
class ReportResult:
    """What `report` wrote: the folder, the rows, and the files by role."""

    out: Path
    rows: list[Row]
    files: dict[str, Path]
    left_out: list[str]


def report(
    run: str | os.PathLike[str],
    data: str | os.PathLike[str],
    *,
    split: str = "test",
    checkpoints: Sequence[str] = ("auto",),
    out: str | os.PathLike[str] | None = None,
    trajectories: int | None = None,
    horizons: Sequence[int | None] = DEFAULT_HORIZONS,
    every: int = DEFAULT_EVERY,
    mpm: Sequence[str] = ("auto",),
    animation_frames: int = 120,
    vtk_every: int | None = None,
    rest_steps: int = 0,
    device: str = "auto",
    progress: bool = True,
    command: str | None = None,
    notes: Sequence[str] = (),
) -> ReportResult:
    """Write the report folder (see the module docstring) for the run (folder or checkpoint
    file) on `split` of the dataset at `data`.

    checkpoints: "auto", "best", "latest" (of the run folder) or checkpoint paths; one row
    each. trajectories: the first N of the split (default all). horizons: frames (None: the
    full rollout). every: OT and MMD on every k-th predicted frame. mpm: MPM settings (see
    parse_mpm_variants). animation_frames: frames in the GIF (0: no animation). vtk_every: VTK
    frame stride (0: no VTK files; default: at most about 100 frames, as ASCII VTK takes ~30
    bytes per particle and frame). rest_steps: hold each trajectory's last frame still and roll
    every checkpoint out this many steps from it (gns.evaluate.rest_test; 0: no rest test).
    command, notes: shown in the report. out: default
    RUN/report_SPLIT; it must be missing, empty or an earlier report, which the new one replaces
    when it is complete (a failed report leaves `out` as it was).
    """

    from gns.checkpoints import load_checkpoint, simulator_from_checkpoint
    from gns.data import at_frame_stride, open_dataset
    from gns.device import resolve_device
    from gns.rollout import frame_stride_metadata

    # Every argument is checked before the first rollout (they take minutes), and nothing is
    # written until then either.
    started = time.perf_counter()
    say = _say(progress)
    info = machine()  # before the report's own work shows in the load average
    run, data = Path(run), Path(data)
    for name, value, low in (
        ("every", every, 1),
        ("animation_frames", animation_frames, 0),
        ("vtk_every", 0 if vtk_every is None else vtk_every, 0),
        ("rest_steps", rest_steps, 0),
    ):
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ValueError(f"{name} must be a whole number >= {low}, got {value!r}")
    horizons = parse_horizons(list(horizons))
    if not checkpoints:
        raise ValueError("at least one checkpoint is needed")
    out = (
        Path(out) if out is not None else (run if run.is_dir() else run.parent) / f"report_{split}"
    )
    _check_output(out)
    torch_device = resolve_device(device)
    dataset = open_dataset(data, split)
    if trajectories is not None and not (
        isinstance(trajectories, int)
        and not isinstance(trajectories, bool)
        and 1 <= trajectories <= len(dataset)
    ):
        raise ValueError(
            f"trajectories must be between 1 and {len(dataset)} (the {split} split's size), "
            f"got {trajectories!r}"
        )
    indices = list(range(trajectories or len(dataset)))
    chosen = list(dict.fromkeys(_checkpoint(run, which) for which in checkpoints))
    metadata = dataset.metadata
    # Each file read and CRC-checked once, here.
    states = [load_checkpoint(path) for path in chosen]
    history = states[0]["config"]["model"]["velocity_history"] + 1
    for path, state in zip(chosen, states, strict=True):
        if (reads := state["config"]["model"]["velocity_history"] + 1) != history:
            raise ValueError(
                f"{path} reads C + 1 = {reads} input frames but the first checkpoint reads "
                f"{history}; every row must predict the same frames, so report them separately"
            )
    simulators = [simulator_from_checkpoint(state, torch_device) for state in states]
    stride = _frame_stride(chosen, simulators, metadata)
    # Every row predicts the frames the models step between: every stride-th of the data's.
    items = [at_frame_stride(dataset[i], stride) for i in indices]
    frame_dt = metadata.dt * stride
    plan = _mpm_plan(dataset, split, items, indices, mpm, frame_dt)
    steps = min(t.num_frames for t in items) - history
    if steps < 1:
        at = f" at frame stride {stride}" if stride > 1 else ""
        raise ValueError(
            f"the {split} trajectories have {steps + history} frames{at}; a rollout needs more "
            f"than the model's {history} input frames"
        )
    if len({t.num_frames for t in items}) > 1:
        raise ValueError(
            f"the {split} trajectories differ in length ({sorted({t.num_frames for t in items})}"
            "); horizon means over them would mix different frames"
        )
    scoring = _Scoring(
        history,
        tuple(sorted(metadata.kinematic_particle_types)),
        horizons,
        every,
        metadata.bounds,
        metadata.default_connectivity_radius,
        tuple(metadata.periodic_boundary_conditions) or None,
    )

    with _output_folder(out) as folder:
        rows: list[Row] = []
        predictions: list[np.ndarray] = []
        stems = [
            p.stem if [q.stem for q in chosen].count(p.stem) == 1 else f"{k}_{p.stem}"
            for k, p in enumerate(chosen)
        ]
        recorded = {"dataset": str(data), "split": split}
        recorded.update(frame_stride_metadata(metadata.dt, stride))
        for path, state, simulator, stem in zip(chosen, states, simulators, stems, strict=True):
            row, predicted = _learned_row(
                path,
                simulator,
                _trained_for(state),
                items,
                indices,
                scoring,
                torch_device,
                folder / "rollouts" / stem,
                split,
                recorded,
                rest_steps,
                say,
            )
            rows.append(row)
            if not predictions:
                predictions = predicted
        left_out: list[str] = []
        if plan.reason:
            left_out.append(plan.reason)
        elif not plan.variants:
            left_out.append("MPM rows: none asked for (--mpm none)")
        else:
            say("MPM rows")
            rows += _mpm_rows(plan, items, indices, scoring, say)
            if plan.same_simulator:
                left_out.append(
                    "MPM with fewer particles: its particles would not be the data's, so MSE "
                    "(particle i against particle i) could not be computed; only coarser grids "
                    "and fewer substeps are compared"
                )
            else:
                left_out.append(
                    "MPM on its own lattice of the blocks: the MPM rows start from the data's "
                    f"particles instead (frame 0, made by {plan.made_by}), so that particle i "
                    "is the data's particle i; the simulator that made the data is not re-run, "
                    "and the cheaper settings change the grid and the substeps, never the "
                    "particles"
                )
        say("baselines: constant velocity, static")
        rows.append(_constant_velocity_row(items, indices, scoring))
        rows.append(_static_row(items, indices, scoring))
        truth = _truth_deposits(items, indices, scoring)
        columns = table_columns(horizons, steps)
        dropped = [h for h in horizons if h is not None and h > steps]
        if dropped:
            left_out.append(
                f"horizons {dropped}: longer than the {steps} predicted frames of these "
                "trajectories"
            )

        frame = _frame_name(frame_dt, stride)
        files = _write_tables(folder, rows, columns, frame)
        say("figures")
        files.update(_write_figures(folder, rows, horizons, steps, history, truth))
        first = items[0]
        files.update(
            _write_media(
                folder,
                first,
                indices[0],
                predictions[0],
                history,
                split,
                metadata.bounds,
                frame_dt,
                rows[0].short,
                animation_frames,
                vtk_every,
                left_out,
                say,
            )
        )
        context = {
            "command": command,
            "run": str(run),
            "data": str(data),
            "dataset": _dataset_name(data, metadata),
            "split": split,
            "checkpoints": [str(p) for p in chosen],
            "trajectories": indices,
            "particles": sorted({t.n_particles for t in items}),
            "frames": first.num_frames,
            "history": history,
            "horizons": list(horizons),
            "steps": steps,
            "every": every,
            # The seconds between the frames of the table, every frame_stride-th of the data's.
            "dt": frame_dt,
            "dataset_dt": metadata.dt,
            "frame_stride": stride,
            "mpm_frame_stride": plan.stride,
            # Where the MPM rows start: the scenes that made the data or the data's particles.
            "mpm_made_by": None if plan.same_simulator else plan.made_by,
            "floor": pile_floor(metadata.bounds, first.positions[0]),
            "radius": metadata.default_connectivity_radius,
            "rest_steps": rest_steps,
            "machine": info,
            "device": str(torch_device),
            "seconds": time.perf_counter() - started,
            "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "notes": list(notes),
            "left_out": left_out,
            "conclusion": conclusion(rows, columns, steps, truth["mean"], frame=frame),
        }
        payload = {
            "columns": columns,
            "rows": [_record(r, columns) for r in rows],
            "deposits": {
                "ground_truth": truth,
                "rows": [
                    {
                        "method": r.method,
                        "setting": r.setting,
                        "mean": {k: r.values[k] for k in DEPOSIT_FIGURES if k in r.values},
                        "trajectories": r.deposits,
                    }
                    for r in rows
                ],
            },
            "context": context,
        }
        if rest_steps:
            payload["rest"] = [
                {"method": r.method, "setting": r.setting, **r.rest}
                for r in rows
                if r.rest is not None
            ]
        _write_json(folder / "table.json", _json_values(payload))
        files["json"] = folder / "table.json"
        markdown = _markdown_report(rows, columns, files, context, folder)
        write_bytes_atomic(folder / "report.md", markdown.encode("utf-8"))
        write_bytes_atomic(
            folder / "report.html",
            _html_report(rows, columns, files, context, folder).encode("utf-8"),
        )
        files.update(markdown=folder / "report.md", html=folder / "report.html")
    say(f"wrote {out / 'report.md'} in {context['seconds']:.0f} s")
    files = {role: out / path.relative_to(folder) for role, path in files.items()}
    return ReportResult(out, rows, files, left_out)


def _frame_stride(checkpoints: Sequence[Path], simulators: Sequence[Any], metadata: Any) -> int:
    """The frame stride every checkpoint takes on the data (LearnedSimulator.frame_stride_for):
    one for all, as every row must predict the same frames. ValueError naming the checkpoint
    when the data's frame spacing does not divide a model's step, or when they differ."""
    strides = []
    for path, simulator in zip(checkpoints, simulators, strict=True):
        try:
            strides.append(simulator.frame_stride_for(metadata))
        except ValueError as err:
            raise ValueError(f"{path}: {err}") from None
    if len(set(strides)) > 1:
        each = ", ".join(f"{p} every {k}" for p, k in zip(checkpoints, strides, strict=True))
        raise ValueError(
            f"the checkpoints step over different frames of the data ({each}); every row must "
            "predict the same frames, so report them separately"
        )
    return strides[0]


def _frame_name(frame_dt: float, stride: int) -> str:
    """What the table's times are per: "frame" (of the data), or at a frame stride one step of
    the model, e.g. "7.5 ms step"."""
    return "frame" if stride == 1 else f"{spacing_text(frame_dt)} step"


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


def _json_values(value: Any) -> Any:
    """`value` as strict JSON values: arrays as lists, non-finite numbers as None (the figure
    does not exist: a rollout that diverged before it)."""
    if isinstance(value, dict):
        return {k: _json_values(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_json_values(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


# Files that only a report folder holds: an existing `out` with one of them may be replaced.
_REPORT_MARKERS = ("table.json", "report.md")


def _check_output(out: Path) -> None:
    """Refuse an `out` that is neither missing, empty nor an earlier report, before any work:
    the finished report replaces the whole folder."""
    if not out.exists():
        return
    if not out.is_dir():
        raise ValueError(f"{out} exists and is not a folder; choose another --out")
    if any(out.iterdir()) and not any((out / name).is_file() for name in _REPORT_MARKERS):
        raise ValueError(
            f"{out} exists, is not empty and is not a gns report folder (no "
            f"{' or '.join(_REPORT_MARKERS)}); choose another --out"
        )


@contextlib.contextmanager
def _output_folder(out: Path) -> Iterator[Path]:
    """A new temporary folder beside `out` to write the report into. On success it takes the
    place of `out` (and of an earlier report there); on failure it is removed, with any parent
    folders made for it, so a failed report leaves no empty or half-written folder behind."""
    made = [parent for parent in out.parents if not parent.exists()]
    out.parent.mkdir(parents=True, exist_ok=True)
    # Not tempfile.mkdtemp: its folders are private (0700), and this one becomes the report.
    while True:
        folder = out.parent / f".{out.name}.{uuid.uuid4().hex[:8]}.tmp"
        try:
            folder.mkdir()
            break
        except FileExistsError:
            continue
    try:
        yield folder
        if out.exists():
            old = folder.with_suffix(".old")
            os.replace(out, old)
            try:
                os.replace(folder, out)
            except BaseException:
                os.replace(old, out)
                raise
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(folder, out)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        for parent in made:  # innermost first; only if still empty
            with contextlib.suppress(OSError):
                parent.rmdir()
        raise


def _checkpoint(run: Path, which: str) -> Path:
    """A run's "auto" / "best" / "latest" checkpoint, or a checkpoint file's path."""
    from gns.checkpoints import choose_checkpoint

    path = choose_checkpoint(run, which) if which in ("auto", "best", "latest") else Path(which)
    if not path.is_file():
        raise ValueError(
            f"checkpoint {which!r}: {path} does not exist (expected auto, best, latest or a file)"
        )
    return path


def _write_json(path: Path, payload: Any) -> None:
    # allow_nan=False: strict JSON; non-finite numbers were made None in _record.
    write_bytes_atomic(
        path, (json.dumps(payload, indent=1, allow_nan=False) + "\n").encode("utf-8")
    )


def _write_tables(
    out: Path, rows: Sequence[Row], columns: Sequence[str], frame: str
) -> dict[str, Path]:
    records = [_record(row, columns) for row in rows]
    write_bytes_atomic(out / "table.csv", _csv_text(records, columns).encode("utf-8"))
    write_bytes_atomic(out / "table.md", _markdown_table(rows, columns, frame).encode("utf-8"))
    return {"csv": out / "table.csv", "table": out / "table.md"}


def _write_figures(
    out: Path,
    rows: Sequence[Row],
    horizons: Sequence[int | None],
    steps: int,
    history: int,
    truth: dict[str, Any],
) -> dict[str, Path]:
    from gns.plots import Series, error_over_time, error_vs_time, front_over_time

    shown = [str(h) if h is not None else "full" for h in horizons if h is None or h <= steps]
    series = [
        Series(
            r.short,
            r.seconds_per_frame,
            r.values,
            None if r.curve is None else (np.arange(len(r.curve)), r.curve),
            r.ot_curve,
            r.diverged_at,
            _fronts(r.deposits[0]) if r.deposits else None,
        )
        for r in rows
    ]
    error_vs_time(series, METRICS, shown, out / "error_vs_time.png", "error against run time")
    error_over_time(series, out / "error_over_time.png", first_frame=history)
    fronts = _fronts(truth["trajectories"][0])
    front_over_time(series, fronts, out / "fronts.png", first_frame=history)
    return {
        "error_vs_time": out / "error_vs_time.png",
        "error_over_time": out / "error_over_time.png",
        "fronts": out / "fronts.png",
    }


def _fronts(deposit: dict[str, Any]) -> np.ndarray:
    """(S, 2): a deposit's fronts (the 1st and the 99th percentile of x) side by side."""
    return np.stack([deposit[k] for k in DEPOSIT_CURVES], axis=1)


def _write_media(
    out: Path,
    trajectory: Any,
    index: int,
    predicted: np.ndarray,
    history: int,
    split: str,
    bounds: Any,
    dt: float,
    label: str,
    animation_frames: int,
    vtk_every: int | None,
    left_out: list[str],
    say: Callable[[str], None],
) -> dict[str, Path]:
    """The animation and VTK files of one trajectory and the first checkpoint's prediction
    (`label`: the row's, e.g. "GNS best.pt (step 2000)"), both up to the frame where the
    prediction diverged, if it did; in the box `bounds`, with frames `dt` seconds apart."""
    from gns.plots import animation, diverged_frame
    from gns.rollout import rollout_path
    from gns.vtk import write_series

    files: dict[str, Path] = {}
    truth = trajectory.positions
    whole = np.concatenate([truth[:history], predicted]).astype(np.float32)
    stop = diverged_frame(whole)
    if trajectory.dim not in (2, 3):
        left_out.append(f"animation and VTK: {trajectory.dim}D positions")
        return files
    if animation_frames:
        say("animation")
        gif = rollout_path(out, split, index, suffix=".gif")
        mp4 = gif.with_suffix(".mp4")
        projection = " (x-y projection)" if trajectory.dim == 3 else ""
        why_not = animation(
            truth,
            whole,
            trajectory.particle_type,
            gif,
            bounds=bounds,
            titles=(f"ground truth{projection}", f"{label}{projection}"),
            first_predicted=history,
            dt=dt,
            max_frames=animation_frames,
            mp4_path=mp4,
        )
        files["gif"] = gif
        if why_not is None:
            files["mp4"] = mp4
        else:
            left_out.append(f"MP4 animation: {why_not} (the GIF has the same frames)")
    else:
        left_out.append("animation: not asked for")
    if vtk_every is None:
        vtk_every = max(1, math.ceil(len(truth) / 100))
    if vtk_every:
        say(f"VTK files (every {vtk_every} frame{'s' * (vtk_every > 1)})")
        folder = out / "vtk"
        finite = len(whole) if stop is None else stop
        types = {"particle_type": trajectory.particle_type.astype(np.int32)}
        files["vtk_truth"] = write_series(
            folder, "ground_truth", truth, dt=dt, every=vtk_every, point_data=types
        )
        error = np.linalg.norm(whole[:finite] - truth[:finite], axis=-1).astype(np.float32)
        files["vtk_prediction"] = write_series(
            folder,
            "prediction",
            whole[:finite],
            dt=dt,
            every=vtk_every,
            point_data=types,
            frame_data={"error": error},
        )
        if stop is not None:
            left_out.append(
                f"VTK prediction after frame {stop - 1}: the prediction diverged at frame {stop}"
            )
    else:
        left_out.append("VTK files: not asked for")
    return files


# ---------------------------------------------------------------------------------- conclusion


def _times(ratio: float) -> str:
    return f"{ratio:.1f}x" if ratio < 9.95 else f"{ratio:,.0f}x"


def _ms(seconds: float) -> str:
    ms = seconds * 1e3
    return f"{ms:#.2g} ms" if ms < 10 else f"{ms:,.0f} ms"


def _mse_against(mse: float, other: float, name: str) -> str:
    """How an MSE compares with `other`, the MSE of `name`: "3.0x lower MSE than X"."""
    if mse == other:
        return f"the same MSE as {name}"
    direction = "lower" if mse < other else "higher"
    if min(mse, other) == 0:  # no ratio to an exact result
        return f"{direction} MSE than {name} ({_format(mse)} against {_format(other)})"
    return f"{_times(max(mse, other) / min(mse, other))} {direction} MSE than {name}"


def _speed_against(seconds: float, other: float, name: str) -> str:
    """How a time per frame compares with `other`, that of `name`: "3.1x faster than X"."""
    if seconds == other:
        return f"as fast as {name}"
    direction = "faster" if seconds < other else "slower"
    return f"{_times(max(seconds, other) / min(seconds, other))} {direction} than {name}"


def _horizon_phrase(key: str, steps: int) -> str:
    h = key.split("@", 1)[1]
    if h == "full":
        return f"the full {steps}-frame rollouts"
    return "the first predicted frame" if h == "1" else f"the first {h} predicted frames"


def _finite(row: Row, key: str) -> float | None:
    value = row.values.get(key)
    return value if value is not None and math.isfinite(value) else None


def _lowest(rows: Sequence[Row], key: str) -> Row | None:
    """The row of lowest finite value at `key` (the first of equals), or None."""
    scored = [r for r in rows if _finite(r, key) is not None]
    return min(scored, key=lambda r: r.values[key]) if scored else None


def _ratio_text(ratio: float) -> str:
    """A ratio to the truth to two figures: "0.43x", "1.6x", "12x"."""
    if ratio < 1:
        return f"{ratio:.2f}x"
    return f"{ratio:.1f}x" if ratio < 9.95 else _times(ratio)


def _deposit_sentence(
    best: Row, static: Row | None, truth: Mapping[str, float] | None
) -> str | None:
    """Where the best learned row's sand stops and how high it piles against the truth, and
    the static baseline's; None when the figures are not there. The widths and heights are
    means over trajectories; the ratios are the table's (per trajectory, then the mean), which
    the means need not divide to."""
    if truth is None or "runout" not in truth or _finite(best, "runout_ratio") is None:
        return None
    height = "pile_height" in truth and _finite(best, "height_ratio") is not None

    def size(row: Row, against: bool) -> str:
        """ "0.31 wide [against the truth's 0.72] and piles 0.08 high [against 0.05]"."""
        text = f"{_format(row.values['runout'])} wide"
        text += f" against the truth's {_format(truth['runout'])}" if against else ""
        if height and _finite(row, "height_ratio") is not None:
            text += f" and piles {_format(row.values['pile_height'])} high"
            text += f" against {_format(truth['pile_height'])}" if against else ""
        return text

    def ratios(row: Row) -> list[tuple[str, str]]:
        """(figure, "0.43x") for each finite ratio of the row."""
        named = {"runout": "runout_ratio", "height": "height_ratio", "density": "density_ratio"}
        values = [(name, _finite(row, key)) for name, key in named.items()]
        return [(name, _ratio_text(v)) for name, v in values if v is not None]

    ours = ratios(best)
    sentence = (
        f"Where the sand stops (the last frame, means over trajectories): {best.short}'s "
        f"deposit is {size(best, True)}; per trajectory its {ours[0][0]} is {ours[0][1]} the "
        "truth's"
        + "".join(f", its {name} {value}" for name, value in ours[1:])
        + " (the table's ratios)"
    )
    if static is not None and _finite(static, "runout_ratio") is not None:
        theirs = ", ".join(f"{name} {value}" for name, value in ratios(static))
        sentence += f"; the static baseline's is {size(static, False)} ({theirs})"
    return sentence + "."


def _rest_sentence(best: Row) -> str | None:
    """How the best learned row kept the piles held still, when the rest test ran."""
    if best.rest is None:
        return None
    figures, steps = best.rest["mean"], best.rest["steps"]
    held = f"Held still for {_count(steps, 'step')}, the last frames under {best.short}"
    moved = figures.get("max_displacement", math.inf)
    if not math.isfinite(moved):
        return f"{held} diverged (see the rest test)."
    sentence = f"{held} move by at most {_format(moved)}"
    if math.isfinite(speed := figures.get("truth_speed", math.nan)):
        sentence += f" (the data's own last step: at most {_format(speed)})"
    if math.isfinite(density := figures.get("density_ratio", math.nan)):
        sentence += f" and end {_ratio_text(density)} as densely packed as they started"
    return sentence + "."


def conclusion(
    rows: Sequence[Row],
    columns: Sequence[str],
    steps: int,
    truth: Mapping[str, float] | None = None,
    *,
    frame: str = "frame",
) -> list[str]:
    """The table in plain words, computed from it: how the best learned row compares with
    constant velocity (and the static baseline, when there is its row) over the longest horizon
    and at what cost against the reference simulator at its native settings, where its sand
    stops and how high it piles against `truth` (the ground truth's mean deposit, see
    _truth_deposits) and the static baseline's, how it kept a pile held still (when the rest
    test ran), which method has the lowest MSE at each horizon, how the learned model compares
    with the cheaper MPM settings, and which learned rows diverged. One sentence a list entry;
    true for any outcome (a learned model worse than the baseline, every learned row diverged,
    no MPM rows). Times are quoted per `frame`, what the rows' seconds_per_frame are per
    (at a frame stride, one step of the model: "7.5 ms step")."""
    keys = [c for c in columns if c.startswith("mse@")]
    learned = [r for r in rows if r.role == "learned"]
    baseline = next((r for r in rows if r.method == CONSTANT_VELOCITY), None)
    static = next((r for r in rows if r.method == STATIC and r.role == "baseline"), None)
    reference = next((r for r in rows if r.native), None)
    # The native MPM on its own data is the ground truth itself (error 0): not a contender.
    exact = reference is not None and reference.same_simulator
    cheaper = [r for r in rows if r.role == "mpm" and not r.native]
    if not keys or baseline is None:
        return []
    sentences = []
    key = keys[-1]  # the longest horizon: what a simulator is for
    horizon = _horizon_phrase(key, steps)
    best = _lowest(learned, key)
    if best is None:
        sentences.append(
            f"Over {horizon} no learned model has a finite MSE (every one diverged, see below); "
            f"constant velocity's is {_format(baseline.values.get(key))}."
        )
    else:
        sentence = (
            f"Over {horizon} {best.short} has "
            f"{_mse_against(best.values[key], baseline.values[key], 'constant velocity')} "
            f"({_format(best.values[key])} against {_format(baseline.values[key])})"
        )
        if static is not None and (held := _finite(static, key)) is not None:
            versus = _mse_against(best.values[key], held, "the static baseline")
            sentence += f" and {versus} ({_format(held)})"
        if best.seconds_per_frame is not None:
            sentence += f" at {_ms(best.seconds_per_frame)} per {frame}"
            if reference is not None and reference.seconds_per_frame is not None:
                sentence += ", " + _speed_against(
                    best.seconds_per_frame,
                    reference.seconds_per_frame,
                    "the reference simulator at its native settings",
                )
                sentence += f" ({_ms(reference.seconds_per_frame)})"
        if reference is None:
            sentence += "; the reference simulator was not run (see Left out)"
        elif reference.seconds_per_frame is None:
            sentence += "; the reference simulator failed at its native settings (see status)"
        sentences.append(sentence + ".")
        for extra in (_deposit_sentence(best, static, truth), _rest_sentence(best)):
            if extra is not None:
                sentences.append(extra)

    winners = []
    for k in keys:
        winner = _lowest([r for r in rows if not (r.native and r.same_simulator)], k)
        if winner is None:
            continue
        text = f"{_horizon_phrase(k, steps)}: {winner.short}"
        if winner.role == "learned":
            text += f", {_mse_against(winner.values[k], baseline.values[k], 'constant velocity')}"
        elif (runner_up := _lowest(learned, k)) is not None:
            text += f", {_mse_against(winner.values[k], runner_up.values[k], runner_up.short)}"
        else:
            text += " (every learned model had diverged)"
        winners.append(text)
    if winners:
        left = ", leaving out the MPM at its native settings (it is the ground truth)"
        sentences.append(f"Lowest MSE{left if exact else ''}: " + "; ".join(winners) + ".")

    if best is not None and cheaper:
        against = []
        for row in cheaper:
            value = _finite(row, key)
            if value is None or row.seconds_per_frame is None:
                against.append(f"{row.short} did not finish (see its status)")
                continue
            text = f"{_mse_against(best.values[key], value, row.short)} ({_format(value)}"
            text += f" at {_ms(row.seconds_per_frame)} per {frame}"
            if best.seconds_per_frame is not None:
                text += ", " + _speed_against(best.seconds_per_frame, row.seconds_per_frame, "it")
            against.append(text + ")")
        sentences.append(
            f"Against the reference simulator at cheaper settings over {horizon}, "
            f"{best.short} has " + "; ".join(against) + "."
        )

    diverged = [r for r in learned if r.diverged]
    for row in diverged:
        sentences.append(
            f"{row.short} diverged: {row.divergence()}; its later frames count as infinitely wrong."
        )
    if learned and not diverged:
        sentences.append("No learned rollout diverged.")
    return sentences


def _relative(path: Path, out: Path) -> str:
    return os.path.relpath(path, out)


def _count(n: int, noun: str, plural: str | None = None) -> str:
    return f"{n} {noun if n == 1 else plural or noun + 's'}"


def _context_lines(context: dict[str, Any]) -> list[str]:
    m = context["machine"]
    return [
        f"- Command: `{context['command']}`" if context["command"] else "- Command: (Python API)",
        f"- Date: {context['date']}; report made in {context['seconds']:.0f} s",
        f"- Machine: {m['cpu']}, {m['logical_cpus']} logical CPUs, {m['platform']}; "
        f"torch {m['torch']} with {_count(m['torch_threads'], 'thread')}, the Rust core (MPM) "
        f"with {_count(m['rust_threads'], 'thread')}"
        + (f"; GPU {m['cuda']}" if m["cuda"] else "")
        + (
            f"; load average {m['load_average']:.1f} when the report started (other work on "
            "the machine slows every row)"
            if m["load_average"] is not None
            else ""
        ),
        f"- Device of the learned model: {context['device']}",
        f"- Run: `{context['run']}`; checkpoints: "
        + ", ".join(f"`{c}`" for c in context["checkpoints"]),
        f"- Data: `{context['data']}`, split {context['split']}, trajectories "
        f"{context['trajectories']}, {', '.join(map(str, context['particles']))} particles, "
        f"{context['frames']} frames each (dt {context['dt']:g} s)",
        *_stride_lines(context),
    ]


def _stride_lines(context: dict[str, Any]) -> list[str]:
    """The frame stride, when the models step over more than one frame of the data."""
    stride = context["frame_stride"]
    if stride == 1:
        return []
    return [
        f"- Frame stride {stride}: {describe_frame_stride(context['dataset_dt'], stride)}, from "
        "frame 0 (as `gns convert --frame-stride` writes them). Every row predicts these "
        "frames; every figure, frame number and time per frame here is of them."
    ]


def _method_lines(context: dict[str, Any]) -> list[str]:
    h, s, k = context["history"], context["steps"], context["every"]
    stride, mpm_stride = context["frame_stride"], context["mpm_frame_stride"]
    made_by = context.get("mpm_made_by")
    if made_by is None:
        mpm_start = (
            "MPM rows are re-run from frame 0 with the scene and seed that made the data, so "
            "their error at a frame includes their own drift since frame 0 (the simulator's "
            "state holds more than positions and cannot be restarted from the data)."
        )
    else:
        mpm_start = (
            f"The data was made by another simulator ({made_by}): MPM rows run this project's "
            "(gns.mpm) from the data's own frame-0 particles, with each trajectory's material, "
            "block velocity and settings from its manifest, so their error at a frame is the two "
            "simulators' disagreement since frame 0 (not zero, even at the native settings)."
        )
    return [
        f"- Every row predicts frames {h} to {h + s - 1} ({s} frames) of each trajectory; the "
        f"learned model and the baselines start from the {h} ground-truth frames before them. "
        + mpm_start,
        "- MSE: squared position error, mean over the non-kinematic particles and the axes, "
        "then over the first h predicted frames (`@h`; `@full`: all), then over trajectories.",
        f"- OT (W2^2, exact assignment up to 2048 points) and MMD^2 (Gaussian kernel, "
        f"bandwidth 0.1): evaluated on one predicted frame in k = {k} only (frames 1, "
        f"{k + 1}, {2 * k + 1}, ... of the rollout), as they cost O(N^2) or more per frame; "
        "`@h` is the mean over the evaluated frames among the first h ("
        + ", ".join(
            f"@{'full' if h is None else h}: {len(range(0, s if h is None else min(h, s), k))}"
            for h in context["horizons"]
            if h is None or h <= s
        )
        + " frames).",
        "- Baselines: constant velocity (every particle keeps the velocity between the last two "
        f"input frames) and static (every particle stays where the last input frame, frame "
        f"{h - 1}, has it). For sand that comes to rest the static baseline is the harder one "
        "to beat late in a rollout.",
        "- Runout ratio, height ratio, density ratio: where the sand stops, from the last "
        f"frame (frame {h + s - 1}) of each rollout, over the non-kinematic particles, each "
        "over the ground truth's: per trajectory, then the mean over trajectories (1 is right; "
        "so the mean values the conclusion quotes need not divide to it exactly). Runout: the "
        "99th minus the 1st percentile of x, how wide the deposit lies (the 1% of particles "
        "farthest out on either side do not count). Height: the 99th percentile of y minus the "
        f"floor, the box's lower y bound {context['floor']:g}. Density: the mean number of "
        f"other particles within the connectivity radius R = {context['radius']:g}. "
        "Percentiles interpolate linearly between sorted values. table.json's `deposits` "
        "holds every row's and the ground truth's values per trajectory and the fronts (the "
        "1st and 99th percentile of x) of every frame, drawn for the first trajectory in "
        "fronts.png.",
        *_rest_lines(context),
        "- Time: wall-clock per simulated frame"
        + (f" (one step of the model, {spacing_text(context['dt'])})" if stride > 1 else "")
        + ", mean over every frame of every trajectory. "
        "Learned rows: graph building + features + model + integration (the split adds up to "
        "the total; one untimed warm-up rollout first). MPM: the whole frame (substeps, "
        "transfers)"
        + (
            f", i.e. the {mpm_stride} frames of its own it simulates per frame here, "
            f"{spacing_text(context['dt'] / mpm_stride)} apart"
            if mpm_stride > 1
            else ""
        )
        + ". Baselines: the numpy extrapolation.",
        "- A value of 0 is exact (e.g. the deterministic simulator reproducing its own data); "
        "`inf` means the rollout diverged before the end of that horizon; `n/a`: not computed "
        "(see status). A diverged row's status (and table.csv's diverged_at_step) gives the "
        f"rollout step it diverged at (step k predicts frame {h} + k); the figures mark its "
        "last finite point with an x.",
    ]


def _rest_lines(context: dict[str, Any]) -> list[str]:
    """What the rest test is, when it ran."""
    if not context["rest_steps"]:
        return []
    return [
        "- Rest test: each trajectory's last frame held still (the model's "
        f"{context['history']} input frames all equal to it, so every velocity is zero) and "
        f"rolled out {_count(context['rest_steps'], 'step')} by each learned model "
        "(gns.evaluate.rest_test): sand the data leaves at rest should stay where it is. "
        "Density ratio: the mean neighbour count within R after the steps over that of the "
        "held frame, the mean over trajectories; the largest displacement of any particle, how "
        "far any is outside the box and the data's own last step (how still the held frame "
        "really was): the worst trajectory's."
    ]


def _title(context: dict[str, Any]) -> str:
    return f"Error against run time: {context['dataset']}, {context['split']} split"


def _markdown_report(
    rows: Sequence[Row],
    columns: Sequence[str],
    files: dict[str, Path],
    context: dict[str, Any],
    out: Path,
) -> str:
    lines = [f"# {_title(context)}", ""]
    if context["conclusion"]:
        lines += ["**In short.** " + " ".join(context["conclusion"]), ""]
    lines += [
        *_context_lines(context),
        "",
        f"![error against run time]({_relative(files['error_vs_time'], out)})",
        "",
        _markdown_table(rows, columns, _frame_name(context["dt"], context["frame_stride"])),
        "## How to read it",
        "",
        *_method_lines(context),
        "",
        "## Error over time",
        "",
        f"![error over time]({_relative(files['error_over_time'], out)})",
        "",
        "## Where the sand stops",
        "",
        f"![fronts over time]({_relative(files['fronts'], out)})",
        "",
    ]
    if any(row.rest is not None for row in rows):
        lines += ["## Rest test", "", _rest_table(rows)]
    if "gif" in files:
        lines += [
            "## Rollout",
            "",
            f"![ground truth and prediction]({_relative(files['gif'], out)})",
            "",
        ]
        if "mp4" in files:
            lines += [f"[MP4]({_relative(files['mp4'], out)})", ""]
    if "vtk_truth" in files:
        lines += [
            "## ParaView",
            "",
            f"Open `{_relative(files['vtk_truth'], out)}` and "
            f"`{_relative(files['vtk_prediction'], out)}` (time series of VTK PolyData files, "
            "with `particle_type` and, for the prediction, `error`, the distance to the ground "
            "truth).",
            "",
        ]
    if context["notes"]:
        lines += ["## Notes", "", *[f"- {n}" for n in context["notes"]], ""]
    lines += ["## Left out", ""]
    lines += [f"- {item}" for item in context["left_out"]] or ["- nothing"]
    return "\n".join(lines) + "\n"


def _html_report(
    rows: Sequence[Row],
    columns: Sequence[str],
    files: dict[str, Path],
    context: dict[str, Any],
    out: Path,
) -> str:
    e = html.escape

    def items(lines: list[str]) -> str:
        return (
            "<ul>" + "".join(f"<li>{e(line.removeprefix('- '))}</li>" for line in lines) + "</ul>"
        )

    def table(markdown: str) -> str:
        text = markdown.splitlines()
        head = [c.strip() for c in text[0].strip("|").split("|")]
        body = [[c.strip() for c in line.strip("|").split("|")] for line in text[2:]]
        cells = "<tr>" + "".join(f"<th>{e(c)}</th>" for c in head) + "</tr>"
        for line in body:
            cells += "<tr>" + "".join(f"<td>{e(c)}</td>" for c in line) + "</tr>"
        return f"<table>{cells}</table>"

    images = "".join(
        f'<p><img src="{e(_relative(files[key], out))}" alt="{key}" style="max-width:100%"></p>'
        for key in ("error_over_time", "fronts", "gif")
        if key in files
    )
    if any(row.rest is not None for row in rows):
        images += "<h2>Rest test</h2>" + table(_rest_table(rows))
    return (
        "<!DOCTYPE html>\n<html><head><meta charset='utf-8'>"
        f"<title>gns report: {e(context['dataset'])}</title>"
        "<style>body{font-family:sans-serif;max-width:1200px;margin:auto}"
        "table{border-collapse:collapse;font-size:12px}td,th{border:1px solid #ccc;"
        "padding:3px 6px}</style></head><body>"
        f"<h1>{e(_title(context))}</h1>"
        + (
            f"<p><b>In short.</b> {e(' '.join(context['conclusion']))}</p>"
            if context["conclusion"]
            else ""
        )
        + items(_context_lines(context))
        + f'<p><img src="{e(_relative(files["error_vs_time"], out))}" alt="error against run time" '
        'style="max-width:100%"></p>'
        + table(_markdown_table(rows, columns, _frame_name(context["dt"], context["frame_stride"])))
        + "<h2>How to read it</h2>"
        + items(_method_lines(context))
        + images
        + (("<h2>Notes</h2>" + items(context["notes"])) if context["notes"] else "")
        + "<h2>Left out</h2>"
        + items(context["left_out"] or ["nothing"])
        + "</body></html>\n"
    )
