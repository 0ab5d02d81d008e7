"""What a particle model (2D or 3D) sees and does: reach, floor, landing, rest, fall, spread,
squeeze, collapse, runout (docs/probes.md).

    python scripts/probe.py reach MODEL [MODEL ...] [--untrained] [--variant KEY=VALUE ...]
    python scripts/probe.py floor MODEL [MODEL ...] [--shift 1.0]
    python scripts/probe.py landing MODEL DATA SPLIT [--trajectories 0 1 ...] [--bands 3]
        [--threshold 3]
    python scripts/probe.py rest MODEL [MODEL ...] --data DATA [--split valid]
    python scripts/probe.py fall MODEL [MODEL ...] --data DATA [--split test]
        [--trajectories 0 1 ...] [--tol 0.1] [--speeds 0.25 0.5 1] [--steps 1 2 4 8]
        [--heights 1 2 3 4 6 8 12 20] [--noise-draws K]
    python scripts/probe.py spread MODEL [MODEL ...] --data DATA [--split test] [--flowing 0.3]
        [--near-floor GAP [--start-speed 0.5]]
    python scripts/probe.py squeeze MODEL [MODEL ...] --data DATA [--split test] [--factor 0.9]
        [--random STD] [--every 10]
    python scripts/probe.py collapse MODEL [MODEL ...] [--heights 0.05 0.1 0.2 0.3]
    python scripts/probe.py runout MODEL [MODEL ...] [--angles 20 30 45] [--gap 0.019]

MODEL: a model name, folder or checkpoint (as `gns rollout --run`). The block of reach and
floor is a square (a cube in 3D) lattice (`--spacing`, `--size` wide; the defaults are
sand2d-taichi's block and particle spacing) of the scene's one free particle type, with
tan(--friction-angle) as the context where the model takes one.

- reach: the block at the top of a throw in the middle of the box (free fall, no wall near);
  the sensitivity of the 9 central particles' predictions to the node inputs of the
  particles k graph hops away, over hop 0's: per particle and for all of hop k together.
  --untrained adds the same architecture with fresh weights, and each --variant
  model.FIELD=VALUE or scene.FIELD=VALUE (e.g. model.layer_norm=false, scene.radius=0.03) an
  untrained one with that setting changed.
- floor: the block on the floor at rest (its lowest row half a spacing above it), and 0.5 R
  higher falling at --landing-speed m/s (the moment before a landing); the mean change of
  the predicted acceleration, in g, when the floor is moved --shift further down, by height
  above the floor in radii.
- landing: each trajectory rolled out from its first frames and predicted one step at a time
  from the truth's; the mean vertical acceleration (g, up positive) and neighbour count of
  the lowest, middle and highest third of the particles (by height in the first frame)
  around the landing (the first frame at which the lowest third decelerates by --threshold g).
  After each landing, and over all of them: the largest rollout / truth density of any third
  (how many landings stay within --density-limit), and each third's share of the truth's
  stop that the one-step predictions give (summed where the truth decelerates by more than
  --threshold g).
- rest: one step from each trajectory's last C + 1 frames (a settled pile), the predicted
  vertical acceleration (g, up positive) by height above the floor (below R, 1-3 R, 3-6 R,
  above 6 R): the truth's is about 0, and a model that pushes the pile down by a tenth of g
  sinks it 0.5 m in a second of rollout unless the floor holds it.
- fall: one step at a time from the truth's frames, the particles that fell within --tol g
  of g through the model's input frames (the top of a throw, a block dropped): the next
  acceleration over g of the truth and the model, by whether the model sees a wall (within
  its wall clip), speed at the last input frame (bins at --speeds m/s) and place in the sand
  (the bottom, inside or top: no particle in the 45-degree cone below or above within R).
  A second table takes those within the wall clip of the floor, faster than the lowest
  --speeds, by steps of travel to the floor (bins at --steps): the share the truth keeps
  falling at g, the model's acceleration there, and both for the rest (the landing).
  A third takes them by place, height above the floor (bins at --heights, radii) and speed:
  where the truth falls on at every speed, a model that brakes there has smoothed the
  landing over the heights above it.
  --noise-draws K adds, after the model's, its mean over K draws of its own training noise on
  the inputs: a model fitted to what training showed it reads the truth there (with
  noise.exact_last_position exactly; otherwise the correction fraction moves the target).
  The lattice block of free_fall_probe.py asks the same of a block the data may not have.
- spread: one step at a time from the truth's frames of each trajectory, the outward
  horizontal acceleration of the outer fifth of the particles (farthest in x from the mean),
  the truth's and the model's: summed up to the frame of their peak outward speed (the speed
  a landing or a collapse launches the front with, m/s), and averaged after it over the
  frames faster than --flowing m/s (how hard the front brakes, g). A model short of either
  stops short of the truth's runout. --near-floor GAP keeps only the trajectories whose block
  starts at most GAP above the floor, slower than --start-speed m/s (a short drop, then a
  collapse under its own weight), e.g. in the training data: `--split train`.
- squeeze: every --every steps of each trajectory, the truth's input frames shifted alike in
  every frame (velocities kept): the sand squeezed towards the floor (heights times --factor)
  or, with --random STD, each particle moved at random; the share of the shift the model
  undoes in one step (probes.shift_undone), by step with the truth's mean speed. Does a model
  restore the packing a rollout squeezes out of its sand (above 0), or keep it (0)?
- collapse: blocks --width wide and --heights high standing at rest on the floor, friction
  angle --friction-angle, run by the reference MPM (the sand-taichi preset's resolution and
  box); the launch of `spread` one step at a time from the MPM's frames. A block taller than
  its angle of repose allows collapses, the harder the taller; a model that holds it as a
  settled pile (negative launch) cannot reach the runout of a block that starts at rest.
- runout: a block (--width x --height) at rest with its lower edge --gap above the floor
  (default sand2d-taichi's sand_04), run by the reference MPM at each of --angles; each model
  rolled out from the MPM's first frames with that angle as its context, and its last frame's
  runout and pile height over the MPM's. The looser the sand the further it spreads (the MPM:
  0.49 m at 45 degrees, 0.78 m at 20); a model that stops every block alike misses it most
  where the sand is loosest.
"""

