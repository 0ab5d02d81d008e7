"""Evaluation of a trained run: one-step MSE over a split, and the metrics of its rollouts next
to two baselines on the same frames: constant velocity (every particle keeps its last velocity)
and static (every particle stays where the last input frame has it).

    one_step_errors(simulator, dataset)   position MSE of single steps from ground-truth inputs
    one_step_predictions(...)             those single steps themselves, window by window
    evaluate_rollouts(rollouts)           per-trajectory and mean rollout metrics (MSE over time
                                          and at horizons, OT, MMD), model and baselines, plus
                                          how far any particle left the box and the deposit:
                                          where the sand stops (runout, fronts), how high it
                                          piles and how densely it packs, against the truth's
    rest_test(simulator, trajectory, steps)
                                          the trajectory's last frame held still and rolled
                                          out: does the model keep a settled pile in place?
The metrics themselves are gns.metrics, gns.deposit and gns.baselines; this module only decides
what is compared with what.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch
from torch import Tensor

from gns.baselines import constant_velocity_rollout, static_rollout
from gns.batches import batch_obstacles, batch_tensors
from gns.data.trajectory import Trajectory
from gns.data.windows import pack_batches, trajectory_windows, window_keys
from gns.deposit import (
    DEPOSIT_CURVES,
    DEPOSIT_FIGURES,
    deposit,
    deposit_ratios,
    mean_neighbours,
    pile_floor,
    ratio_of,
)
from gns.metrics import DEFAULT_HORIZONS, evaluate_rollout
from gns.periodic import period_of
from gns.rollout import Rollout, RolloutDiverged, rollout
from gns.simulator import LearnedSimulator

# mean_neighbours lived here first: still importable from gns.evaluate.
__all__ = [
    "evaluate_rollouts",
    "generalisation",
    "mean_neighbours",
    "one_step_errors",
    "one_step_predictions",
    "outside_box",
    "rest_summary",
    "rest_test",
    "summary_table",
]

# What is scored: the learned model and the two baselines.
MODELS = ("model", "constant_velocity", "static")
# Per-frame curves, kept per trajectory and left out of the means.
CURVES = ("mse", *DEPOSIT_CURVES)


# Particles per forward pass of one_step_predictions, by device: windows are packed into one
# disjoint graph up to this many. A GPU runs one sand2d-taichi window (656 particles) in a few
# dozen kernel launches' time, so it takes many at once. A CPU is compute-bound already at one
# window (fp32 matmuls, LayerNorm, gathers: 50 ms of a 2-core Xeon's core, of which the Python
# and dispatch overhead is a few percent), and at 16k particles it ran ~20% slower per window,
# its node tables no longer in L2: there a few windows a pass.
ONE_STEP_PARTICLES = {"cpu": 2**11, "cuda": 2**16}


@torch.no_grad()
def one_step_predictions(
    simulator: LearnedSimulator,
    trajectories: Sequence[Any],
    pairs: Sequence[tuple[int, int]],
    device: torch.device | str = "cpu",
    *,
    max_particles: int | None = None,
) -> Iterator[tuple[Tensor, Tensor, Tensor, Tensor]]:
    """For each (trajectory index, start) of `pairs` (gns.data.windows.window_keys), in order:
    the input sequence (N, C + 1, D), the true next frame (N, D), the model's next frame (N, D)
    from those ground-truth inputs, and which particles are free, not kinematic (N,) bool. The
    simulator's mode is the caller's (eval for a prediction).

    The windows are stepped together, packed in order into batches of up to `max_particles`
    particles (default: the device's ONE_STEP_PARTICLES; gns.data.windows.pack_batches; the
    budget is raised to the largest window's size): a batch is one disjoint graph, so each
    window's prediction is the one it gets alone, to the float32 round-off of matmuls over
    more rows.
    """
    history = simulator.config.model.velocity_history + 1
    device = torch.device(device)
    if max_particles is None:
        max_particles = ONE_STEP_PARTICLES.get(device.type, ONE_STEP_PARTICLES["cuda"])
    windows = (next(trajectory_windows(trajectories[k], history, [start])) for k, start in pairs)
    largest = max((trajectories[k].n_particles for k, _ in pairs), default=1)
    for batch in pack_batches(windows, max(max_particles, largest)):
        t = batch_tensors(batch, device)
        sequence, truth = t["position_sequence"], t["next_position"]
        assert sequence is not None and truth is not None and t["particle_type"] is not None
        predicted = simulator.predict_positions(
            sequence,
            t["particle_type"],
            t["n_node"],
            t["context"],
            t["material_property"],
            obstacles=batch_obstacles(batch),
        )
        free = ~simulator.kinematic_mask(t["particle_type"])
        counts = batch.n_node.tolist()
        parts = (torch.split(x, counts) for x in (sequence, truth, predicted, free))
        yield from zip(*parts, strict=True)


@torch.no_grad()
def one_step_errors(
    simulator: LearnedSimulator,
    trajectories: Sequence[Any],
    *,
    max_windows: int | None = None,
    device: torch.device | str = "cpu",
) -> dict[str, float]:
    """Mean one-step position MSE (per particle and axis, non-kinematic particles) of the model,
    of the constant-velocity baseline and of the static one (the last input frame again) over
    the windows of `trajectories`: all of them, or `max_windows` spread evenly over the
    split."""
    history = simulator.config.model.velocity_history + 1
    pairs = window_keys(trajectories, history)
    if not pairs:
        raise ValueError(f"no trajectory has more than {history} frames: nothing to evaluate")
    if max_windows is not None and max_windows < len(pairs):
        pairs = [pairs[i] for i in np.linspace(0, len(pairs) - 1, max_windows).round().astype(int)]
    was_training = simulator.training
    simulator.eval()
    sums = {name: 0.0 for name in MODELS}
    try:
        for sequence, truth, predicted, free in one_step_predictions(
            simulator, trajectories, pairs, device
        ):
            # Differences as the model takes them: minimum images on periodic axes.
            last = sequence[:, -1]
            guesses = {
                "model": predicted,
                "constant_velocity": simulator.wrap(
                    last + simulator.displacement(last, sequence[:, -2])
                ),
                "static": last,
            }
            for name, guess in guesses.items():
                error = simulator.displacement(guess.double(), truth.double())[free].square().mean()
                sums[name] += float(error)
    finally:
        simulator.train(was_training)
    return {name: total / len(pairs) for name, total in sums.items()}


def outside_box(positions: np.ndarray, bounds: Sequence[Sequence[float]]) -> float:
    """How far (in position units) the farthest particle of (T, N, D) is outside the box;
    0 when every particle stays inside."""
    box = np.asarray(bounds, dtype=np.float64)
    below = box[:, 0] - positions
    above = positions - box[:, 1]
    return float(max(0.0, below.max(), above.max()))


def _deposit_entry(ours: dict[str, Any], truth: dict[str, Any]) -> dict[str, Any]:
    """A deposit and its ratios as plain JSON values (curves as lists)."""
    entry: dict[str, Any] = {k: float(v) for k, v in ours.items() if k not in DEPOSIT_CURVES}
    entry.update(deposit_ratios(ours, truth))
    entry.update({k: np.asarray(ours[k]).tolist() for k in DEPOSIT_CURVES if k in ours})
    return entry


def evaluate_rollouts(
    rollouts: Sequence[Rollout],
    *,
    horizons: Sequence[int | None] = DEFAULT_HORIZONS,
    distribution_every: int = 1,
    bandwidth: float = 0.1,
    workers: int | None = None,
) -> dict[str, Any]:
    """Rollout metrics of the model, of the constant-velocity baseline and of the static one.

    Each rollout needs its ground truth. Kinematic particles (metadata's
    kinematic_particle_types) are held to the ground truth in all three and left out of every
    metric. Returns {"trajectories": [per-rollout dicts], "mean": {name: {metric: value}}} for
    the names "model", "constant_velocity", "static" and "ground_truth". A per-rollout dict
    holds, per name, the scalar metrics and the per-frame curves:

      mse@h, mse@full, ot_mean, mmd_mean   errors against the ground truth (gns.metrics)
      finite, outside_box                  1 if every frame is finite; how far the farthest
                                           particle left the box (with bounds)
      runout, pile_height, pile_base, neighbours
                                           the last frame's deposit (gns.deposit.deposit): the
                                           1st-to-99th percentile extent of x, the 99th and the
                                           1st percentile of y above the floor (the box's lower
                                           y bound, else the truth's lowest y at frame 0), the
                                           mean neighbour count within the connectivity radius
      runout_ratio, height_ratio, density_ratio
                                           those three over the ground truth's (1 is right)
      density_ratio_max                    the largest over frames of the mean neighbour
                                           count over the truth's: the packing at its worst
      mse, front_x_p1, front_x_p99, neighbours_by_frame
                                           per-frame MSE, the 1st and 99th percentiles of x
                                           (the fronts) and the mean neighbour count of every
                                           predicted frame
      wall_corrections, wall_correction_max
                                           the model's, when its rollout enforced the walls:
                                           particle-steps put back on a wall, the largest move
    The "ground_truth" entry has the deposit figures (its ratios are 1), the fronts and
    outside_box, no errors. Means are over trajectories (of the per-trajectory ratios for the
    ratios), except outside_box and wall_correction_max, the worst case. A rollout that
    diverged has inf for mse@full, OT, MMD and the deposit figures; its file holds the ground
    truth only up to where it diverged, so that trajectory's baselines and truth are scored on
    those frames. workers:
    rollouts scored at once, in threads (default: one per CPU).
    """
    if not rollouts:
        raise ValueError("no rollouts to evaluate")
    if workers is not None and (isinstance(workers, bool) or workers < 1):
        raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
    # One rollout a thread: exact OT (lapx), cdist and numpy release the GIL, so the rollouts'
    # metrics run side by side on the cores (12 of eval's OT solves: 0.53 s on one thread, 0.26
    # s on two). Each rollout's figures are computed as alone; map keeps their order.
    threads = min(len(rollouts), workers or os.cpu_count() or 1)
    with ThreadPoolExecutor(threads) as pool:
        per_rollout = list(
            pool.map(lambda r: _evaluate_one(r, horizons, distribution_every, bandwidth), rollouts)
        )
    mean: dict[str, dict[str, float]] = {}
    for name in (*MODELS, "ground_truth"):
        entries = [entry[name] for entry in per_rollout if entry.get(name) is not None]
        keys = list(dict.fromkeys(key for e in entries for key in e if key not in CURVES))
        if not keys and name == "ground_truth":  # every rollout diverged at its first step
            continue
        mean[name] = {}
        for key in keys:
            # A diverged model rollout lacks the later horizons: they count as infinitely wrong.
            values = [e.get(key, np.inf) for e in entries]
            # The worst case, not the mean, is what "inside the box" must mean.
            mean[name][key] = float(np.max(values) if key in WORST_CASE else np.mean(values))
    return {"trajectories": per_rollout, "mean": mean}


# What a rollout with the walls enforced records of them (gns.rollout), kept in its figures.
WALL_CORRECTIONS = ("wall_corrections", "wall_correction_max")
# Figures whose summary over trajectories is the worst case, not the mean.
WORST_CASE = ("outside_box", "wall_correction_max")


def _evaluate_one(
    r: Rollout, horizons: Sequence[int | None], distribution_every: int, bandwidth: float
) -> dict[str, Any]:
    """Model, baseline and ground-truth figures of one rollout (see evaluate_rollouts)."""
    if r.ground_truth_rollout is None:
        raise ValueError(
            f"rollout of trajectory {r.metadata.get('trajectory')} has no ground truth"
        )
    diverged_at = r.metadata.get("diverged_at_step")
    entry: dict[str, Any] = {"trajectory": r.metadata.get("trajectory")}
    bounds = r.metadata.get("bounds")
    scene = {
        "radius": r.metadata.get("connectivity_radius"),
        "bounds": bounds,
        "periodic": r.metadata.get("periodic"),
    }
    if diverged_at is not None:
        entry["diverged_at_step"] = int(diverged_at)
    if r.num_steps == 0:  # diverged at its first step: nothing to compare, all infinitely wrong
        entry["model"] = dict.fromkeys(("mse@full", "ot_mean", "mmd_mean"), np.inf)
        entry["model"]["finite"] = 0.0
        entry.update(dict.fromkeys(("constant_velocity", "static", "ground_truth")))
        return entry
    truth = r.ground_truth_rollout
    kinematic = np.isin(r.particle_type, r.metadata.get("kinematic_particle_types", [3]))
    free = ~kinematic
    floor = pile_floor(bounds, r.initial_positions[0])
    period = period_of(bounds, scene["periodic"])
    # The ground truth's deposit, the reference of every ratio, computed once.
    truth_deposit = deposit(truth, free, floor, **scene)
    entry["ground_truth"] = _deposit_entry(truth_deposit, truth_deposit)
    if bounds is not None:
        entry["ground_truth"]["outside_box"] = outside_box(truth, bounds)
    held = {"kinematic_mask": kinematic, "ground_truth": truth}
    baselines = {
        "constant_velocity": constant_velocity_rollout(
            r.initial_positions, r.num_steps, **held, bounds=bounds, period=period
        ),
        "static": static_rollout(r.initial_positions, r.num_steps, **held),
    }
    for name, predicted in (("model", r.predicted_rollout), *baselines.items()):
        metrics = evaluate_rollout(
            predicted,
            truth,
            mask=free,
            horizons=horizons,
            distribution_every=distribution_every,
            bandwidth=bandwidth,
            nonfinite="inf",
            period=period,
        )
        scalars = {
            key: float(value)
            for key, value in metrics.items()
            if key.startswith("mse@") or key in ("ot_mean", "mmd_mean")
        }
        finite = bool(np.isfinite(predicted).all())
        figures = _deposit_entry(deposit(predicted, free, floor, **scene), truth_deposit)
        if name == "model" and diverged_at is not None:
            # The rollout stopped early: what lies beyond its last finite frame counts as
            # infinitely wrong, not as absent; it never reached the last frame's deposit.
            finite = False
            scalars.update(dict.fromkeys(("mse@full", "ot_mean", "mmd_mean"), np.inf))
            figures.update({k: np.inf for k in figures if k in DEPOSIT_FIGURES})
        scalars["finite"] = float(finite)
        if bounds is not None:
            scalars["outside_box"] = outside_box(predicted, bounds) if finite else np.inf
        if name == "model" and r.metadata.get("enforce_walls"):
            scalars.update({k: float(r.metadata[k]) for k in WALL_CORRECTIONS})
        entry[name] = {**scalars, **figures, "mse": metrics["mse"].tolist()}
    return entry


def rest_summary(results: Sequence[dict[str, float]], steps: int) -> dict[str, Any]:
    """The `rest_test` results of several trajectories, held still for `steps` steps:
    {"steps", "trajectories": the results, "mean": density_ratio's mean and, for how far
    particles went (max_displacement, outside_box, truth_speed), the worst pile's value}."""
    if not results:
        raise ValueError("no rest test results to summarise")
    worst = ("max_displacement", "outside_box", "truth_speed")
    return {
        "steps": int(steps),
        "trajectories": list(results),
        "mean": {
            key: float((np.max if key in worst else np.mean)([r[key] for r in results]))
            for key in results[0]
        },
    }


def rest_test(
    simulator: LearnedSimulator,
    trajectory: Trajectory,
    steps: int,
    *,
    device: torch.device | str = "cpu",
) -> dict[str, float]:
    """Holds the trajectory's last frame still (C + 1 identical frames, so every input velocity
    is zero) and rolls the model out `steps` steps from it, with the last frame's step context.

    Sand that the data leaves at rest should stay where it is; a model that loses volume packs
    it ever closer and sinks it into the floor. Returns, over non-kinematic particles:
    density_ratio, the mean neighbour count within the connectivity radius after the rollout
    over that of the held frame (1 when the pile keeps its packing; with no neighbours in the
    held frame, 1 if there are none after either, else inf); max_displacement, how far
    the farthest particle moved (inf if the rollout diverged); outside_box (with bounds); and
    truth_speed, the largest displacement of the data's own last step, which says how still
    the held frame really was.
    """
    steps = int(steps)
    if steps < 1:
        raise ValueError(f"rest_test needs at least 1 step, got {steps}")
    history = simulator.config.model.velocity_history + 1
    frames = history + steps
    held = trajectory.positions[-1]
    context = trajectory.step_context
    still = Trajectory(
        positions=np.repeat(held[None], frames, axis=0),
        particle_type=trajectory.particle_type,
        step_context=None if context is None else np.repeat(context[-1:], frames, axis=0),
        material_property=trajectory.material_property,
        key=trajectory.key,
        source=f"{trajectory.source} (last frame held still)",
    )
    free = ~simulator.scene.kinematic_mask(trajectory.particle_type)
    scene = simulator.scene
    result = {"truth_speed": np.nan}  # a one-frame trajectory has no last step
    if trajectory.num_frames > 1:
        last_step = trajectory.positions[-1, free] - trajectory.positions[-2, free]
        result["truth_speed"] = float(np.linalg.norm(last_step, axis=-1).max(initial=0.0))
    try:
        final = rollout(simulator, still, num_steps=steps, device=device).predicted_rollout[-1]
    except RolloutDiverged:
        result.update(density_ratio=np.inf, max_displacement=np.inf)
        if scene.bounds is not None:
            result["outside_box"] = np.inf
        return result
    before = mean_neighbours(held[free], scene.radius, scene.bounds, scene.periodic)
    after = mean_neighbours(final[free], scene.radius, scene.bounds, scene.periodic)
    moved = np.linalg.norm(final[free].astype(np.float64) - held[free], axis=-1)
    result["density_ratio"] = ratio_of(after, before)
    result["max_displacement"] = float(moved.max(initial=0.0))
    if scene.bounds is not None:
        result["outside_box"] = outside_box(final[None], scene.bounds)
    return result


def generalisation(
    report: dict[str, Any], rollouts: Sequence[Rollout], generator: dict[str, Any] | None
) -> dict[str, Any] | None:
    """Error against friction angle on data whose metadata holds a band of angles out of
    training (gns.mpm.presets' continuous; the paper's figure C.5): {"held_out": [lo, hi],
    "angle": per trajectory (degrees, from the global feature tan(angle)), "in_band": bool,
    and per method its "mse@full" per trajectory}. None for other data."""
    band = (generator or {}).get("held_out_friction_angle_deg")
    if band is None or any(r.step_context is None for r in rollouts):
        return None
    lo, hi = (float(v) for v in band)
    angles = [math.degrees(math.atan(float(r.step_context[0, 0]))) for r in rollouts]
    out: dict[str, Any] = {
        "held_out": [lo, hi],
        "angle": angles,
        "in_band": [lo < a < hi for a in angles],
    }
    for name in ("model", "constant_velocity"):
        # A rollout that diverged at its first step has no baseline entries: infinitely wrong.
        out[name] = [
            (entry.get(name) or {}).get("mse@full", math.inf) for entry in report["trajectories"]
        ]
    return out


# The columns of `gns eval`'s summary: evaluate_rollouts' names and their headings.
SUMMARY_COLUMNS = {
    "model": "model",
    "constant_velocity": "const. velocity",
    "static": "static",
    "ground_truth": "truth",
}


def summary_table(mean: dict[str, dict[str, float]]) -> str:
    """evaluate_rollouts' means as the text table `gns eval` prints: one line per figure, one
    column per name, and for the errors how many times the model's each baseline's is (above 1:
    the model is better)."""
    names = list(SUMMARY_COLUMNS)
    keys = list(dict.fromkeys(k for name in names for k in mean.get(name, {})))
    keys = [k for k in keys if k != "finite"] + ["finite"]
    headings = [f"{SUMMARY_COLUMNS[n]:>{max(12, len(SUMMARY_COLUMNS[n]))}}" for n in names]
    key_width = max(16, *map(len, keys))
    lines = [f"{'metric':<{key_width}} {' '.join(headings)} {'cv/model':>9} {'static/model':>12}"]
    for key in keys:
        values = [mean.get(name, {}).get(key) for name in names]
        cells = [
            f"{'' if v is None else f'{v:.4g}':>{len(h)}}"
            for v, h in zip(values, headings, strict=True)
        ]
        # Errors are compared as ratios; the other figures (the deposit, the box) are not.
        error = key.startswith("mse@") or key in ("ot_mean", "mmd_mean", "one_step_mse")
        model, ratios = values[0], []
        for baseline, width in ((values[1], 9), (values[2], 12)):
            ratio = ""
            if error and baseline is not None and model and math.isfinite(model):
                ratio = f"{baseline / model:.3g}"
            ratios.append(f"{ratio:>{width}}")
        lines.append(f"{key:<{key_width}} {' '.join(cells)} {' '.join(ratios)}")
    lines.append(
        "last frame: runout = 99th - 1st percentile of x, pile_height and pile_base = 99th and "
        "1st percentile\nof y above the floor, neighbours within the connectivity radius; "
        "*_ratio: over the truth's "
        "(1 is right); density_ratio_max:\nthe largest over frames; cv/model, static/model: "
        "the baseline's error over the model's (above 1: the\nmodel is better)"
    )
    return "\n".join(lines)
