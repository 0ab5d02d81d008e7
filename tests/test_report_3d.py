"""`gns report` on 3D data end to end (a tiny hand-made free-fall dataset and a 2-step run):
its animation shows ground truth and prediction each from two sides, front (x-y) and top
(x-z), in a GIF twice as wide as a 2D one, with the box's bounds as every view's limits, and
the report's text names the views. 2D animations are drawn as before 3D views existed: pixel
for pixel against the drawing code of that time, kept here as the oracle."""

from __future__ import annotations

import numpy as np
import pytest
from gns.config import Config, ModelConfig, TrainConfig
from gns.data import open_dataset
from gns.plots import TYPE_NAMES, RolloutFigure, animation, type_colours
from gns.report import report
from gns.train import train
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba_array
from matplotlib.figure import Figure
from PIL import Image
from test_pipeline_3d import BOUNDS, DT, HISTORY, free_fall, write_free_fall

pytestmark = pytest.mark.usefixtures("torch_one_thread")

TINY = Config(
    model=ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=1, precision="fp32"),
    train=TrainConfig(steps=2, log_every=1, validate_every=0, checkpoint_every=2),
)
VIEWS = "front (x-y, y up) and top (x-z, seen from above)"


@pytest.fixture(scope="module")
def report_3d(tmp_path_factory):
    """A report (one trajectory, 4 animation frames, no MPM rows, no VTK) of a 2-step run on a
    3D free-fall dataset (h5 layout)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        root = tmp_path_factory.mktemp("report_3d")
        data = write_free_fall(root / "data", "h5", particles=24, train=1, test=1)
        train(data, root / "run", TINY, device="cpu", progress=False)
        result = report(
            root / "run",
            data,
            out=root / "report",
            trajectories=1,
            mpm=["none"],
            animation_frames=4,
            vtk_every=0,
            progress=False,
        )
    finally:
        torch.set_num_threads(threads)
    return result, data


def gif_frames(path):
    with Image.open(path) as gif:
        frames = []
        for i in range(gif.n_frames):
            gif.seek(i)
            frames.append(np.asarray(gif.convert("RGB")))
        return gif.size, frames


def test_the_3d_report_animates_two_views_and_says_which(report_3d, tmp_path):
    result, data = report_3d
    gif = result.files["gif"]
    assert gif.is_file() and gif.name == "rollout_test_0.gif"
    size, frames = gif_frames(gif)
    assert len(frames) == 4
    # Twice as wide as the 2D animation of the same frames' x-y, as high.
    (trajectory,) = open_dataset(data, "test")
    flat = trajectory.positions[..., :2]
    animation(flat, flat, trajectory.particle_type, tmp_path / "2d.gif", max_frames=2)
    width, height = gif_frames(tmp_path / "2d.gif")[0]
    assert size == (2 * width, height)
    # The text names the views; the old note that 3D was only its x-y projection is gone.
    markdown = (result.out / "report.md").read_text()
    rollout = markdown.split("## Rollout")[1].split("##")[0]
    assert f"from two sides: {VIEWS}" in rollout and "projection" not in markdown
    assert VIEWS in (result.out / "report.html").read_text()
    assert not any(VIEWS in item for item in result.left_out)


def test_a_3d_frame_shows_front_and_top_views_in_the_box():
    rng = np.random.default_rng(1)
    truth = free_fall(rng, 20, 3).positions
    types = np.array([5] * 12 + [6] * 8 + [3] * 3)
    predicted = truth + rng.normal(0.0, 0.01, truth.shape).astype(np.float32)
    predicted[10:] = np.nan
    figure = RolloutFigure(truth, predicted, types, BOUNDS, ("ground truth", "GNS"), HISTORY, DT)
    # Four axes in a row: ground truth's front and top views, then the prediction's.
    views = ["front (x-y)", "top (x-z, from above)"]
    assert [ax.get_title() for ax in figure.figure.axes] == views * 2
    assert [sub.get_suptitle() for sub in figure.figure.subfigs] == ["ground truth", "GNS"]
    assert [[axes for _, axes in panel] for panel in figure.views] == [[(0, 1), (0, 2)]] * 2
    # Limits: the metadata's box with a 5% margin; the top view looks down, so z grows downward.
    margin = [(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo)) for lo, hi in BOUNDS]
    for ax in figure.figure.axes:
        assert ax.get_xlim() == pytest.approx(margin[0])
    front, top = figure.figure.axes[:2]
    assert front.get_ylim() == pytest.approx(margin[1])
    assert top.get_ylim() == pytest.approx(margin[2][::-1])
    # The same colour per particle type in every view.
    colours = to_rgba_array(type_colours(types)[0])
    for panel in figure.views:
        for scatter, _ in panel:
            np.testing.assert_array_equal(scatter.get_facecolors(), colours)
    for t in (HISTORY, 9):
        figure.draw(t)
        for (scatter, (a, b)), (guess, _) in zip(*figure.views, strict=True):
            np.testing.assert_array_equal(scatter.get_offsets(), truth[t][:, [a, b]])
            np.testing.assert_array_equal(guess.get_offsets(), predicted[t][:, [a, b]])
        assert figure.notice.get_text() == ""
    # Diverged at frame 10: both views of the prediction keep frame 9, under the notice.
    figure.draw(12)
    assert figure.notice.get_text() == "diverged at frame 10"
    for guess, (a, b) in figure.views[1]:
        np.testing.assert_array_equal(guess.get_offsets(), predicted[9][:, [a, b]])
    assert figure.scatters == [figure.views[0][0][0], figure.views[1][0][0]]


def drawn_before_3d_views(truth, predicted, types, bounds, titles, t, first_predicted, dt):
    """Frame t of a 2D animation whose prediction did not diverge, drawn by RolloutFigure's
    code as it was before 3D views existed (copied here): the oracle that 2D is unchanged."""
    colours, legend = type_colours(types)
    figure = Figure(figsize=(8, 4.3), dpi=80)
    canvas = FigureCanvasAgg(figure)
    axes = figure.subplots(1, 2)
    limits = [(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo)) for lo, hi in bounds]
    size = float(np.clip(3000 / max(1, truth.shape[1]), 0.5, 12))
    for ax, title, positions in zip(axes, titles, (truth, predicted), strict=True):
        ax.set_xlim(*limits[0])
        ax.set_ylim(*limits[1])
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(title, fontsize=10)
        ax.scatter(positions[t, :, 0], positions[t, :, 1], s=size, c=colours, lw=0)
    for kind, colour in legend.items():
        axes[0].scatter([], [], s=20, c=colour, label=TYPE_NAMES.get(kind, f"type {kind}"))
    axes[0].legend(loc="upper right", fontsize=7, markerscale=1.0)
    figure.subplots_adjust(left=0.02, right=0.98, top=0.92, bottom=0.08, wspace=0.05)
    phase = "given (history)" if t < first_predicted else "predicted"
    figure.text(0.5, 0.02, f"frame {t}  t = {t * dt:.3f} s  ({phase})", ha="center", fontsize=9)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3]


def test_2d_animations_are_drawn_as_before():
    rng = np.random.default_rng(2)
    truth = rng.uniform(0.2, 0.8, size=(9, 30, 2)).astype(np.float32)
    predicted = truth + np.float32(0.01)
    types = np.array([5] * 20 + [6] * 7 + [3] * 3)
    bounds, titles = [[0.1, 0.9], [0.1, 0.9]], ("ground truth", "GNS")
    figure = RolloutFigure(truth, predicted, types, bounds, titles, 6, 0.01)
    assert [ax.get_title() for ax in figure.figure.axes] == list(titles)
    for t in (2, 8):
        image = np.asarray(figure.draw(t))
        np.testing.assert_array_equal(
            image, drawn_before_3d_views(truth, predicted, types, bounds, titles, t, 6, 0.01)
        )