from __future__ import annotations

import argparse
import json
import math

import gns
import numpy as np
import torch
from gns import probes
from gns.data import at_frame_stride
from gns.rollout import RolloutDiverged, rollout


def block_in(simulator, args, where: str) -> np.ndarray:
    """The probe's block (probes.probe_block) in the model's box, or a clear exit."""
    try:
        return probes.probe_block(simulator.scene, args.size, args.spacing, where)
    except ValueError as err:
        raise SystemExit(str(err)) from err


def reach(args) -> None:
    for name in args.models:
        simulator = gns.load_simulator(name).eval()
        context, kind = probes.probe_inputs(simulator, args.friction_angle)
        block = block_in(simulator, args, "middle")
        history = probes.falling_history(simulator, block, 0.0)
        centre = block.mean(axis=0)
        targets = np.argsort(np.linalg.norm(block - centre, axis=1), kind="stable")[:9]
        versions = [("trained", simulator)]
        if args.untrained:
            versions.append(("untrained", probes.untrained_copy(simulator)))
        for variant in args.variant:
            versions.append((f"untrained, {variant}", untrained_variant(simulator, variant)))
        hops = " | ".join(str(k) for k in range(args.max_hop + 1))
        print(f"{name}: sensitivity by graph hop, over hop 0's ({len(block)} particles)")
        print(f"| network | per | {hops} |")
        print("|---" * (args.max_hop + 3) + "|")
        for label, model in versions:
            r = probes.reach_by_hop(model, history, kind, context, targets, args.max_hop)
            for per in ("mean", "total"):
                cells = " | ".join(f"{v:.2g}" for v in r[per])
                print(f"| {label} | {'particle' if per == 'mean' else 'hop'} | {cells} |")


def untrained_variant(simulator, variant: str):
    """The untrained architecture with one setting changed: "model.FIELD=VALUE" or
    "scene.FIELD=VALUE", VALUE in JSON (true, 20, 0.03)."""
    key, _, value = variant.partition("=")
    section, _, field = key.partition(".")
    if section not in ("model", "scene") or not field or not value:
        raise SystemExit(f"--variant {variant!r}: expected model.FIELD=VALUE or scene.FIELD=VALUE")
    try:
        parsed = json.loads(value)
    except json.JSONDecodeError as err:
        raise SystemExit(f"--variant {variant!r}: {value!r} is not a JSON value") from err
    return probes.untrained_copy(simulator, **{section: {field: parsed}})


def floor(args) -> None:
    for name in args.models:
        simulator = gns.load_simulator(name).eval()
        context, kind = probes.probe_inputs(simulator, args.friction_angle)
        scene, frames = simulator.scene, simulator.config.model.velocity_history + 1
        g = probes.g_step(simulator)
        block = block_in(simulator, args, "floor")
        floor_y = scene.bounds[1][0]
        rest = np.repeat(block[:, None], frames, axis=1)
        speed = args.landing_speed * scene.dt
        up = np.eye(scene.dim)[1]  # y is up
        falling = probes.block_history(block + 0.5 * scene.radius * up, frames, g, -speed)
        edges = np.arange(0.0, args.size / scene.radius + args.bin, args.bin)
        print(
            f"{name}: change of the predicted acceleration (g) when the floor moves {args.shift} "
            f"down, by height above the floor in R (walls seen from {scene.wall_clip:g} R)"
        )
        ranges = [f"{a:g}-{b:g}" for a, b in zip(edges[:-1], edges[1:], strict=True)]
        print("| block | " + " | ".join(ranges) + " |")
        print("|---" * len(edges) + "|")
        for label, history in (("at rest", rest), ("landing", falling)):
            change = probes.floor_shift(simulator, history, kind, context, args.shift)
            height = (history[:, -1, 1] - floor_y) / scene.radius
            where = np.digitize(height, edges) - 1
            cells = [change[where == b].mean() for b in range(len(edges) - 1)]
            print(f"| {label} | " + " | ".join(f"{c:.2f}" for c in cells) + " |")


