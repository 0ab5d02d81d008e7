"""Input noise of sections B.3 and C.2: velocity noise, positions adjusted to match.

Every function takes a position sequence (N, C + 1, D) and returns position noise of the same
shape. The noise is drawn on the C input velocities and integrated into positions (the first
position is left as it is), so velocity_k = p_k - p_{k-1} of the noisy sequence is exactly the
clean velocity plus the velocity noise. Each type is scaled so the velocity noise at the last
input step has standard deviation `std` (C.2: "the variance of the velocity noise at the last
step is constant"). Kinematic particles get no noise.

    only_last     noise on the most recent velocity only
    correlated    one draw per particle and axis, the same for all C velocities
    uncorrelated  an independent draw for each velocity
    random_walk   independent increments of std / sqrt(C), summed over the steps (the default)
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from gns.config import NoiseConfig

__all__ = [
    "NOISE_FUNCTIONS",
    "correlated",
    "only_last",
    "random_walk",
    "sample_noise",
    "uncorrelated",
    "wall_push",
]


def _draw(shape: tuple[int, ...], like: Tensor, std: float, generator: torch.Generator | None):
    noise = torch.randn(shape, generator=generator, dtype=like.dtype, device=like.device)
    return noise * std


def _integrate(
    position_sequence: Tensor, velocity_noise: Tensor, kinematic: Tensor | None
) -> Tensor:
    """Position noise whose finite differences are `velocity_noise` (N, C, D)."""
    first = torch.zeros_like(position_sequence[:, :1])
    noise = torch.cat([first, torch.cumsum(velocity_noise, dim=1)], dim=1)
    if kinematic is not None:
        noise = noise * (~kinematic.to(torch.bool)).to(noise.dtype)[:, None, None]
    return noise


def _velocity_shape(position_sequence: Tensor) -> tuple[int, int, int]:
    if position_sequence.ndim != 3 or position_sequence.shape[1] < 2:
        raise ValueError(
            "position_sequence must be (N, C + 1, D) with C >= 1, got "
            f"{tuple(position_sequence.shape)}"
        )
    n, steps, d = position_sequence.shape
    return n, steps - 1, d


def random_walk(
    position_sequence: Tensor,
    std: float = 3e-4,
    *,
    kinematic: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Velocity noise as a random walk over the C steps; std at the last step."""
    n, c, d = _velocity_shape(position_sequence)
    increments = _draw((n, c, d), position_sequence, std / math.sqrt(c), generator)
    return _integrate(position_sequence, torch.cumsum(increments, dim=1), kinematic)


def uncorrelated(
    position_sequence: Tensor,
    std: float = 3e-4,
    *,
    kinematic: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Independent velocity noise of std `std` on each of the C steps."""
    n, c, d = _velocity_shape(position_sequence)
    return _integrate(
        position_sequence, _draw((n, c, d), position_sequence, std, generator), kinematic
    )


def correlated(
    position_sequence: Tensor,
    std: float = 3e-4,
    *,
    kinematic: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """One velocity noise draw per particle and axis, applied to all C steps."""
    n, c, d = _velocity_shape(position_sequence)
    velocity_noise = _draw((n, 1, d), position_sequence, std, generator).expand(n, c, d)
    return _integrate(position_sequence, velocity_noise, kinematic)


def only_last(
    position_sequence: Tensor,
    std: float = 3e-4,
    *,
    kinematic: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Velocity noise on the most recent step only (moves only the most recent position)."""
    n, c, d = _velocity_shape(position_sequence)
    velocity_noise = torch.zeros(
        n, c, d, dtype=position_sequence.dtype, device=position_sequence.device
    )
    velocity_noise[:, -1] = _draw((n, d), position_sequence, std, generator)
    return _integrate(position_sequence, velocity_noise, kinematic)


NOISE_FUNCTIONS: dict[str, Callable[..., Tensor]] = {
    "random_walk": random_walk,
    "only_last": only_last,
    "correlated": correlated,
    "uncorrelated": uncorrelated,
}


def sample_noise(
    config: NoiseConfig,
    position_sequence: Tensor,
    *,
    n_node: Tensor | None = None,
    kinematic: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Position noise (N, C + 1, D) of the configured type and std; with
    config.exact_last_position the same velocity noise, shifted so the most recent position
    has none; with config.std_min, each window's (the n_node (B,) particles of each, in order;
    None: one window) scaled to a std drawn uniformly from [std_min, std]."""
    function = NOISE_FUNCTIONS[config.type]
    noise = function(position_sequence, config.std, kinematic=kinematic, generator=generator)
    if config.exact_last_position:
        # A shift common to all C + 1 positions leaves their differences, the velocities, as drawn.
        noise = noise - noise[:, -1:]
    if config.std_min is not None and config.std > 0:
        counts = torch.as_tensor([len(noise)] if n_node is None else n_node).to(noise.device)
        if int(counts.sum()) != len(noise):
            raise ValueError(f"n_node sums to {int(counts.sum())}, not the {len(noise)} particles")
        u = torch.rand(len(counts), generator=generator, dtype=noise.dtype, device=noise.device)
        std = config.std_min + (config.std - config.std_min) * u
        noise = noise * torch.repeat_interleave(std / config.std, counts)[:, None, None]
    return noise


def wall_push(
    last_position: Tensor,
    bounds: Tensor,
    axes: tuple[int, ...],
    radius: float,
    std: float,
    *,
    through_only: bool = False,
    kinematic: Tensor | None = None,
    generator: torch.Generator | None = None,
) -> Tensor:
    """A shift (N, D) into the walls (NoiseConfig.wall_push): each free particle closer than
    `radius` to the lower or upper wall of one of `axes` (last_position (N, D), bounds (D, 2))
    is moved into it by |N(0, std radius)|. The training target stays the true next position,
    so the model learns to push a particle that is inside a wall back out, which no trajectory
    of the data shows: it is where a learned rollout's sand sinks through a floor.

    through_only keeps only the shifts that take a particle past the wall: a particle left
    inside the box keeps its own target, so the model is not taught a push on the layer at a
    wall that the data does not have (NoiseConfig.wall_push_through_only)."""
    shift = torch.zeros_like(last_position)
    for axis in axes:
        for side, sign in ((0, -1.0), (1, 1.0)):
            gap = sign * (bounds[axis, side].to(last_position) - last_position[:, axis])
            depth = _draw((last_position.shape[0],), last_position, std * radius, generator).abs()
            near = depth > gap if through_only else gap < radius
            shift[:, axis] += torch.where(near, sign * depth, 0.0)
    if kinematic is not None:
        shift = shift * (~kinematic.to(torch.bool)).to(shift.dtype)[:, None]
    return shift
