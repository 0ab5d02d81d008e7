"""The figures of `gns report`: error against run time, error over time, the fronts of the sand
over time, rollout animations (3D from two sides: front x-y and top x-z).

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

from gns.files import atomic_file

__all__ = [
    "RolloutFigure",
    "Series",
    "VIEWS_3D",
    "VIEWS_3D_TEXT",
    "animation",
    "animation_frames",
    "diverged_frame",
    "error_against_parameter",
    "error_over_time",
    "error_vs_time",
    "front_over_time",
    "type_colours",
]

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
    missing when not computed, inf when it diverged), per-frame curves (frames, values) of
    MSE and of optimal transport for the error-over-time figure, the rollout step at which it
    diverged (None if it did not), after which its values are inf, and the fronts of one
    trajectory, (S, 2): the 1st and 99th percentile of x in every predicted frame
    (gns.deposit.front_positions), inf after a divergence."""

    label: str
    seconds_per_frame: float | None
    values: Mapping[str, float]
    mse_curve: tuple[np.ndarray, np.ndarray] | None = None
    ot_curve: tuple[np.ndarray, np.ndarray] | None = None
    diverged_at: int | None = None
    fronts: np.ndarray | None = None

    @property
    def legend(self) -> str:
        """The label, with where it diverged: a diverged method must not pass for a good one
        whose points happen to be missing."""
        if self.diverged_at is None:
            return self.label
        return f"{self.label}: diverged at step {self.diverged_at}"


# A diverged method's mark: an x at its last finite point, or at the top edge of a panel where
# it has none.
_DIVERGED_MARKER = "x"
_DIVERGED: dict[str, Any] = {
    "marker": _DIVERGED_MARKER,
    "markersize": 9,
    "markeredgewidth": 2,
    "linestyle": "none",
}


def _mark_diverged(ax: Any, x: float, y: float | None, colour: str) -> None:
    """The x of a diverged method at (x, y), or at x on the panel's top edge when y is None
    (no finite value to put it at: a log axis cannot show inf)."""
    if y is None:
        ax.plot([x], [0.97], color=colour, transform=ax.get_xaxis_transform(), **_DIVERGED)
    else:
        ax.plot([x], [y], color=colour, **_DIVERGED)


def _styles(series: Sequence[Series]) -> list[dict[str, Any]]:
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
) -> Figure:
    """A grid of log-log scatter plots, one row per metric ("mse", "ot", "mmd") and one column
    per horizon ("1", "10", "full"): error against milliseconds per simulated frame, one marker
    per method. An error of exactly 0 (a deterministic simulator reproducing its own ground
    truth) cannot sit on a log axis: it is drawn hollow at the bottom of the panel, labelled
    "= 0". A method that diverged before a horizon (inf) is an x on that panel's top edge and
    says where it diverged in the legend. Methods without a time or a value are left out of
    that panel. Returns the figure (saved to `path`)."""
    rows, cols = len(metrics), len(horizons)
    figure = Figure(figsize=(3.3 * cols + 0.6, 2.7 * rows + 0.6 + 0.25 * len(series) / 2), dpi=100)
    axes = figure.subplots(rows, cols, squeeze=False)
    styles = _styles(series)
    drawn = {i for i, s in enumerate(series) if s.diverged_at is not None}
    for r, metric in enumerate(metrics):
        for c, horizon in enumerate(horizons):
            ax = axes[r][c]
            key = f"{metric}@{horizon}"
            timed = [
                (i, s.seconds_per_frame * 1e3, value)
                for i, s in enumerate(series)
                if s.seconds_per_frame is not None and (value := s.values.get(key)) is not None
            ]
            points = [(i, ms, value) for i, ms, value in timed if math.isfinite(value)]
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
            for i, ms, value in timed:
                if not math.isfinite(value):
                    _mark_diverged(ax, ms, None, styles[i]["color"])
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
    _legend_below(figure, handles, [series[i].legend for i in shown], 0.96 if title else 1.0)
    _save_png(figure, path)
    return figure