def landing(args) -> None:
    simulator = gns.load_simulator(args.model).eval()
    dataset = gns.data.open_dataset(args.data, args.split)
    stride = simulator.frame_stride_for(dataset.metadata)
    g, radius = probes.g_step(simulator), simulator.scene.radius
    chosen = args.trajectories if args.trajectories else range(len(dataset))
    ratios, stopping_truth, stopping_one_step = [], 0.0, 0.0
    for index in chosen:
        trajectory = at_frame_stride(dataset[index], stride)
        truth = trajectory.positions.astype(np.float64)
        free = ~simulator.scene.kinematic_mask(trajectory.particle_type)
        rolled = np.full_like(truth, np.nan)
        try:
            done = rollout(simulator, trajectory)
        except RolloutDiverged as err:  # keep the good steps; the rest stays NaN
            print(f"({args.model} on trajectory {index}: {err})")
            done = err.rollout
        good = done.predicted_trajectory
        rolled[: len(good)] = good
        one_step = one_step_frames(simulator, trajectory)
        r = probes.landing_timeline(
            truth[:, free],
            rolled[:, free],
            one_step[:, free],
            radius,
            g,
            bands=args.bands,
            threshold=args.threshold,
        )
        print(f"{args.model} on {args.split} trajectory {index}: ", end="")
        if r["landing"] is None:
            print(f"no landing (the lowest band never decelerates by {args.threshold:g} g)")
            continue
        print(
            f"landing at step {r['landing']} (lowest band first up by {args.threshold:g} g); "
            "bands low to high"
        )
        bands = range(args.bands)
        heads = [f"a{b} truth / 1-step / rollout" for b in bands]
        heads += [f"density{b} truth / rollout" for b in bands]
        print("| step | " + " | ".join(heads) + " |")
        print("|---" * (2 * args.bands + 1) + "|")
        for row, t in enumerate(r["frames"]):
            a = [
                f"{r['truth'][row, b]:+.1f} / {r['one_step'][row, b]:+.1f} / "
                f"{r['rollout'][row, b]:+.1f}"
                for b in bands
            ]
            d = [
                f"{r['density_truth'][row, b]:.1f} / {r['density_rollout'][row, b]:.1f}"
                for b in bands
            ]
            print(f"| {t - r['landing']:+d} | " + " | ".join(a + d) + " |")
        ratios.append(r["density_ratio"])
        stopping_truth = stopping_truth + r["stopping_truth"]
        stopping_one_step = stopping_one_step + r["stopping_one_step"]
        print(
            f"largest density over the truth's: {r['density_ratio']:.2f}; one step from the "
            f"truth, share of its stop (over {args.threshold:g} g), bands low to high: "
            + _shares(r["stopping_one_step"], r["stopping_truth"])
        )
    if ratios:
        within = sum(ratio <= args.density_limit for ratio in ratios)
        print(
            f"{args.model}: {within} of {len(ratios)} landings within {args.density_limit:g} of "
            f"the truth's density (largest {np.max(ratios):.2f}); share of the truth's stop one "
            "step from it, bands low to high: " + _shares(stopping_one_step, stopping_truth)
        )


def _shares(model: np.ndarray, truth: np.ndarray) -> str:
    """Each band's model / truth, or "-" where the truth's band never stops."""
    return " / ".join(f"{m / t:.2f}" if t > 0 else "-" for m, t in zip(model, truth, strict=True))


@torch.no_grad()
def rest(args) -> None:
    dataset = gns.data.open_dataset(args.data, args.split)
    edges = (1.0, 3.0, 6.0)
    names = ["below R", "1-3 R", "3-6 R", "above 6 R"]
    print(f"one step from the last frames of each {args.split} trajectory; acceleration in g, up")
    print("positive: mean over trajectories (their range)")
    print("| model | " + " | ".join(names) + " | truth, largest |")
    print("|---" * (len(names) + 2) + "|")
    for name in args.models:
        simulator = gns.load_simulator(name).eval()
        if not simulator.scene.walls or simulator.scene.bounds is None:
            raise ValueError(f"{name} has no walls: there is no floor to rest on")
        stride = simulator.frame_stride_for(dataset.metadata)
        history = simulator.config.model.velocity_history + 1
        floor = simulator.scene.bounds[1][0]
        ours, truth = [], []
        for trajectory in dataset:
            trajectory = at_frame_stride(trajectory, stride)
            frames = trajectory.positions[-history:].transpose(1, 0, 2).copy()
            context = trajectory.step_context
            predicted = simulator.predict_positions(
                torch.from_numpy(frames),
                torch.tensor(trajectory.particle_type),
                context=None if context is None else torch.from_numpy(context[-1:]).float(),
            )
            free = ~simulator.scene.kinematic_mask(trajectory.particle_type)
            r = probes.rest_by_height(
                frames[free],
                predicted.double().numpy()[free],
                floor,
                simulator.scene.radius,
                probes.g_step(simulator),
                edges,
            )
            ours.append(r["acceleration"])
            truth.append(r["truth"])
        a, t = np.array(ours), np.array(truth)
        cells = [
            f"{np.nanmean(a[:, b]):+.3f} ({np.nanmin(a[:, b]):+.2f} to {np.nanmax(a[:, b]):+.2f})"
            for b in range(a.shape[1])
        ]
        print(f"| {name} | " + " | ".join(cells) + f" | {np.nanmax(np.abs(t)):.3f} |")


