"""The figures of `gns report`: error against run time, error over time, rollout animations.

Drawn with matplotlib's Agg canvas on figures that are never registered with pyplot, so
nothing here touches a global backend or needs a display; animations are assembled by Pillow
(GIF) and, where an `ffmpeg` executable exists, by ffmpeg (MP4). Every file is written
atomically.
"""

from __future__ import annotations

import itertools
import math
import os
import shutil
import subprocess
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from PIL import Image

from gns.data.atomic import atomic_file

__all__ = ["Series", "animation", "error_over_time", "error_vs_time", "type_colours"]

# DeepMind's particle types (learning_to_simulate's datasets), which gns.mpm also uses.
TYPE_NAMES = {3: "obstacle", 5: "water", 6: "sand", 7: "goop"}
_TYPE_COLOURS = {3: "#4d4d4d", 5: "#1f77b4", 6: "#c8961e", 7: "#b5338a"}
_OTHER_COLOURS = ("#2ca02c", "#d62728", "#9467bd", "#8c564b", "#17becf", "#7f7f7f")
_MARKERS = ("o", "s", "D", "^", "P", "X", "*", "h", "<", ">", "p", "d")
_METRIC_NAMES = {"mse": "MSE", "ot": "optimal transport (W2^2)", "mmd": "MMD^2"}


def _save_png(figure: Figure, path: str | os.PathLike[str]) -> None:
    FigureCanvasAgg(figure)
    with atomic_file(path) as tmp, open(tmp, "wb") as f:
        figure.savefig(f, format="png")


def type_colours(types: np.ndarray) -> tuple[np.ndarray, dict[int, str]]:
    """(N,) colours for particle types (N,) and the legend {type: colour} of those present."""
    legend: dict[int, str] = {}
    others = itertools.cycle(_OTHER_COLOURS)
    for t in np.unique(types).tolist():
        legend[int(t)] = _TYPE_COLOURS.get(int(t)) or next(others)
    return np.array([legend[int(t)] for t in types]), legend


@dataclass(frozen=True)
class Series:
    """One method (a row of the report's table) in the figures: a short label, wall time per
    frame in seconds (None if unknown), its figures by metric key ("mse@10", "ot@full", ...;
    missing when not computed, inf when it diverged), and per-frame curves (frames, values) of
    MSE and of optimal transport for the error-over-time figure."""

    label: str
    seconds_per_frame: float | None
    values: Mapping[str, float]
    mse_curve: tuple[np.ndarray, np.ndarray] | None = None
    ot_curve: tuple[np.ndarray, np.ndarray] | None = None


def _styles(series: Sequence[Series]) -> list[dict[str, str]]:
    """The same colour and marker for a method in every figure."""
    return [
        {"marker": _MARKERS[i % len(_MARKERS)], "color": f"C{i % 10}"} for i in range(len(series))
    ]


def _legend_below(figure: Figure, handles: list[Any], labels: list[str], top: float) -> None:
    """One legend for all panels, under them, two entries a line."""
    lines = math.ceil(len(labels) / 2)
    height_inches = 0.25 * lines + 0.15
    bottom = height_inches / figure.get_figheight()
    if handles:
        figure.legend(
            handles,
            labels,
            loc="lower center",
            ncol=2,
            fontsize=8,
            frameon=False,
            bbox_to_anchor=(0.5, 0.0),
        )
    figure.tight_layout(rect=(0, bottom, 1, top))


def _horizon_label(key: str) -> str:
    h = key.split("@", 1)[1]
    return "full rollout" if h == "full" else f"first {h} frame{'s' if h != '1' else ''}"