def _last_finite(values: np.ndarray) -> tuple[int | None, int | None]:
    """(index of the last finite value before the first non-finite one, or None; index of the
    first non-finite one, or None)."""
    bad = np.flatnonzero(~np.isfinite(values))
    end = int(bad[0]) if len(bad) else len(values)
    return (end - 1 if end > 0 else None), (int(bad[0]) if len(bad) else None)


def error_over_time(
    series: Sequence[Series],
    path: str | os.PathLike[str],
    first_frame: int = 0,
    title: str = "",
) -> Figure:
    """Two panels over frame number: each method's per-frame MSE and its optimal-transport
    distance at the frames where that was evaluated. Curve frames count from 0 = the first
    predicted frame, shown as `first_frame`. Values that are 0 or infinite cannot be drawn on a
    log axis and are left out; a method that is 0 throughout is named as such, and one that
    diverged gets an x at its last finite point (at the top edge over the frame it diverged at,
    if it has none) and says where in the legend. Returns the figure (saved to `path`)."""
    figure = Figure(figsize=(11, 4.2 + 0.25 * len(series) / 2), dpi=100)
    axes = figure.subplots(1, 2)
    styles = _styles(series)
    handles, labels = [], []
    for i, s in enumerate(series):
        zero = True
        colour = styles[i]["color"]
        for ax, curve in ((axes[0], s.mse_curve), (axes[1], s.ot_curve)):
            if curve is None:
                continue
            frames, values = np.asarray(curve[0]), np.asarray(curve[1], dtype=np.float64)
            zero = zero and bool(np.all(values == 0))
            shown = np.where(np.isfinite(values) & (values > 0), values, np.nan)
            ax.plot(frames + first_frame, shown, color=colour, lw=1.5)
            last, bad = _last_finite(values)
            if s.diverged_at is not None and bad is not None:
                if last is not None and values[last] > 0:
                    _mark_diverged(ax, frames[last] + first_frame, values[last], colour)
                else:
                    _mark_diverged(ax, frames[bad] + first_frame, None, colour)
        if s.mse_curve is not None:
            marker = "none" if s.diverged_at is None else _DIVERGED_MARKER
            handles.append(Line2D([], [], color=colour, lw=1.5, marker=marker))
            labels.append(f"{s.label} (0 throughout)" if zero else s.legend)
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
    return figure


def front_over_time(
    series: Sequence[Series],
    truth: np.ndarray,
    path: str | os.PathLike[str],
    first_frame: int = 0,
    title: str = "",
) -> Figure:
    """Where the sand's fronts are over time: the ground truth's fronts, truth (S, 2), the 1st
    and the 99th percentile of x in every predicted frame, in black, and each method's
    (Series.fronts) in its colour; frames count from 0 = the first predicted frame, shown as
    `first_frame`. A method that diverged stops there, with an x at its last finite front.
    Methods without fronts are left out. Returns the figure (saved to `path`)."""
    figure = Figure(figsize=(8, 4.6 + 0.25 * len(series) / 2), dpi=100)
    ax = figure.subplots()
    styles = _styles(series)
    frames = np.arange(len(truth)) + first_frame
    for side in range(2):
        ax.plot(frames, truth[:, side], color="black", lw=2.5)
    handles: list[Any] = [Line2D([], [], color="black", lw=2.5)]
    labels = ["ground truth"]
    for i, s in enumerate(series):
        if s.fronts is None:
            continue
        fronts, colour = np.asarray(s.fronts, dtype=np.float64), styles[i]["color"]
        shown = np.where(np.isfinite(fronts), fronts, np.nan)
        for side in range(2):
            ax.plot(frames[: len(shown)], shown[:, side], color=colour, lw=1.3)
        last, bad = _last_finite(fronts[:, 1])
        if s.diverged_at is not None and bad is not None and last is not None:
            for side in range(2):
                _mark_diverged(ax, frames[last], fronts[last, side], colour)
        marker = "none" if s.diverged_at is None else _DIVERGED_MARKER
        handles.append(Line2D([], [], color=colour, lw=1.3, marker=marker))
        labels.append(s.legend)
    ax.set_xlabel("frame")
    ax.set_ylabel("x")
    ax.grid(True, alpha=0.3)
    ax.set_title("fronts of the sand: 1st and 99th percentile of x (first trajectory)", fontsize=10)
    if title:
        figure.suptitle(title, fontsize=11)
    _legend_below(figure, handles, labels, 0.94 if title else 1.0)
    _save_png(figure, path)
    return figure