def bin_labels(edges: np.ndarray) -> list[str]:
    """'under a', 'a-b', ..., 'over z' for increasing bin edges a ... z."""
    labels = [f"under {edges[0]:g}"]
    labels += [f"{a:g}-{b:g}" for a, b in zip(edges[:-1], edges[1:], strict=True)]
    return labels + [f"over {edges[-1]:g}"]


def increasing(values: list[float], option: str) -> np.ndarray:
    edges = np.asarray(values, dtype=np.float64)
    if not (np.all(edges > 0) and np.all(np.diff(edges) > 0)):
        raise ValueError(f"{option} must be positive and increasing, got {values}")
    return edges


def fall(args) -> None:
    dataset = gns.data.open_dataset(args.data, args.split)
    edges = increasing(args.speeds, "--speeds")
    steps_edges = increasing(args.steps, "--steps")
    height_edges = increasing(args.heights, "--heights")
    if args.noise_draws < 0:
        raise ValueError(f"--noise-draws must be >= 0, got {args.noise_draws}")
    places = (("bottom", -1), ("inside", 0), ("top", 1))
    results = {}
    for name in args.models:
        simulator = gns.load_simulator(name).eval()
        scene = simulator.scene
        if not scene.walls or scene.bounds is None:
            raise ValueError(f"{name} has no walls to tell seen from unseen")
        stride = simulator.frame_stride_for(dataset.metadata)
        history = simulator.config.model.velocity_history + 1
        g = probes.g_step(simulator)
        # A periodic axis has no wall to see: its bounds are not walls.
        bounds = np.asarray(scene.bounds, dtype=np.float64)
        bounds[[a for a in range(scene.dim) if a not in scene.wall_axes]] = (-np.inf, np.inf)
        parts = []
        for index in args.trajectories if args.trajectories else range(len(dataset)):
            trajectory = at_frame_stride(dataset[index], stride)
            free = ~scene.kinematic_mask(trajectory.particle_type)
            truth = trajectory.positions[:, free]
            frames = probes.falling_frames(truth, g, history, args.tol)
            common = (g, history, bounds, scene.radius, args.tol)
            predicted = one_step_frames(simulator, trajectory, frames)[:, free]
            part = probes.falling_in_data(truth, predicted, *common)
            if args.noise_draws:
                shaken = noisy_one_step_frames(simulator, trajectory, frames, args.noise_draws)
                part["noisy"] = probes.falling_in_data(truth, shaken[:, free], *common)["model"]
            parts.append(part)
        r = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
        results[name] = (r, scene.wall_clip * scene.radius, scene.dt, scene.radius)

    noisy = args.noise_draws > 0
    keys = ("truth", "model", "noisy") if noisy else ("truth", "model")  # the cells' figures
    under_noise = (
        f"; after the model's, its mean over {args.noise_draws} draws of its training noise"
        if noisy
        else ""
    )
    print(
        f"one step from the truth's frames of each {args.split} trajectory: the particles that "
        f"fell within {args.tol} g of g through the model's input frames; their next "
        "acceleration over g (falling on: 1), the truth / the model (samples), by the walls "
        "the model sees, speed at the last input frame (m/s, down) and place in the sand"
        + under_noise
    )
    print("| model | walls | speed | bottom | inside | top |")
    print("|---|---|---|---|---|---|")
    for name, (r, clip, dt, _) in results.items():
        seen = r["wall"] < clip
        speed = np.digitize(r["speed"] / dt, edges)
        for walls, mask in (("seen", seen), ("none", ~seen)):
            for b, label in enumerate(bin_labels(edges)):
                cells = []
                for _, place in places:
                    k = mask & (speed == b) & (r["surface"] == place)
                    if not k.any():
                        cells.append("-")
                        continue
                    means = " / ".join(f"{r[key][k].mean():.2f}" for key in keys)
                    cells.append(f"{means} ({k.sum()})")
                print(f"| {name} | {walls} | {label} | " + " | ".join(cells) + " |")

    print()
    print(
        "the same particles within the wall clip of the floor and faster than "
        f"{edges[0]:g} m/s, by steps of travel to the floor at their last input speed "
        f"(height / speed): the share the truth keeps falling (within {args.tol} g of g), the "
        "model's acceleration over g there, and the truth's / the model's for the rest"
        + under_noise
    )
    print("| model | steps to floor | place | samples | truth falls on | model there | the rest |")
    print("|---|---|---|---|---|---|---|")
    labels, place_names = bin_labels(steps_edges), {p: n for n, p in places}
    number = lambda x: "-" if math.isnan(x) else f"{x:.2f}"  # noqa: E731
    for name, (r, clip, dt, _) in results.items():
        slowest = edges[0] * dt
        rows = probes.approach_to_floor(r, clip, slowest, steps_edges, args.tol)
        under = [None] * len(rows)
        if noisy:
            r_noisy = {**r, "model": r["noisy"]}
            under = probes.approach_to_floor(r_noisy, clip, slowest, steps_edges, args.tol)
        for row, other in zip(rows, under, strict=True):
            shown = [row] if other is None else [row, other]
            there = " / ".join(number(x["model_kept"]) for x in shown)
            rest = " / ".join(
                number(x) for x in [row["truth_rest"], *(x["model_rest"] for x in shown)]
            )
            if math.isnan(row["truth_rest"]):
                rest = "-"
            print(
                f"| {name} | {labels[row['bin']]} | {place_names[row['place']]} | "
                f"{row['samples']} | {row['kept']:.2f} | {there} | {rest} |"
            )

    print()
    print(
        "the same particles by height above the floor (radii) and speed at the last input "
        "frame (m/s, down): the share the truth keeps falling, the truth's / the model's "
        "acceleration over g" + (", the model's under its noise" if noisy else "") + " (samples)"
    )
    speed_labels, height_labels = bin_labels(edges), bin_labels(height_edges)
    print("| model | place | height | " + " | ".join(speed_labels) + " |")
    print("|---|---|---|" + "---|" * len(speed_labels))
    for name, (r, _, dt, radius) in results.items():
        scaled = {**r, "floor": r["floor"] / radius}
        for place_name, place in places:
            rows = probes.approach_by_height(scaled, place, height_edges, edges * dt, args.tol)
            if noisy:
                noisy_rows = probes.approach_by_height(
                    {**scaled, "model": r["noisy"]}, place, height_edges, edges * dt, args.tol
                )
                for row, other in zip(rows, noisy_rows, strict=True):
                    row["noisy"] = other["model"]
            cells = {(row["height"], row["speed"]): row for row in rows}
            for h, label in enumerate(height_labels):
                if not any((h, v) in cells for v in range(len(speed_labels))):
                    continue
                shown = []
                for v in range(len(speed_labels)):
                    row = cells.get((h, v))
                    if row is None:
                        shown.append("-")
                        continue
                    means = " / ".join(f"{row[key]:+.2f}" for key in keys)
                    shown.append(f"{row['kept']:.2f} / {means} ({row['samples']})")
                print(f"| {name} | {place_name} | {label} | " + " | ".join(shown) + " |")