def error_vs_time(
    series: Sequence[Series],
    metrics: Sequence[str],
    horizons: Sequence[str],
    path: str | os.PathLike[str],
    title: str = "",
) -> None:
    """A grid of log-log scatter plots, one row per metric ("mse", "ot", "mmd") and one column
    per horizon ("1", "10", "full"): error against milliseconds per simulated frame, one marker
    per method. An error of exactly 0 (a deterministic simulator reproducing its own ground
    truth) cannot sit on a log axis: it is drawn hollow at the bottom of the panel, labelled
    "= 0". Methods without a time or a finite value are left out of that panel."""
    rows, cols = len(metrics), len(horizons)
    figure = Figure(figsize=(3.3 * cols + 0.6, 2.7 * rows + 0.6 + 0.25 * len(series) / 2), dpi=100)
    axes = figure.subplots(rows, cols, squeeze=False)
    styles = _styles(series)
    drawn: set[int] = set()
    for r, metric in enumerate(metrics):
        for c, horizon in enumerate(horizons):
            ax = axes[r][c]
            key = f"{metric}@{horizon}"
            points = [
                (i, s.seconds_per_frame * 1e3, value)
                for i, s in enumerate(series)
                if s.seconds_per_frame is not None
                and (value := s.values.get(key)) is not None
                and math.isfinite(value)  # inf (diverged): nothing to draw; the table says so
            ]
            positive = [v for _, _, v in points if v > 0]
            floor = min(positive) / 10 if positive else 1e-12
            for i, ms, value in points:
                if value == 0:
                    colour, marker = styles[i]["color"], styles[i]["marker"]
                    ax.scatter([ms], [floor], s=50, marker=marker, facecolors="none", color=colour)
                    ax.annotate("= 0", (ms, floor), textcoords="offset points", xytext=(6, 2))
                else:
                    ax.scatter([ms], [value], s=50, **styles[i])
                drawn.add(i)
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
            if r == 0:
                ax.set_title(_horizon_label(key), fontsize=10)
            if c == 0:
                ax.set_ylabel(_METRIC_NAMES.get(metric, metric))
            if r == rows - 1:
                ax.set_xlabel("ms per simulated frame")
    shown = sorted(drawn)
    handles = [Line2D([], [], linestyle="none", markersize=7, **styles[i]) for i in shown]
    if title:
        figure.suptitle(title, fontsize=11)
    _legend_below(figure, handles, [series[i].label for i in shown], 0.96 if title else 1.0)
    _save_png(figure, path)


def error_over_time(
    series: Sequence[Series],
    path: str | os.PathLike[str],
    first_frame: int = 0,
    title: str = "",
) -> None:
    """Two panels over frame number: each method's per-frame MSE and its optimal-transport
    distance at the frames where that was evaluated. Curve frames count from 0 = the first
    predicted frame, shown as `first_frame`. Values that are 0 or infinite cannot be drawn on a
    log axis and are left out; a method that is 0 throughout is named as such."""
    figure = Figure(figsize=(11, 4.2 + 0.25 * len(series) / 2), dpi=100)
    axes = figure.subplots(1, 2)
    styles = _styles(series)
    handles, labels = [], []
    for i, s in enumerate(series):
        zero = True
        for ax, curve in ((axes[0], s.mse_curve), (axes[1], s.ot_curve)):
            if curve is None:
                continue
            frames, values = np.asarray(curve[0]), np.asarray(curve[1], dtype=np.float64)
            zero = zero and bool(np.all(values == 0))
            shown = np.where(np.isfinite(values) & (values > 0), values, np.nan)
            ax.plot(frames + first_frame, shown, color=styles[i]["color"], lw=1.5)
        if s.mse_curve is not None:
            handles.append(Line2D([], [], color=styles[i]["color"], lw=1.5))
            labels.append(f"{s.label} (0 throughout)" if zero else s.label)
    for ax, name in ((axes[0], "MSE"), (axes[1], "W2^2")):
        ax.set_yscale("log")
        ax.set_xlabel("frame")
        ax.set_ylabel(name)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_title("MSE per frame (mean over trajectories)", fontsize=10)
    axes[1].set_title("optimal transport at the evaluated frames", fontsize=10)
    if title:
        figure.suptitle(title, fontsize=11)
    _legend_below(figure, handles, labels, 0.94 if title else 1.0)
    _save_png(figure, path)


def _limits(
    truth: np.ndarray, predicted: np.ndarray, bounds: Sequence[Sequence[float]] | None
) -> list[tuple[float, float]]:
    """x and y limits: the box when known, else what the ground truth covers, with a margin."""
    if bounds is not None:
        box = [(float(lo), float(hi)) for lo, hi in list(bounds)[:2]]
    else:
        lo, hi = truth[..., :2].min(axis=(0, 1)), truth[..., :2].max(axis=(0, 1))
        box = [(float(a), float(b)) for a, b in zip(lo, hi, strict=True)]
    return [(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo)) for lo, hi in box]


