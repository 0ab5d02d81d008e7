"""gns report's files (see gns.report), made from the measured rows: the table's records and
columns, table.md / table.csv / table.json, the figures, the animation and VTK files, and
report.md / report.html around them."""

from __future__ import annotations

import csv
import html
import io
import json
import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from gns.data.stride import describe_frame_stride, spacing_text
from gns.deposit import FRONT_CURVES
from gns.distances import EXACT_MAX_POINTS
from gns.files import write_bytes_atomic
from gns.report.measure import METRICS, TIMING_PARTS, Row, _count

__all__ = ["DEPOSIT_COLUMNS", "table_columns"]

# The deposit's columns (gns.deposit.deposit_ratios): the last frame's over the truth's, and
# the density's ratio at its worst frame (a landing packs sand that the last frame may not show).
DEPOSIT_COLUMNS = ("runout_ratio", "height_ratio", "density_ratio", "density_ratio_max")


# ------------------------------------------------------------------------------------- table


def table_columns(horizons: Sequence[int | None], steps: int) -> list[str]:
    """The table's columns; horizons longer than the rollout (steps frames) have none. The
    deposit's ratios are of the last frame (density_ratio_max: of every frame), so of the full
    horizon."""
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


def _frame_name(frame_dt: float, stride: int) -> str:
    """What the table's times are per: "frame" (of the data), or at a frame stride one step of
    the model, e.g. "7.5 ms step"."""
    return "frame" if stride == 1 else f"{spacing_text(frame_dt)} step"


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


# ------------------------------------------------------------------------------------- files


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
    return np.stack([deposit[k] for k in FRONT_CURVES], axis=1)


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
    """The animation and VTK files of one trajectory and the headline checkpoint's prediction
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
        why_not = animation(
            truth,
            whole,
            trajectory.particle_type,
            gif,
            bounds=bounds,
            titles=("ground truth", label),
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


# -------------------------------------------------------------------- report.md, report.html


def _relative(path: Path, out: Path) -> str:
    return os.path.relpath(path, out)


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
        f"- OT (W2^2, an exact assignment; above {EXACT_MAX_POINTS} particles on a fixed random "
        f"subset of that many) and MMD^2 (Gaussian kernel, bandwidth 0.1): evaluated on one "
        f"predicted frame in k = {k} only (frames 1, {k + 1}, {2 * k + 1}, ... of the rollout), "
        "as they cost O(N^2) or more per frame; "
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
        "Density ratio max: the same ratio in every predicted frame against the truth's "
        "frame, its largest per trajectory (how far a landing packs the sand before the pile "
        "relaxes; inf from a diverged frame on), then the mean over trajectories. "
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


def _views_sentence() -> str:
    from gns.plots import VIEWS_3D_TEXT

    return f"Each panel shows the 3D positions from two sides: {VIEWS_3D_TEXT}."


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
        if context["dim"] == 3:
            lines += [_views_sentence(), ""]
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
    if "gif" in files and context["dim"] == 3:
        images += f"<p>{e(_views_sentence())}</p>"
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
