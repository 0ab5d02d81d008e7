"""gns report's reference-simulator rows (see gns.report): the MPM settings asked for, the scenes
to re-run (those that made a `gns generate` dataset, or a manifest folder's blocks started from
the data's own particles), and each setting's runs on every trajectory, timed and scored."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gns.data.stride import frame_stride, spacing_text
from gns.machine import rust_threads
from gns.report.measure import Row, _count, _Scoring

__all__ = ["MpmVariant", "parse_mpm_variants"]


# ---------------------------------------------------------------------------------- settings


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
        per_cell = scene.particles_per_cell * (scene.grid / grid) ** scene.dim
        cfl = scene.cfl if self.cfl is None else self.cfl
        return dataclasses.replace(scene, grid=grid, particles_per_cell=per_cell, cfl=cfl)

    @property
    def native(self) -> bool:
        return self.grid is None and self.cfl is None


def parse_mpm_variants(
    specs: Sequence[str], native_grid: int, native_cfl: float, min_grid: int = 2
) -> list[MpmVariant]:
    """MPM settings from the command line: "native", "grid=20", "cfl=0.8", "grid=20,cfl=0.8",
    "auto" (native; 0.6 and 0.5 of the grid; twice the CFL number; 0.6 of the grid with twice
    the CFL number; "auto" takes no grid below `min_grid`, the coarsest the scene's walls allow,
    and repeats none) or "none" (no MPM rows)."""
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
            coarse = max(2, min_grid, round(0.6 * native_grid))
            half = max(2, min_grid, native_grid // 2)
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


def _coarsest_grid(scene: Any) -> int:
    """The fewest cells per unit length the simulator accepts for the scene's walls: they must
    lie 2 cells inside the domain (3D scenes at grid 24 have 0.6 of it, 14, below their 20)."""
    margin = min(min(lo, 1.0 - hi) for lo, hi in scene.bounds)
    return max(2, math.ceil(2.0 / margin - 1e-9))


# ------------------------------------------------------------------------------------ scenes


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
    variants = parse_mpm_variants(specs, native.grid, native.cfl, _coarsest_grid(native))
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
    from gns.mpm.generate import preset_scene

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
            generator["preset"],
            int(generator["seed"]),
            split,
            index,
            int(draws[index]),
            float(generator.get("scale", 1.0)),
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


# -------------------------------------------------------------------------------------- rows


def _mpm_rows(
    plan: _MpmPlan,
    trajectories: list[Any],
    indices: list[int],
    scoring: _Scoring,
    say: Callable[[str], None],
) -> list[Row]:
    """The reference simulator's rows: each of the plan's settings on every trajectory."""
    from gns import mpm

    threads = rust_threads()
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