def error_against_parameter(
    values: np.ndarray,
    errors: dict[str, np.ndarray],
    held_out: tuple[float, float],
    path: str | os.PathLike[str],
    name: str = "friction angle (degrees)",
) -> Figure:
    """The paper's figure C.5: each trajectory's error (errors: label -> (K,) MSE over the full
    rollout, one per value) against the parameter it was made with, values (K,), the band
    held out of training shaded red. Returns the figure (saved to `path`)."""
    figure = Figure(figsize=(7, 4.2), dpi=100)
    ax = figure.subplots()
    ax.axvspan(*held_out, color="#d62728", alpha=0.12, lw=0, label="held out of training")
    order = np.argsort(values)
    for (label, error), marker in zip(errors.items(), "os^v", strict=False):
        shown = np.where(np.isfinite(error), error, np.nan)[order]
        ax.plot(np.asarray(values)[order], shown, marker=marker, lw=1, ms=4, label=label)
    ax.set_yscale("log")
    ax.set_xlabel(name)
    ax.set_ylabel("MSE over the full rollout")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    ax.set_title("error against the held-out parameter (figure C.5)", fontsize=10)
    _save_png(figure, path)
    return figure


def _box(truth: np.ndarray, bounds: Sequence[Sequence[float]] | None) -> list[tuple[float, float]]:
    """(lo, hi) of every axis of truth (T, N, D): the box when known, else what the ground
    truth covers."""
    if bounds is not None:
        return [(float(lo), float(hi)) for lo, hi in list(bounds)[: truth.shape[-1]]]
    lo, hi = truth.min(axis=(0, 1)), truth.max(axis=(0, 1))
    return [(float(a), float(b)) for a, b in zip(lo, hi, strict=True)]


def _limits(box: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
    """Axis limits around the box, with a margin."""
    return [(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo)) for lo, hi in box]


def diverged_frame(positions: np.ndarray) -> int | None:
    """The first frame of positions (T, N, D) holding a non-finite value (where a rollout
    diverged and was padded with NaN), or None when every frame is finite."""
    bad = np.flatnonzero(~np.isfinite(np.asarray(positions)).all(axis=(1, 2)))
    return int(bad[0]) if len(bad) else None


# The two views of 3D positions, side by side in each panel of an animation: (title, axis
# drawn across, axis drawn upward). y is up (gravity along -y): the front view looks along -z;
# the top view looks down along -y, so with x running rightward as in the front view, z grows
# downward (its vertical axis is flipped).
VIEWS_3D = (("front (x-y)", 0, 1), ("top (x-z, from above)", 0, 2))
# What the report says the animation of 3D data shows.
VIEWS_3D_TEXT = "front (x-y, y up) and top (x-z, seen from above)"


