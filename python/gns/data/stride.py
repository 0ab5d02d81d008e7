"""Frame strides: a model trained at one frame spacing, applied to data whose frames are finer.

A GNS learns one step of its training data's frame spacing (metadata.json's dt; the model works
with dt = 1 frame), so it must be applied to frames at that spacing. Data whose frames are a
whole factor k finer is used at every k-th frame, from frame 0:

    frame_stride(model_dt, data_dt)     k = model_dt / data_dt, or ValueError naming both
    at_frame_stride(trajectory, k)      frames 0, k, 2k, ... with everything that is per frame
    describe_frame_stride(data_dt, k)   what was done, in words, for the commands to print

`gns convert --frame-stride k` writes the same frames (at_frame_stride is its subsampling), so a
rollout on the native data equals one on the converted data.
"""

from __future__ import annotations

import math

from gns.data.trajectory import Trajectory

__all__ = [
    "FRAME_SPACING_TOLERANCE",
    "at_frame_stride",
    "describe_frame_stride",
    "frame_stride",
    "frames_at_stride",
    "spacing_text",
]

# Relative: the dt of converted data is k times a float (0.0025 * 3 = 0.007500000000000001),
# and metadata.json's dt went through JSON; a real mismatch is far larger than this.
FRAME_SPACING_TOLERANCE = 1e-6


def spacing_text(seconds: float) -> str:
    """A frame spacing for people: "7.5 ms", "2 ms", "1.2 s" (7 digits: a spacing outside the
    tolerance never prints like its neighbour)."""
    return f"{seconds * 1e3:.7g} ms" if seconds < 1 else f"{seconds:.7g} s"


def _ordinal(n: int) -> str:
    """ "2nd", "3rd", "11th", "21st"."""
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"


def frame_stride(model_dt: float | None, data_dt: float) -> int:
    """Every how many frames of data at `data_dt` seconds a model that steps `model_dt` seconds
    reads: model_dt / data_dt, a whole number >= 1 within a relative FRAME_SPACING_TOLERANCE.

    model_dt None (a checkpoint written before models recorded their spacing): 1, every frame,
    as before. Data whose spacing does not divide the model's, or is coarser than it, raises
    ValueError naming both spacings and the ones the model can be applied to."""
    for name, value in (("the model's step", model_dt), ("the data's frame spacing", data_dt)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a positive number of seconds, got {value!r}")
    if model_dt is None:
        return 1
    ratio = model_dt / data_dt
    stride = round(ratio)
    if stride >= 1 and abs(ratio - stride) <= FRAME_SPACING_TOLERANCE * ratio:
        return stride
    model, data = spacing_text(model_dt), spacing_text(data_dt)
    if ratio < 1:
        problem = "its frames are farther apart than the model's step"
    else:
        problem = f"{model} is not a whole multiple of {data}"
    finer = ", ".join(spacing_text(model_dt / k) for k in (2, 3, 4))
    raise ValueError(
        f"the model steps {model} at a time, the data's frames are {data} apart: {problem}; "
        f"the model rolls out on frames {model} apart or a whole fraction of that ({finer}, "
        f"...): write the data at such a spacing, or use a model trained at a whole multiple "
        f"of {data}"
    )


def frames_at_stride(frames: int, stride: int) -> int:
    """Frames of phase k - 1 (frames k - 1, 2k - 1, ...) of `frames`: what every phase has."""
    return (frames - stride) // stride + 1


def at_frame_stride(trajectory: Trajectory, stride: int, *, phase: int = 0) -> Trajectory:
    """The trajectory at every `stride`-th frame from frame `phase`: its positions and step
    context at frames phase, phase + stride, ...; particle types, material property, key and
    source as they are. Every phase keeps as many frames as the last one has, (T - stride) //
    stride + 1 of T, so that the `stride` phases of a trajectory are equally long (what `gns
    convert --frame-stride` writes: with T not a multiple of the stride, phase 0 loses its last
    frame). stride 1 gives the trajectory itself."""
    if isinstance(stride, bool) or not isinstance(stride, int) or stride < 1:
        raise ValueError(f"the frame stride must be a whole number >= 1, got {stride!r}")
    if isinstance(phase, bool) or not isinstance(phase, int) or not 0 <= phase < stride:
        raise ValueError(f"the phase must be a whole number from 0 to {stride - 1}, got {phase!r}")
    if stride == 1:
        return trajectory
    frames = frames_at_stride(trajectory.num_frames, stride)
    if frames < 1:
        raise ValueError(
            f"frame stride {stride} needs trajectories of at least {stride} frames; trajectory "
            f"{trajectory.key} of {trajectory.source} has {trajectory.num_frames}"
        )
    picked = slice(phase, phase + (frames - 1) * stride + 1, stride)
    context = trajectory.step_context
    return Trajectory(
        trajectory.positions[picked],
        trajectory.particle_type,
        None if context is None else context[picked],
        trajectory.material_property,
        key=trajectory.key,
        source=trajectory.source,
        obstacles=trajectory.obstacles,
    )


def describe_frame_stride(data_dt: float, stride: int) -> str:
    """What a stride does to data at `data_dt`, e.g. "the data's frames are 2.5 ms apart, the
    model's steps 7.5 ms: every 3rd frame"."""
    data = spacing_text(data_dt)
    if stride == 1:
        return f"the data's frames are {data} apart, as the model's steps: every frame"
    model = spacing_text(stride * data_dt)
    every = _ordinal(stride)
    return f"the data's frames are {data} apart, the model's steps {model}: every {every} frame"