def spread(args) -> None:
    dataset = gns.data.open_dataset(args.data, args.split)
    print(
        f"one step at a time from the truth's frames of each {args.split} trajectory, the outer "
        "fifth's outward speed gained up to its peak (the launch, m/s) and its mean outward "
        f"acceleration after the peak while faster than {args.flowing} m/s (the braking, g)"
    )
    print(
        "| model | trajectory | peak speed (m/s, step) | launch truth / one step (ratio) "
        "| braking truth / one step |"
    )
    print("|---|---|---|---|---|")
    for name in args.models:
        simulator = gns.load_simulator(name).eval()
        stride = simulator.frame_stride_for(dataset.metadata)
        dt = simulator.scene.dt
        to_speed = probes.GRAVITY * dt  # g steps -> m/s
        launches, brakings = [], []
        for index, trajectory in enumerate(dataset):
            trajectory = at_frame_stride(trajectory, stride)
            if args.near_floor is not None and not near_floor(simulator, trajectory, args):
                continue
            r = front_launch(simulator, trajectory, args.flowing * dt)
            launch = np.array([r["launch_truth"], r["launch_one_step"]]) * to_speed
            braking = np.array([r["braking_truth"], r["braking_one_step"]])
            launches.append(launch)
            brakings.append(braking)
            print(
                f"| {name} | {index} | {r['peak_speed'] / dt:.2f} ({r['peak']}) | "
                f"{launch[0]:+.2f} / {launch[1]:+.2f} ({launch[1] / launch[0]:.2f}) | "
                f"{braking[0]:+.2f} / {braking[1]:+.2f} |"
            )
        if not launches:
            raise ValueError(
                f"no {args.split} trajectory starts within {args.near_floor} of the floor "
                f"slower than {args.start_speed} m/s"
            )
        total, mean = np.sum(launches, axis=0), np.nanmean(brakings, axis=0)
        print(
            f"| {name} | all (sum; mean) | | {total[0]:+.2f} / {total[1]:+.2f} "
            f"({total[1] / total[0]:.2f}) | {mean[0]:+.2f} / {mean[1]:+.2f} |"
        )


