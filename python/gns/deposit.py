"""Where the sand stops: the deposit of a granular flow (runout, fronts, pile height, packing).

The deposit answers what a geotechnical user asks of a granular model: where does the sand stop
and how high does it pile. All three are robust percentiles (1st and 99th, linear
interpolation between order statistics) over the particles a mask selects, in position units:
`runout_extent` (the 99th minus the 1st percentile of x in one frame: how wide the deposit is),
`front_positions` (those two percentiles of x in every frame: how the fronts advance) and
`pile_height` (the 99th percentile of y in one frame above a floor, `pile_floor`), with
`pile_base` (the 1st percentile: a pile resting on the floor reads about 0). They need no
particle correspondence, so they compare any two simulators of the same scene. `deposit` gathers
them for a rollout's last frame with `mean_neighbours` (how densely it packs, also frame by
frame; the radius search is the Rust core's), and `deposit_ratios` sets them against the ground
truth's.

All functions take numpy arrays (anything `np.asarray` accepts), compute in float64 and return
Python floats or float64 arrays; a diverged (non-finite) frame raises ValueError or, with
nonfinite="inf", scores inf, as in gns.metrics.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from gns.metric_inputs import (
    FloatArray,
    Nonfinite,
    check_nonfinite,
    finite_frames,
    finite_points,
    float_array,
    particle_mask,
)

__all__ = [
    "DEPOSIT_CURVES",
    "DEPOSIT_FIGURES",
    "FRONT_CURVES",
    "deposit",
    "deposit_ratios",
    "front_positions",
    "mean_neighbours",
    "pile_base",
    "pile_floor",
    "pile_height",
    "ratio_of",
    "runout_extent",
]

# The robust ends of the sand: the 1st and 99th percentiles, so that the 1% of particles
# farthest out on either side (a few grains thrown loose) do not set how wide or high it is.
DEPOSIT_PERCENTILES = (1.0, 99.0)
# x runs along the floor, y up (gravity along -y) in this project's scenes and DeepMind's 2D
# datasets: runout is measured along axis 0, height along axis 1.
RUNOUT_AXIS, HEIGHT_AXIS = 0, 1


def _percentiles(values: FloatArray, axis: int = -1) -> FloatArray:
    """The DEPOSIT_PERCENTILES of `values` along `axis` (first axis of the result: 1st, 99th),
    interpolated linearly between order statistics."""
    result: FloatArray = np.percentile(values, DEPOSIT_PERCENTILES, axis=axis, method="linear")
    return result


def _selected_frame(
    name: str, positions: ArrayLike, mask: ArrayLike | None, axis: int, nonfinite: str
) -> FloatArray | None:
    """The coordinate `axis` of the particles of one frame (N, D) selected by mask; None when
    one of their positions is non-finite and nonfinite == "inf" (raises for "raise")."""
    check_nonfinite(nonfinite)
    frame = float_array(name, positions, "(N, D)", 2)
    if frame.shape[1] <= axis:
        raise ValueError(f"{name} needs at least {axis + 1} dimensions, got {frame.shape}")
    selected = frame[particle_mask(mask, frame.shape[0])]
    if not np.isfinite(selected).all():
        if nonfinite == "raise":
            raise ValueError(
                f"{name} holds NaN or Inf: the rollout diverged; pass nonfinite='inf' to score "
                "it as inf"
            )
        return None
    return selected[:, axis]


def runout_extent(
    positions: ArrayLike, mask: ArrayLike | None = None, *, nonfinite: Nonfinite = "raise"
) -> float:
    """How wide the deposit is: the 99th minus the 1st percentile of x (axis 0) over the
    particles of one frame, positions (N, D), selected by `mask` (N,) bool (default all; pass
    the non-kinematic ones), in position units.

    Percentiles interpolate linearly between order statistics (numpy's default, Hyndman and
    Fan's type 7): of M sorted values v_0 <= ... <= v_{M-1} the p-th percentile lies at index
    p / 100 * (M - 1). The 1% of particles farthest out on either side do not count, so a few
    grains thrown loose do not set the width. A selected particle with a non-finite position
    raises ValueError, or with nonfinite="inf" gives inf.
    """
    x = _selected_frame("positions", positions, mask, RUNOUT_AXIS, nonfinite)
    if x is None:
        return math.inf
    low, high = _percentiles(x)
    return float(high - low)


def front_positions(
    trajectory: ArrayLike, mask: ArrayLike | None = None, *, nonfinite: Nonfinite = "raise"
) -> FloatArray:
    """Where the sand's fronts are in every frame of trajectory (T, N, D): (T, 2), column 0
    the 1st and column 1 the 99th percentile of x (axis 0) over the particles selected by
    `mask` (N,) bool, interpolated as in `runout_extent` (whose value for a frame is column 1
    minus column 0). For a pile spreading both ways these are its left and right fronts.

    A frame in which a selected particle has a non-finite position raises ValueError, or with
    nonfinite="inf" is (inf, inf).
    """
    check_nonfinite(nonfinite)
    frames = float_array("trajectory", trajectory, "(T, N, D)", 3)
    selected = frames[:, particle_mask(mask, frames.shape[1])]
    finite = finite_frames("trajectory", selected, nonfinite)
    fronts = np.full((frames.shape[0], 2), np.inf)
    if finite.any():
        fronts[finite] = _percentiles(selected[finite, :, RUNOUT_AXIS], axis=1).T
    return fronts


def _above_floor(
    positions: ArrayLike, mask: ArrayLike | None, floor: float, nonfinite: Nonfinite
) -> tuple[float, float]:
    """The 1st and 99th percentiles of y (axis 1) of the selected particles of one frame
    minus `floor`; (inf, inf) for a non-finite frame under nonfinite="inf"."""
    if not math.isfinite(floor):
        raise ValueError(f"floor must be a finite number, got {floor}")
    y = _selected_frame("positions", positions, mask, HEIGHT_AXIS, nonfinite)
    if y is None:
        return math.inf, math.inf
    low, high = _percentiles(y) - floor
    return float(low), float(high)


def pile_height(
    positions: ArrayLike,
    mask: ArrayLike | None,
    floor: float,
    *,
    nonfinite: Nonfinite = "raise",
) -> float:
    """How high the deposit piles: the 99th percentile of y (axis 1; D >= 2) over the particles
    of one frame, positions (N, D), selected by `mask` (N,) bool (None: all), minus `floor`
    (see `pile_floor`), in position units. Interpolated as in `runout_extent`; the 1% of
    particles highest up (grains thrown loose, a few riding on top) do not count. A selected
    particle with a non-finite position raises ValueError, or with nonfinite="inf" gives inf.
    """
    return _above_floor(positions, mask, floor, nonfinite)[1]


def pile_base(
    positions: ArrayLike,
    mask: ArrayLike | None,
    floor: float,
    *,
    nonfinite: Nonfinite = "raise",
) -> float:
    """Where the deposit's bottom is: the 1st percentile of y over the selected particles of
    one frame, minus `floor`, as `pile_height` takes the 99th. Sand resting on the floor reads
    about 0 (a fraction of the particle spacing); a model that holds its pile up off the floor
    reads the gap, which `pile_height` alone would count as height."""
    return _above_floor(positions, mask, floor, nonfinite)[0]


def pile_floor(bounds: Sequence[Sequence[float]] | None, first_frame: ArrayLike) -> float:
    """The floor `pile_height` measures from: the lower y bound of the scene's box, bounds
    (D pairs (lo, hi)), when there is one; otherwise the lowest y of any particle of
    `first_frame` (N, D), frame 0 of the ground truth, kinematic particles included (a floor
    made of boundary particles is the floor)."""
    if bounds is not None:
        box = np.asarray(bounds, dtype=np.float64)
        if box.ndim != 2 or box.shape[1] != 2 or box.shape[0] <= HEIGHT_AXIS:
            raise ValueError(f"bounds must be D >= 2 pairs (lo, hi), got {box.tolist()}")
        return float(box[HEIGHT_AXIS, 0])
    frame = finite_points("first_frame", first_frame)
    if frame.shape[1] <= HEIGHT_AXIS:
        raise ValueError(f"first_frame needs at least 2 dimensions, got {frame.shape}")
    return float(frame[:, HEIGHT_AXIS].min())


# The figures of `deposit` and `deposit_ratios` (scalars) and the fronts of `deposit` (curves).
DEPOSIT_FIGURES = (
    "runout",
    "pile_height",
    "pile_base",
    "neighbours",
    "runout_ratio",
    "height_ratio",
    "density_ratio",
    "density_ratio_max",
)
FRONT_CURVES = ("front_x_p1", "front_x_p99")
DEPOSIT_CURVES = (*FRONT_CURVES, "neighbours_by_frame")
# Each ratio of `deposit_ratios` and the figure of `deposit` it compares.
_RATIOS = {"runout_ratio": "runout", "height_ratio": "pile_height", "density_ratio": "neighbours"}


def deposit(
    positions: ArrayLike,
    mask: ArrayLike,
    floor: float | None,
    *,
    radius: float | None = None,
    bounds: Sequence[Sequence[float]] | None = None,
    periodic: Sequence[bool] | None = None,
) -> dict[str, Any]:
    """Where the sand of a rollout, positions (S, N, D), ends up, over the particles in `mask`
    (N,) bool (the non-kinematic ones), from its last frame:

      runout        runout_extent: the 99th minus the 1st percentile of x, how wide it lies
      pile_height   pile_height: the 99th percentile of y minus `floor` (see
                    pile_floor); only with a floor and D >= 2
      pile_base     pile_base: the 1st percentile of y minus `floor` (about 0 for sand
                    resting on the floor); as pile_height
      neighbours    mean_neighbours: other particles within `radius` per particle (minimum
                    image on `periodic` axes of `bounds`); only with a radius
      front_x_p1, front_x_p99
                    (S,) arrays: the 1st and the 99th percentile of x in every frame
                    (front_positions), how the fronts advance
      neighbours_by_frame
                    (S,) array: mean_neighbours of every frame, how the packing evolves (a
                    landing packs sand that the last frame may no longer show); with a radius

    A rollout whose last frame is not finite (it diverged) has inf for the three scalars, and
    inf fronts and neighbours in every non-finite frame.
    """
    frames = float_array("positions", positions, "(S, N, D)", 3)
    keep = particle_mask(mask, frames.shape[1])
    last = frames[-1]
    fronts = front_positions(frames, keep, nonfinite="inf")
    figures: dict[str, Any] = {"runout": runout_extent(last, keep, nonfinite="inf")}
    if floor is not None and frames.shape[-1] > HEIGHT_AXIS:
        figures["pile_height"] = pile_height(last, keep, floor, nonfinite="inf")
        figures["pile_base"] = pile_base(last, keep, floor, nonfinite="inf")
    figures.update(front_x_p1=fronts[:, 0], front_x_p99=fronts[:, 1])
    if radius is not None:
        selected = frames[:, keep]
        finite = finite_frames("positions", selected, "inf")
        packed = np.full(len(frames), math.inf)  # a non-finite frame, as for the fronts
        for i in np.flatnonzero(finite):
            packed[i] = mean_neighbours(selected[i], radius, bounds, periodic)
        figures["neighbours"] = float(packed[-1])
        figures["neighbours_by_frame"] = packed
    return figures


def ratio_of(ours: float, reference: float) -> float:
    """ours / reference; with a reference of 0 (nothing to divide by), 1 when ours is 0 too,
    else inf: never NaN."""
    if reference == 0:
        return 1.0 if ours == 0 else math.inf
    return ours / reference


def deposit_ratios(ours: dict[str, Any], truth: dict[str, Any]) -> dict[str, float]:
    """Two `deposit`s compared, ours over the ground truth's, for the figures both have:
    runout_ratio (runout), height_ratio (pile_height) and density_ratio (neighbours). 1 is
    right; a simulator that loses volume packs its particles ever closer (density_ratio above
    1) and often spreads too little (runout_ratio below 1); inf: ours diverged. Where both
    have neighbours_by_frame over the same frames, density_ratio_max: the largest of the
    frame-by-frame ratios, how far it packs at its worst (a landing), which the last frame's
    density_ratio may not show once the pile relaxes."""
    ratios = {
        ratio: ratio_of(float(ours[key]), float(truth[key]))
        for ratio, key in _RATIOS.items()
        if key in ours and key in truth
    }
    curves = [np.asarray(d.get("neighbours_by_frame", ())) for d in (ours, truth)]
    if len(curves[0]) and curves[0].shape == curves[1].shape:
        ratios["density_ratio_max"] = float(max(map(ratio_of, *curves)))
    return ratios


def mean_neighbours(
    positions: ArrayLike,
    radius: float,
    bounds: Sequence[Sequence[float]] | None = None,
    periodic: Sequence[bool] | None = None,
) -> float:
    """The mean number of other particles within `radius` of a particle of one frame (N, D),
    minimum image on periodic axes: how densely the frame is packed."""
    from gns import radius_graph

    x = np.asarray(positions, dtype=np.float64)
    if len(x) == 0:
        return 0.0
    kwargs: dict[str, Any] = {"self_edges": False}
    if periodic is not None and any(periodic):
        if bounds is None:
            raise ValueError("mean_neighbours: periodic axes need the bounds of the box")
        box = np.asarray(bounds, dtype=np.float64)
        x = x - box[:, 0]
        kwargs.update(box=(box[:, 1] - box[:, 0]).tolist(), periodic=list(periodic))
    return radius_graph(x, radius, **kwargs).shape[1] / len(x)