def _frame_images(
    truth: np.ndarray,
    predicted: np.ndarray,
    particle_type: np.ndarray,
    bounds: Sequence[Sequence[float]] | None,
    titles: tuple[str, str],
    frames: np.ndarray,
    first_predicted: int,
    dt: float | None,
) -> list[Image.Image]:
    colours, legend = type_colours(particle_type)
    figure = Figure(figsize=(8, 4.3), dpi=80)
    canvas = FigureCanvasAgg(figure)
    axes = figure.subplots(1, 2)
    limits = _limits(truth, predicted, bounds)
    size = float(np.clip(3000 / max(1, truth.shape[1]), 0.5, 12))
    scatters = []
    for ax, title in zip(axes, titles, strict=True):
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(title, fontsize=10)
        scatters.append(ax.scatter(truth[0, :, 0], truth[0, :, 1], s=size, c=colours, lw=0))
    for t, colour in legend.items():
        axes[0].scatter([], [], s=20, c=colour, label=TYPE_NAMES.get(t, f"type {t}"))
    axes[0].legend(loc="upper right", fontsize=7, markerscale=1.0)
    figure.subplots_adjust(left=0.02, right=0.98, top=0.92, bottom=0.08, wspace=0.05)
    caption = figure.text(0.5, 0.02, "", ha="center", fontsize=9)
    images = []
    for t in frames.tolist():
        for scatter, positions in zip(scatters, (truth[t], predicted[t]), strict=True):
            scatter.set_offsets(positions[:, :2])
        phase = "given (history)" if t < first_predicted else "predicted"
        when = f"  t = {t * dt:.3f} s" if dt else ""
        caption.set_text(f"frame {t}{when}  ({phase})")
        canvas.draw()
        rgba = np.asarray(canvas.buffer_rgba())
        images.append(Image.fromarray(rgba[..., :3].copy()))
    return images


def _write_mp4(images: list[Image.Image], path: str | os.PathLike[str], fps: float) -> str | None:
    """Encode with the ffmpeg executable; returns why not, or None when written."""
    ffmpeg = shutil.which("ffmpeg")
    if ffmpeg is None:
        return "no ffmpeg executable on PATH"
    width, height = images[0].size
    with atomic_file(path) as tmp:
        command = [
            ffmpeg,
            "-loglevel",
            "error",
            "-y",
            "-f",
            "rawvideo",
            "-pix_fmt",
            "rgb24",
            "-s",
            f"{width}x{height}",
            "-r",
            f"{fps:g}",
            "-i",
            "-",
            # H.264 in yuv420p needs even sides.
            "-vf",
            "pad=ceil(iw/2)*2:ceil(ih/2)*2",
            "-pix_fmt",
            "yuv420p",
            "-f",
            "mp4",
            str(tmp),
        ]
        payload = b"".join(image.tobytes() for image in images)
        try:
            subprocess.run(command, input=payload, check=True, capture_output=True)
        except (OSError, subprocess.CalledProcessError) as err:
            detail = getattr(err, "stderr", b"") or b""
            return f"ffmpeg failed ({err}; {detail.decode(errors='replace').strip()[:200]})"
    return None


def animation(
    truth: np.ndarray,
    predicted: np.ndarray,
    particle_type: np.ndarray,
    gif_path: str | os.PathLike[str],
    *,
    bounds: Sequence[Sequence[float]] | None = None,
    titles: tuple[str, str] = ("ground truth", "prediction"),
    first_predicted: int = 0,
    dt: float | None = None,
    max_frames: int = 120,
    fps: float = 20.0,
    mp4_path: str | os.PathLike[str] | None = None,
) -> str | None:
    """Ground truth and prediction side by side, coloured by particle type, as a GIF (and an
    MP4 when mp4_path is given and ffmpeg exists). truth and predicted: (T, N, D) whole
    sequences (history included: frames before `first_predicted` are marked as given); 3D is
    shown as its x-y projection. At most max_frames frames, evenly spaced, always including the
    last. Returns None, or why the MP4 was not written."""
    truth, predicted = np.asarray(truth), np.asarray(predicted)
    if truth.ndim != 3 or truth.shape != predicted.shape or truth.shape[2] < 2:
        raise ValueError(
            f"truth and predicted must be the same (T, N, D >= 2) shape, got {truth.shape} "
            f"and {predicted.shape}"
        )
    if isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1:
        raise ValueError(f"max_frames must be a positive integer, got {max_frames!r}")
    count = min(max_frames, truth.shape[0])
    frames = np.unique(np.linspace(0, truth.shape[0] - 1, count).round().astype(int))
    images = _frame_images(
        truth, predicted, particle_type, bounds, titles, frames, first_predicted, dt
    )
    palette = [image.quantize(colors=64, method=Image.Quantize.MEDIANCUT) for image in images]
    with atomic_file(gif_path) as tmp, open(tmp, "wb") as f:
        palette[0].save(
            f,
            format="GIF",
            save_all=True,
            append_images=palette[1:],
            duration=round(1000 / fps),
            loop=0,
        )
    if mp4_path is None:
        return None
    return _write_mp4(images, mp4_path, fps)
