"""The overburden: what lies above each particle, an input no neighbourhood can give.

A 7.5 ms sand step stops a landing block in one step, and a block standing on the floor
collapses harder the taller it is: both depend on the column above a particle (its weight, and
the momentum still coming down), 13 R and more above the base, while the network's influence
fades within 2-3 hops (docs/probes.md, "reach"). This feature hands the column over directly:
for each particle i, over the free particles j in the vertical column above it (up = against
gravity; the column's half-width is `half_width`),

    count_i    = |{j : (x_j - x_i) . up > 0, lateral distance < half_width}|
    momentum_i = sum over those j of v_j . up   (their most recent velocity, per frame)

Measured on sand (docs/sand-ablation.md, session 31): the network reads it and a settled pile
is no longer pushed up, but the collapse and the landing's launch did not need it (a model
without it learns the collapse from data that weighs it). Off by default (scene.overburden).

Graphs of a batch are kept apart (n_node). The candidates of each particle are those within
half_width along one lateral axis: after a sort along it, a contiguous run (searchsorted), so the
work is N times a column's population, not N^2.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch import Tensor

__all__ = ["overburden"]

# Candidate pairs handled at once: bounds the memory of a dense 3D scene's slabs.
_PAIRS = 1 << 22


def overburden(
    position: Tensor,
    velocity: Tensor,
    up: Tensor,
    half_width: float,
    free: Tensor,
    n_node: Tensor | None = None,
) -> Tensor:
    """(N, 2): the count of free particles in the column above each particle and the sum of
    their velocity along `up`.

    position, velocity: (N, D); up: (D,), any length > 0 (normalised here); half_width: the
    column's lateral half-width (> 0); free: (N,) bool, the particles that count (kinematic
    ones carry no weight); n_node: particles per graph (None: one graph)."""
    n, dim = position.shape
    if velocity.shape != (n, dim) or up.shape != (dim,) or free.shape != (n,):
        raise ValueError(
            f"overburden needs position and velocity (N, D), up (D,) and free (N,); got "
            f"{tuple(position.shape)}, {tuple(velocity.shape)}, {tuple(up.shape)}, "
            f"{tuple(free.shape)}"
        )
    if not half_width > 0:
        raise ValueError(f"overburden's half_width must be positive, got {half_width}")
    norm = torch.linalg.vector_norm(up)
    if not norm > 0:
        raise ValueError("overburden needs a nonzero up direction (the scene's gravity)")
    up = (up / norm).to(position.dtype)
    height = position @ up
    lift = velocity @ up
    # A lateral axis: the coordinate axis least aligned with up, made perpendicular to it.
    axis = torch.zeros_like(up)
    axis[torch.argmin(up.abs())] = 1.0
    lateral = axis - (axis @ up) * up
    lateral = lateral / torch.linalg.vector_norm(lateral)
    side = position @ lateral
    out = torch.zeros(n, 2, dtype=position.dtype, device=position.device)
    counts = [n] if n_node is None else [int(c) for c in n_node]
    if sum(counts) != n:
        raise ValueError(f"n_node sums to {sum(counts)} but there are {n} particles")
    start = 0
    for size in counts:
        end = start + size
        for i, j in _strip_pairs(side[start:end], half_width):
            i, j = i + start, j + start
            d = position[j] - position[i]
            above = height[j] - height[i]
            beside2 = (d * d).sum(-1) - above * above
            keep = (above > 0) & (beside2 < half_width * half_width) & free[j]
            i, j = i[keep], j[keep]
            out[:, 0].index_add_(0, i, torch.ones_like(height[j]))
            out[:, 1].index_add_(0, i, lift[j])
        start = end
    return out


def _strip_pairs(side: Tensor, half_width: float) -> Iterator[tuple[Tensor, Tensor]]:
    """All (i, j), i != j, with |side_j - side_i| < half_width, about _PAIRS pairs at a time:
    sorted along `side`, each i's partners are one run of the sorted order."""
    order = torch.argsort(side)
    sorted_side = side[order]
    lo = torch.searchsorted(sorted_side, sorted_side - half_width, side="right")
    hi = torch.searchsorted(sorted_side, sorted_side + half_width, side="left")
    length = hi - lo
    end = torch.cumsum(length, 0)
    # Rows [cuts[k], cuts[k + 1]) hold about _PAIRS pairs (a longer run is a chunk alone).
    total = int(end[-1]) if len(end) else 0
    marks = torch.tensor(range(_PAIRS, total, _PAIRS), dtype=end.dtype, device=end.device)
    cuts = [0, *torch.searchsorted(end, marks, side="right").tolist(), side.shape[0]]
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        if a == b:
            continue
        run = length[a:b]
        rows = torch.repeat_interleave(torch.arange(a, b, device=side.device), run)
        first = end[a:b] - run
        cols = (
            lo[rows] + torch.arange(rows.shape[0], device=side.device) + first[0] - first[rows - a]
        )
        i, j = order[rows], order[cols]
        yield i[i != j], j[i != j]