def squeeze(args) -> None:
    if args.every < 1:
        raise ValueError(f"--every must be at least 1 step, got {args.every}")
    if args.random is not None and not (math.isfinite(args.random) and args.random > 0):
        raise ValueError(f"--random must be a finite std > 0, got {args.random}")
    dataset = gns.data.open_dataset(args.data, args.split)
    what = (
        f"a random shift of std {args.random:g} per particle and axis (seeded)"
        if args.random
        else f"heights above the floor times {args.factor:g}"
    )
    print(
        f"every {args.every} steps of each {args.split} trajectory, the truth's input frames "
        f"shifted alike ({what}; velocities kept): the share of the shift the model undoes in "
        "one step (1: puts the sand back; 0: keeps it where it was put); mean over "
        "trajectories (their range), by the step's truth speed"
    )
    print("| model | step | speed (m/s) | undone |")
    print("|---|---|---|---|")
    for name in args.models:
        simulator = gns.load_simulator(name).eval()
        if not args.random and (not simulator.scene.walls or simulator.scene.bounds is None):
            raise ValueError(f"{name} has no walls: there is no floor to squeeze towards")
        floor = None if args.random else simulator.scene.bounds[1][0]
        stride = simulator.frame_stride_for(dataset.metadata)
        history = simulator.config.model.velocity_history + 1
        rows: dict[int, list[tuple[float, float]]] = {}
        for trajectory in dataset:
            trajectory = at_frame_stride(trajectory, stride)
            types = torch.as_tensor(trajectory.particle_type)
            free = ~simulator.scene.kinematic_mask(trajectory.particle_type)
            context = trajectory.step_context
            for t in range(history, len(trajectory.positions), args.every):
                frames = trajectory.positions[t - history : t].transpose(1, 0, 2)
                if args.random:
                    generator = np.random.default_rng(t)
                    shift = generator.normal(0.0, args.random, frames[:, -1].shape)
                else:
                    shift = probes.squeeze_toward_floor(frames[:, -1], floor, args.factor)
                shift[~free] = 0.0  # the kinematic particles stay where they are
                step_context = None if context is None else torch.as_tensor(context[t - 1 : t])
                undone = probes.shift_undone(simulator, frames, shift, types, step_context)
                speed = np.linalg.norm(frames[free, -1] - frames[free, -2], axis=1).mean()
                rows.setdefault(t, []).append((undone, speed / simulator.scene.dt))
        for t, values in rows.items():
            undone, speed = np.array(values).T
            print(
                f"| {name} | {t} | {speed.mean():.2f} | {undone.mean():+.3f} "
                f"({undone.min():+.3f} to {undone.max():+.3f}) |"
            )
        every = np.array([u for values in rows.values() for u, _ in values])
        print(
            f"| {name} | all | | {every.mean():+.3f} ({every.min():+.3f} to {every.max():+.3f}) |"
        )


def near_floor(simulator, trajectory, args) -> bool:
    """spread --near-floor: the trajectory starts within args.near_floor of the model's floor,
    slower than args.start_speed m/s (probes.starts_near_floor)."""
    if simulator.scene.bounds is None:
        raise ValueError("--near-floor needs a model with a box (scene.bounds)")
    free = ~simulator.scene.kinematic_mask(trajectory.particle_type)
    return probes.starts_near_floor(
        trajectory.positions[:, free],
        simulator.scene.bounds[1][0],
        args.near_floor,
        args.start_speed * simulator.scene.dt,
    )


def collapse(args) -> None:
    from gns.mpm import MpmScene

    simulators = [gns.load_simulator(name).eval() for name in args.models]
    stride = mpm_stride(simulators)
    dt = stride * MpmScene.frame_dt
    to_speed = probes.GRAVITY * dt  # g steps -> m/s
    print(
        f"blocks {args.width} wide standing at rest on the floor, friction angle "
        f"{args.friction_angle:g}, run by our MPM; the outer fifth's outward speed gained to "
        "its peak (m/s), one step at a time from the MPM's frames"
    )
    print("| height | MPM (peak speed m/s, step) | " + " | ".join(args.models) + " |")
    print("|---" * (len(args.models) + 2) + "|")
    for height in args.heights:
        # A thousandth above the floor: no particle starts on a wall node.
        trajectory = block_on_floor(
            args.friction_angle, args.width, height, 0.001, args.frames, stride
        )
        cells = []
        for simulator in simulators:
            r = front_launch(simulator, trajectory, 0.0)
            cells.append(f"{r['launch_one_step'] * to_speed:+.2f}")
        mpm_cell = f"{r['launch_truth'] * to_speed:+.2f} ({r['peak_speed'] / dt:.2f}, {r['peak']})"
        print(f"| {height:g} | {mpm_cell} | " + " | ".join(cells) + " |", flush=True)


def mpm_stride(simulators) -> int:
    """How many of the reference MPM's frames (the sand-taichi preset's, 2.5 ms, box
    DEFAULT_WALLS) one step of the models is; they must agree on a whole number."""
    from gns.mpm import MpmScene

    frame_dt = MpmScene.frame_dt
    steps = {round(s.scene.dt / frame_dt, 6) for s in simulators}
    if len(steps) != 1 or not float(next(iter(steps))).is_integer():
        raise ValueError(
            f"the models step {sorted(s.scene.dt for s in simulators)} s; the probe needs one "
            f"step, a whole number of the MPM's {frame_dt} s frames"
        )
    return int(next(iter(steps)))


