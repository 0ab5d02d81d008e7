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
  constant velocity   every particle keeps its last velocity (gns.baselines)
  static              every particle stays where the last input frame has it (gns.baselines):
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

Where the sand stops (gns.deposit), from the last frame's non-kinematic particles:
runout (the 99th minus the 1st percentile of x), pile height (the 99th percentile of y above the
box's floor) and the mean neighbour count within the dataset's connectivity radius; the table
has each over the ground truth's (runout_ratio, height_ratio, density_ratio: per trajectory,
then the mean) and density_ratio_max (the density ratio at its worst frame), table.json the
values per trajectory, the truth's own, and the fronts (the 1st and 99th percentile of x) of
every frame. With rest_steps, every learned row also holds each trajectory's last frame still
and rolls out from it (gns.evaluate.rest_test).

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
  rollout_{split}_{i}.gif     ground truth and prediction side by side (and .mp4 with ffmpeg);
                              the prediction of the headline checkpoint (default the first)
  vtk/                        ground_truth.pvd, prediction.pvd + one .vtp per frame (ParaView)
  rollouts/{checkpoint}/      the learned rollouts (gns.rollout's npz schema, for `gns eval`)

The work is split by job: gns.report.measure rolls out, extrapolates, times and scores the
learned model and the baselines; gns.report.reference the MPM rows; gns.report.render writes the
tables, figures, media and report.md / report.html; gns.report.conclusion puts the table into
words. This module checks the arguments, runs them in order and writes the folder atomically.
"""

from __future__ import annotations

import contextlib
import datetime
import os
import shutil
import sys
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gns.deposit import DEPOSIT_FIGURES, pile_floor
from gns.files import write_bytes_atomic
from gns.machine import machine_info
from gns.report.conclusion import conclusion
from gns.report.measure import (
    Row,
    _constant_velocity_row,
    _learned_row,
    _Scoring,
    _static_row,
    _trained_for,
    _truth_deposits,
    score,
)
from gns.report.reference import MpmVariant, _generator, _mpm_plan, _mpm_rows, parse_mpm_variants
from gns.report.render import (
    _frame_name,
    _html_report,
    _json_values,
    _markdown_report,
    _record,
    _write_figures,
    _write_json,
    _write_media,
    _write_tables,
    table_columns,
)

__all__ = [
    "DEFAULT_EVERY",
    "REPORT_HORIZONS",
    "MpmVariant",
    "Row",
    "parse_horizons",
    "parse_mpm_variants",
    "report",
    "score",
    "table_columns",
]

# The report's default horizons, in frames (None: the full rollout); `gns report --horizons`
# defaults to the same. Fewer than gns.metrics.DEFAULT_HORIZONS (gns eval's, 1 5 10 20 50 100
# full): each horizon here is three columns of the table (MSE, OT, MMD) and a column of panels
# in error_vs_time.png, so the report keeps one frame, 10, 50 and the full rollout.
REPORT_HORIZONS: tuple[int | None, ...] = (1, 10, 50, None)
# OT and MMD on every 10th predicted frame: exact OT takes 0.05 s per frame at 1000 particles
# when the prediction is close and ~1.7 s at 1400 particles when it is far off (this project's
# 2-core CPU), so a 155-frame rollout of a poor model costs ~25 s per row and trajectory.
DEFAULT_EVERY = 10


def _say(enabled: bool) -> Callable[[str], None]:
    """Progress lines on stderr, each with the seconds since the report started."""
    started = time.perf_counter()

    def say(message: str) -> None:
        if enabled:
            elapsed = time.perf_counter() - started
            sys.stderr.write(f"gns report [{elapsed:5.0f} s] {message}\n")
            sys.stderr.flush()

    return say


# --------------------------------------------------------------------------------- arguments


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


# ------------------------------------------------------------------------------------ report


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
    horizons: Sequence[int | None] = REPORT_HORIZONS,
    every: int = DEFAULT_EVERY,
    mpm: Sequence[str] = ("auto",),
    animation_frames: int = 120,
    vtk_every: int | None = None,
    rest_steps: int = 0,
    device: str = "auto",
    progress: bool = True,
    command: str | None = None,
    notes: Sequence[str] = (),
    labels: Sequence[str] | None = None,
    headline: int | None = None,
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
    command, notes: shown in the report. labels: a name per checkpoint, shown before its file
    in its row (e.g. "fine-tuned"). headline: the index in `checkpoints` of the row the
    conclusion speaks of, chosen by the caller on other data (e.g. the valid split); default:
    the learned row of lowest MSE over the full rollout, which is chosen on this split. out:
    default RUN/report_SPLIT (for a model folder, ./NAME/report_SPLIT:
    gns.checkpoints.run_folder); it must be missing, empty or an earlier report, which the new
    one replaces when it is complete (a failed report leaves `out` as it was).
    """

    from gns.checkpoints import load_checkpoint, run_folder, simulator_from_checkpoint
    from gns.data import at_frame_stride, open_dataset
    from gns.device import resolve_device
    from gns.rollout import frame_stride_metadata

    # Every argument is checked before the first rollout (they take minutes), and nothing is
    # written until then either.
    started = time.perf_counter()
    say = _say(progress)
    info = machine_info()  # before the report's own work shows in the load average
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
    out = Path(out) if out is not None else run_folder(run) / f"report_{split}"
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
    if labels is not None and len(labels) != len(checkpoints):
        raise ValueError(f"{len(labels)} labels for {len(checkpoints)} checkpoints")
    if headline is not None and headline not in range(len(checkpoints)):
        raise ValueError(f"headline must index the {len(checkpoints)} checkpoints, got {headline}")
    paths = [_checkpoint(run, which) for which in checkpoints]
    # One row per file; a file named twice keeps its first label.
    named = dict(zip(reversed(paths), reversed(labels or [""] * len(paths)), strict=True))
    chosen = list(dict.fromkeys(paths))
    # The row the conclusion speaks of, and the animation and VTK files show.
    shown = 0 if headline is None else chosen.index(paths[headline])
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
                named[path],
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
            if len(rows) - 1 == shown:
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
                rows[shown].short,
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
            "dim": first.dim,
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
            "conclusion": conclusion(
                rows,
                columns,
                steps,
                truth["mean"],
                frame=frame,
                headline=None if headline is None else rows[shown],
            ),
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


def _dataset_name(data: Path, metadata: Any) -> str:
    generator = _generator(metadata)
    if generator is None:
        return data.name
    return f"{data.name} (gns generate preset {generator['preset']}, seed {generator['seed']})"


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