class RolloutFigure:
    """The animation's figure: ground truth and prediction side by side, coloured by particle
    type. draw(t) shows frame t. A prediction that diverged (non-finite from frame k on) is
    shown up to frame k - 1; from frame k its panel keeps that last state, faded, under
    "diverged at frame k", rather than going blank.

    2D positions (and the x-y of more than 3 axes) get one view per panel; 3D positions two,
    side by side (VIEWS_3D): front (x-y) and top (x-z), each with the box's bounds as its
    ticks, so the figure is twice as wide. views: per panel (truth, prediction), each view's
    scatter and the (across, upward) axes it draws; scatters: each panel's first view."""

    def __init__(
        self,
        truth: np.ndarray,
        predicted: np.ndarray,
        particle_type: np.ndarray,
        bounds: Sequence[Sequence[float]] | None,
        titles: tuple[str, str],
        first_predicted: int,
        dt: float | None,
    ) -> None:
        self.truth, self.predicted = truth, predicted
        self.first_predicted, self.dt = first_predicted, dt
        self.diverged_at = diverged_frame(predicted)
        colours, legend = type_colours(particle_type)
        three = truth.shape[2] == 3
        self.figure = Figure(figsize=(16 if three else 8, 4.3), dpi=80)
        self.canvas = FigureCanvasAgg(self.figure)
        box = _box(truth, bounds)
        # The notice goes over the prediction's panel: its axes in 2D, its pair of views in 3D.
        panels, over = (self._panels_3d if three else self._panels_2d)(titles, box)
        size = float(np.clip(3000 / max(1, truth.shape[1]), 0.5, 12))
        self.views: list[list[tuple[Any, tuple[int, int]]]] = [
            [
                (ax.scatter(truth[0, :, a], truth[0, :, b], s=size, c=colours, lw=0), (a, b))
                for ax, (a, b) in panel
            ]
            for panel in panels
        ]
        first = panels[0][0][0]
        for t, colour in legend.items():
            first.scatter([], [], s=20, c=colour, label=TYPE_NAMES.get(t, f"type {t}"))
        first.legend(loc="upper right", fontsize=7, markerscale=1.0)
        self.notice = self.figure.text(
            0.5,
            0.5,
            "",
            transform=over,
            ha="center",
            va="center",
            fontsize=13,
            color="#d62728",
            fontweight="bold",
        )
        if not three:
            self.figure.subplots_adjust(left=0.02, right=0.98, top=0.92, bottom=0.08, wspace=0.05)
        self.caption = self.figure.text(0.5, 0.02, "", ha="center", fontsize=9)

    @property
    def scatters(self) -> list[Any]:
        """The scatter of each panel's first view: [truth, prediction]."""
        return [panel[0][0] for panel in self.views]

    def _panels_2d(
        self, titles: tuple[str, str], box: Sequence[tuple[float, float]]
    ) -> tuple[list[list[tuple[Any, tuple[int, int]]]], Any]:
        """One x-y axes per panel, without ticks; and the prediction's axes' transform."""
        limits = _limits(box)
        panels = []
        for ax, title in zip(self.figure.subplots(1, 2), titles, strict=True):
            ax.set_xlim(*limits[0])
            ax.set_ylim(*limits[1])
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(title, fontsize=10)
            panels.append([(ax, (0, 1))])
        return panels, panels[1][0][0].transAxes

    def _panels_3d(
        self, titles: tuple[str, str], box: Sequence[tuple[float, float]]
    ) -> tuple[list[list[tuple[Any, tuple[int, int]]]], Any]:
        """Per panel, a subfigure titled with the panel's title holding the VIEWS_3D side by
        side, each axes labelled and ticked at the box's bounds (which show the direction of
        the top view's flipped z); and the prediction's subfigure's transform."""
        limits = _limits(box)
        panels = []
        subfigures = np.asarray(self.figure.subfigures(1, 2, wspace=0.0))
        for subfigure, title in zip(subfigures, titles, strict=True):
            subfigure.suptitle(title, fontsize=10, y=0.97)
            views = []
            for ax, (name, a, b) in zip(subfigure.subplots(1, 2), VIEWS_3D, strict=True):
                ax.set_xlim(*limits[a])
                # The top view's z grows downward: seen from above, with x to the right.
                ax.set_ylim(*(limits[b][::-1] if b == 2 else limits[b]))
                ax.set_aspect("equal")
                ax.set_xticks(box[a], [f"{v:g}" for v in box[a]], fontsize=7)
                ax.set_yticks(box[b], [f"{v:g}" for v in box[b]], fontsize=7)
                ax.set_xlabel("xyz"[a], fontsize=8, labelpad=-6)
                ax.set_ylabel("xyz"[b], fontsize=8, labelpad=-10)
                ax.set_title(name, fontsize=9)
                views.append((ax, (a, b)))
            subfigure.subplots_adjust(left=0.05, right=0.97, top=0.86, bottom=0.1, wspace=0.14)
            panels.append(views)
        # A rule between the panels: four axes in a row would read as four of one kind.
        self.figure.add_artist(
            Line2D([0.5, 0.5], [0.1, 0.97], transform=self.figure.transFigure, color="#bbbbbb")
        )
        return panels, subfigures[1].transSubfigure

    def draw(self, t: int) -> Image.Image:
        """Frame t as an RGB image."""
        truth, prediction = self.views
        for scatter, axes in truth:
            scatter.set_offsets(self.truth[t][:, axes])
        stop = self.diverged_at
        if stop is None or t < stop:
            shown, alpha = self.predicted[t], None
            self.notice.set_text("")
        else:
            # Diverged at frame 0 would leave nothing finite to keep: then only the notice.
            shown = self.predicted[stop - 1] if stop > 0 else self.predicted[:0, 0]
            alpha = 0.25
            self.notice.set_text(f"diverged at frame {stop}")
        for scatter, axes in prediction:
            scatter.set_offsets(shown[:, axes])
            scatter.set_alpha(alpha)
        phase = "given (history)" if t < self.first_predicted else "predicted"
        when = f"  t = {t * self.dt:.3f} s" if self.dt else ""
        self.caption.set_text(f"frame {t}{when}  ({phase})")
        self.canvas.draw()
        rgba = np.asarray(self.canvas.buffer_rgba())
        return Image.fromarray(rgba[..., :3].copy())