def block_on_floor(angle: float, width: float, height: float, gap: float, frames: int, stride):
    """Our MPM's run (every `stride`-th of `frames` frames) of a sand block `width` x `height`
    at rest, centred in MpmScene's box with its lower edge `gap` above the floor, friction
    `angle` degrees (tan(angle) its context)."""
    from gns.mpm import DEFAULT_WALLS, Block, MpmScene, Sand, simulate

    floor, top = DEFAULT_WALLS
    block = Block(
        Sand(friction_angle_deg=angle),
        lower=((floor + top - width) / 2, floor + gap),
        size=(width, height),
    )
    mpm = simulate(MpmScene([block], context=[math.tan(math.radians(angle))]), frames)
    return at_frame_stride(mpm.to_trajectory(), stride)


def runout(args) -> None:
    from gns.deposit import pile_height, runout_extent
    from gns.mpm import DEFAULT_WALLS

    simulators = [gns.load_simulator(name).eval() for name in args.models]
    stride = mpm_stride(simulators)
    floor, top = DEFAULT_WALLS  # MpmScene's box (the sand-taichi preset's)
    side = top - floor
    if not (0 <= args.gap and 0 < args.width <= side and 0 < args.height <= side - args.gap):
        raise ValueError(
            f"the block ({args.width} x {args.height}, {args.gap} above the floor) must lie "
            f"inside the box [{floor}, {top}]^2: gap >= 0, 0 < width <= {side:g}, "
            f"0 < height <= {side:g} - gap"
        )
    print(
        f"a block {args.width} x {args.height} at rest, its lower edge {args.gap} above the "
        f"floor, run by our MPM for {args.frames} frames at each friction angle; the last "
        "frame's runout and pile height of the MPM (m) and of each model's rollout from the "
        "MPM's first frames (over the MPM's: runout / height)"
    )
    print("| angle | MPM runout | MPM height | " + " | ".join(args.models) + " |")
    print("|---" * (len(args.models) + 3) + "|")
    for angle in args.angles:
        truth = block_on_floor(angle, args.width, args.height, args.gap, args.frames, stride)
        last = truth.positions[-1]
        extent, height = runout_extent(last), pile_height(last, None, floor)
        cells = []
        for simulator in simulators:
            try:
                predicted = rollout(simulator, truth).predicted_rollout[-1]
            except RolloutDiverged:
                cells.append("diverged")
                continue
            cells.append(
                f"{runout_extent(predicted) / extent:.2f} / "
                f"{pile_height(predicted, None, floor) / height:.2f}"
            )
        row = f"| {angle:g} | {extent:.3f} | {height:.3f} | " + " | ".join(cells) + " |"
        print(row, flush=True)


def front_launch(simulator, trajectory, flowing: float) -> dict:
    """probes.launch_and_braking of the trajectory's free particles, the model predicting one
    step at a time from its frames; flowing: a speed per step."""
    free = ~simulator.scene.kinematic_mask(trajectory.particle_type)
    truth = trajectory.positions.astype(np.float64)[:, free]
    one_step = one_step_frames(simulator, trajectory)[:, free]
    rows = probes.spreading(truth, one_step, probes.g_step(simulator))
    return probes.launch_and_braking(rows, flowing)


@torch.no_grad()
def one_step_frames(simulator, trajectory, only=None) -> np.ndarray:
    """(T, N, D) float64: each frame t from the model's C + 1 on (or each t of `only`),
    predicted from the truth's frames before it; NaN elsewhere (before: no history)."""
    from gns.data.windows import window_keys
    from gns.evaluate import one_step_predictions

    history = simulator.config.model.velocity_history + 1
    pairs = list(window_keys([trajectory], history))  # start s predicts frame s + history
    if only is not None:
        wanted = set(only)
        pairs = [(k, start) for k, start in pairs if start + history in wanted]
    frames = np.full(trajectory.positions.shape, np.nan)
    for (_, start), (_, _, following, _) in zip(
        pairs, one_step_predictions(simulator, [trajectory], pairs), strict=True
    ):
        frames[start + history] = following.double().numpy()
    return frames