def animation_frames(total: int, max_frames: int, diverged_at: int | None = None) -> np.ndarray:
    """The frames an animation of `total` frames shows: at most max_frames, evenly spaced,
    always with the last one and, for a prediction that diverged at frame k, frames k - 1 and
    k (its last state and the divergence), which even spacing could skip."""
    count = min(max_frames, total)
    shown = np.unique(np.linspace(0, total - 1, count).round().astype(int)).tolist()
    kept = {total - 1}
    wanted = [] if diverged_at is None else [diverged_at - 1, diverged_at]
    for frame in wanted:
        if not 0 <= frame < total:
            continue
        if frame not in shown:
            # Replace the nearest frame not already kept, so the count stays within the cap.
            free = [i for i, f in enumerate(shown) if f not in kept]
            if not free:
                break
            shown[min(free, key=lambda i: abs(shown[i] - frame))] = frame
        kept.add(frame)
    return np.array(sorted(shown))


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
    shown from two sides, front (x-y) and top (x-z), in each panel (see RolloutFigure), in a
    GIF twice as wide as 2D's. bounds: the box, (lo, hi) per axis (default: what the truth
    covers), which sets every view's limits. A prediction that diverged (NaN from some frame
    on) is shown up to there, then marked as diverged (see RolloutFigure). Frames: see
    animation_frames. Returns None, or why the MP4 was not written."""
    truth, predicted = np.asarray(truth), np.asarray(predicted)
    if truth.ndim != 3 or truth.shape != predicted.shape or truth.shape[2] < 2:
        raise ValueError(
            f"truth and predicted must be the same (T, N, D >= 2) shape, got {truth.shape} "
            f"and {predicted.shape}"
        )
    if isinstance(max_frames, bool) or not isinstance(max_frames, int) or max_frames < 1:
        raise ValueError(f"max_frames must be a positive integer, got {max_frames!r}")
    figure = RolloutFigure(truth, predicted, particle_type, bounds, titles, first_predicted, dt)
    frames = animation_frames(truth.shape[0], max_frames, figure.diverged_at)
    images = [figure.draw(t) for t in frames.tolist()]
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