def noisy_one_step_frames(simulator, trajectory, only, draws: int) -> np.ndarray:
    """one_step_frames at the frames `only`, each the mean prediction over `draws` draws of
    the model's own training noise (config.noise) on the truth's input frames (seeded)."""
    if simulator.scene.obstacles:
        raise ValueError("--noise-draws takes scenes without obstacles")
    history = simulator.config.model.velocity_history + 1
    generator = torch.Generator().manual_seed(0)
    types = torch.as_tensor(trajectory.particle_type)
    material = trajectory.material_property
    material = None if material is None else torch.as_tensor(material)
    frames = np.full(trajectory.positions.shape, np.nan)
    for t in only:
        given = torch.as_tensor(trajectory.positions[t - history : t]).permute(1, 0, 2)
        context = trajectory.step_context
        context = None if context is None else torch.as_tensor(context[t - 1 : t])
        with torch.no_grad():
            frames[t] = np.mean(
                [
                    simulator.predict_positions(
                        given + simulator.sample_noise(given, types, generator),
                        types,
                        context=context,
                        material_property=material,
                    )
                    .double()
                    .numpy()
                    for _ in range(draws)
                ],
                axis=0,
            )
    return frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    probes_ = parser.add_subparsers(dest="probe", required=True)
    for name, run in (("reach", reach), ("floor", floor)):
        p = probes_.add_parser(name)
        p.add_argument("models", nargs="+")
        p.add_argument("--size", type=float, default=0.2)
        p.add_argument("--spacing", type=float, default=1 / 128)
        p.add_argument("--friction-angle", type=float, default=30.0)
        p.set_defaults(run=run)
    probes_.choices["reach"].add_argument("--untrained", action="store_true")
    probes_.choices["reach"].add_argument("--max-hop", type=int, default=8)
    probes_.choices["reach"].add_argument("--variant", action="append", default=[])
    probes_.choices["floor"].add_argument("--shift", type=float, default=1.0)
    probes_.choices["floor"].add_argument("--landing-speed", type=float, default=1.25)
    probes_.choices["floor"].add_argument("--bin", type=float, default=3.0)
    p = probes_.add_parser("landing")
    p.add_argument("model")
    p.add_argument("data")
    p.add_argument("split")
    p.add_argument("--trajectories", type=int, nargs="*")
    p.add_argument("--bands", type=int, default=3)
    p.add_argument("--threshold", type=float, default=3.0, help="g; default 3")
    p.add_argument(
        "--density-limit",
        type=float,
        default=1.5,
        help="the landings whose rollout stays within this many times the truth's density are "
        "counted; default 1.5 (issue 39's goal)",
    )
    p.set_defaults(run=landing)
    p = probes_.add_parser("rest")
    p.add_argument("models", nargs="+")
    p.add_argument("--data", required=True)
    p.add_argument("--split", default="valid")
    p.set_defaults(run=rest)
    p = probes_.add_parser("fall")
    p.add_argument("models", nargs="+")
    p.add_argument("--data", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--trajectories", type=int, nargs="*", help="indices (default: all)")
    p.add_argument("--tol", type=float, default=0.1, help="g; default 0.1")
    p.add_argument("--speeds", type=float, nargs="+", default=[0.25, 0.5, 1.0], help="m/s")
    p.add_argument(
        "--steps", type=float, nargs="+", default=[1, 2, 4, 8], help="steps of travel to the floor"
    )
    p.add_argument(
        "--heights",
        type=float,
        nargs="+",
        default=[1, 2, 3, 4, 6, 8, 12, 20],
        help="radii above the floor",
    )
    p.add_argument(
        "--noise-draws",
        type=int,
        default=0,
        help="also the model's mean prediction over this many draws of its training noise",
    )
    p.set_defaults(run=fall)
    p = probes_.add_parser("spread")
    p.add_argument("models", nargs="+")
    p.add_argument("--data", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--flowing", type=float, default=0.3)
    p.add_argument(
        "--near-floor", type=float, help="only trajectories starting this close to the floor"
    )
    p.add_argument("--start-speed", type=float, default=0.5, help="m/s; with --near-floor")
    p.set_defaults(run=spread)
    p = probes_.add_parser("squeeze")
    p.add_argument("models", nargs="+")
    p.add_argument("--data", required=True)
    p.add_argument("--split", default="test")
    p.add_argument("--factor", type=float, default=0.9, help="heights times this; default 0.9")
    p.add_argument("--random", type=float, help="a random shift of this std instead")
    p.add_argument("--every", type=int, default=10, help="steps between frames; default 10")
    p.set_defaults(run=squeeze)
    p = probes_.add_parser("collapse")
    p.add_argument("models", nargs="+")
    p.add_argument("--heights", type=float, nargs="+", default=[0.05, 0.1, 0.2, 0.3])
    p.add_argument("--width", type=float, default=0.2)
    p.add_argument("--friction-angle", type=float, default=30.0)
    p.add_argument("--frames", type=int, default=181, help="MPM frames of 2.5 ms (default 181)")
    p.set_defaults(run=collapse)
    p = probes_.add_parser("runout")
    p.add_argument("models", nargs="+")
    p.add_argument("--angles", type=float, nargs="+", default=[20.0, 30.0, 45.0])
    p.add_argument("--gap", type=float, default=0.019, help="default 0.019, sand_04's")
    p.add_argument("--width", type=float, default=0.2)
    p.add_argument("--height", type=float, default=0.2)
    p.add_argument("--frames", type=int, default=350, help="MPM frames of 2.5 ms (default 350)")
    p.set_defaults(run=runout)
    args = parser.parse_args()
    torch.set_num_threads(1)
    try:
        args.run(args)
    except ValueError as err:  # a model or data the probe cannot take: say why, no traceback
        raise SystemExit(f"probe.py {args.probe}: {err}") from err


if __name__ == "__main__":
    main()
