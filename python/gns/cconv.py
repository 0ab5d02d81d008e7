"""CConv: the continuous-convolution network of Ummenhofer et al. (2020), section D.1's baseline,
as a drop-in for EncodeProcessDecode (same inputs, same normalised-acceleration output).

Section D.1 reads a continuous convolution as a graph network whose edge function is indexed by
the displacement tau_ij = x_j - x_i of sender j from receiver i:

    f'_i = b + 1 / psi(x_i) * sum_{j in N(x_i, R)} a(x_j, x_i) W(Lambda(tau_ij / R)) f_j

W is a grid of kernel_size^D weight matrices (in, out) over the cube [-1, 1]^D, read at a point
by bilinear (2D) or trilinear (3D) interpolation of the 2^D cells around it; Lambda maps the unit
ball (every neighbour lies within R) onto that cube; a is a window that fades a neighbour out as
it nears the radius; psi normalises by the neighbourhood's size (1 in the original and in D.1).

The graph is the simulator's (the Rust radius graph); the displacements come in as the first D
columns of its edge features, tau / R, so nothing here searches for neighbours. Per forward pass
the geometry (each edge's 2^D cells and their interpolation x window weights) is computed once
and shared by every layer (a Neighbourhood). A layer then sums each edge's weighted sender
features into a (N, kernel_size^D * in) array of its receiver's cells and multiplies that by the
(kernel_size^D * in, out) kernel in one matmul. The sums are index_add_, one call per corner
(implementation "plain", the reference), or one sparse (N * kernel_size^D, N) matrix built per
forward pass and applied to every layer's features (the default, "fast"); never a loop over
edges, and both run on CUDA as well.

The network, as in the original with D.1's flat-wall change (walls are the node features'
clipped wall distances, so the original's convolution over boundary particles is left out):
  layer 0   [conv(x), dense(x)] concatenated, x = [1, node features] (the constant lets the
            convolution see the neighbourhood's shape and density when velocities are 0)
  layer k   conv(relu(h)) + dense(relu(h)), plus h itself where the width stays the same
  widths    model.cconv.layer_channels (32, 64, 64 by default; layer 0's branches 32 each),
            then D: the last layer's output is the normalised acceleration, as the GNS decoder's
The original scales its output by 1/128 because it predicts a position correction in metres;
here the target is normalised to unit variance, so there is no scale.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

import gns.model
from gns.config import (
    IMPLEMENTATIONS,
    CConvConfig,
    CoordinateMapping,
    Implementation,
    ModelConfig,
    Precision,
    Window,
)

__all__ = [
    "CConv",
    "ContinuousConv",
    "Neighbourhood",
    "ball_to_cube",
    "corner_weights",
    "kernel_corners",
    "neighbourhood",
    "window_weight",
]

# Denominators of the mappings are clamped here: a zero displacement maps to zero, without a
# 0/0 that would turn into NaN in the forward or the backward pass.
_TINY = 1e-30


# ---------------------------------------------------------------------------------- geometry


def _disk_to_square(x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """The area-preserving map of the disk of radius rho onto the square of half-width rho
    (the inverse of Shirley and Chiu's concentric map): in the quarter where |x| >= |y| the
    point goes to (sign(x) rho, sign(x) rho (4 / pi) atan(y / x)); the other quarters alike."""
    rho = torch.sqrt((x * x + y * y).clamp_min(_TINY))
    x_major = x.abs() >= y.abs()
    major, minor = torch.where(x_major, x, y), torch.where(x_major, y, x)
    safe_major = torch.where(major == 0, torch.ones_like(major), major)
    along = torch.copysign(rho, major) * (major != 0)
    across = along * (4 / math.pi) * torch.atan(minor / safe_major)
    return torch.where(x_major, along, across), torch.where(x_major, across, along)


def _ball_to_cylinder(tau: Tensor) -> Tensor:
    """The first step of Griepentrog et al.'s (2008) volume-preserving map from the unit ball
    onto the cube: the ball onto the cylinder of radius 1 and height [-1, 1], volumes scaled by
    the constant 3/2. The sphere of radius r goes onto the surface of the cylinder of radius r
    and half-height r: its polar caps (5/4 z^2 > x^2 + y^2) onto the end discs, the rest onto
    the side."""
    x, y, z = tau.unbind(-1)
    rho2 = x * x + y * y
    r = torch.sqrt((rho2 + z * z).clamp_min(_TINY))
    cap = 1.25 * z * z > rho2
    cap_scale = torch.sqrt(3 * r / (r + z.abs()).clamp_min(_TINY))
    side_scale = r / torch.sqrt(rho2.clamp_min(_TINY))
    scale = torch.where(cap, cap_scale, side_scale)
    height = torch.where(cap, torch.copysign(r, z), 1.5 * z)
    return torch.stack([x * scale, y * scale, height], dim=-1)


def ball_to_cube(tau: Tensor, mapping: CoordinateMapping) -> Tensor:
    """Lambda: displacements in the unit ball (E, D), D = 2 or 3, placed in the cube [-1, 1]^D.

    "ball_to_cube_volume_preserving" (the original's): equal volumes of the ball get equal
    volumes of the cube, so every kernel cell covers an equal share of the neighbourhood; in 2D
    the inverse concentric map, in 3D Griepentrog et al.'s map (ball to cylinder about the
    z axis, then the concentric map across it). "ball_to_cube_radial": radial stretching,
    tau |tau|_2 / |tau|_inf. Both send the sphere of radius r onto the cube's surface of
    half-width r (|Lambda(tau)|_inf = |tau|_2: nearer neighbours stay nearer the centre), fix
    the centre, are continuous, and commute with 90-degree rotations and reflections of the
    axes (the volume-preserving 3D map only with those that keep the z axis).
    "identity": as given (the cube's corners stay unused).
    """
    if tau.ndim != 2 or tau.shape[1] not in (2, 3):
        raise ValueError(f"displacements must be (E, 2) or (E, 3), got {tuple(tau.shape)}")
    if mapping == "identity":
        return tau
    if mapping == "ball_to_cube_radial":
        length = torch.linalg.vector_norm(tau, dim=-1, keepdim=True)
        largest = tau.abs().amax(dim=-1, keepdim=True)
        return tau * (length / largest.clamp_min(_TINY))
    if mapping == "ball_to_cube_volume_preserving":
        if tau.shape[1] == 2:
            return torch.stack(_disk_to_square(tau[:, 0], tau[:, 1]), dim=-1)
        cylinder = _ball_to_cylinder(tau)
        x, y = _disk_to_square(cylinder[:, 0], cylinder[:, 1])
        return torch.stack([x, y, cylinder[:, 2]], dim=-1)
    raise ValueError(
        "coordinate mapping must be 'ball_to_cube_volume_preserving', 'ball_to_cube_radial' or "
        f"'identity', got {mapping!r}"
    )


def kernel_corners(cube: Tensor, kernel_size: int) -> tuple[Tensor, Tensor]:
    """The kernel cells around each point of the cube [-1, 1]^D and their bilinear / trilinear
    weights: (E, 2^D) flat cell indices (row-major over a (kernel_size,) * D grid, axis 0 most
    significant) and (E, 2^D) weights that sum to 1 per point.

    The grid's outer cells sit on the cube's faces (the original's align_corners=True): cube
    coordinate u is grid coordinate (u + 1) / 2 * (kernel_size - 1). Points a rounding error
    outside the cube are clamped onto it.
    """
    if isinstance(kernel_size, bool) or not isinstance(kernel_size, int) or kernel_size < 1:
        raise ValueError(f"kernel_size must be a whole number >= 1, got {kernel_size!r}")
    dim = cube.shape[1]
    grid = (cube.clamp(-1.0, 1.0) + 1.0) * (0.5 * (kernel_size - 1))
    lower = grid.floor().clamp(0, max(kernel_size - 2, 0))
    fraction = grid - lower  # in [0, 1]; exactly 1 on the upper face
    # (2^D, D): which corner of the cell, 0 = lower and 1 = upper along each axis.
    bits = torch.tensor(list(itertools.product((0, 1), repeat=dim)), device=cube.device)
    index = (lower.long()[:, None, :] + bits).clamp(max=kernel_size - 1)
    upper = bits.to(torch.bool)
    weight = torch.where(upper, fraction[:, None, :], 1.0 - fraction[:, None, :]).prod(dim=-1)
    strides = kernel_size ** torch.arange(dim - 1, -1, -1, device=cube.device)
    return (index * strides).sum(dim=-1), weight


def window_weight(squared_distance: Tensor, window: Window) -> Tensor:
    """a(x_j, x_i) of the squared distance / R^2: "poly6", (1 - r^2)^3 clipped at 0 (as the
    SPH poly6 kernel: 1 at the centre, 0 with zero slope at the radius), or "none", 1."""
    if window == "poly6":
        return (1.0 - squared_distance).clamp_min(0.0) ** 3
    if window == "none":
        return torch.ones_like(squared_distance)
    raise ValueError(f"window must be 'poly6' or 'none', got {window!r}")


def corner_weights(
    tau: Tensor,
    receivers: Tensor,
    num_nodes: int,
    kernel_size: int,
    mapping: CoordinateMapping = "ball_to_cube_volume_preserving",
    window: Window = "poly6",
    normalize: bool = False,
) -> tuple[Tensor, Tensor]:
    """Each edge's kernel cells and their weights, window and normalisation included: (E, 2^D)
    flat cell indices and (E, 2^D) weights a(x_j, x_i) / psi(x_i) * (interpolation weight).

    tau: (E, D) displacements x_sender - x_receiver divided by the radius R (the unit ball).
    psi(x_i) is the number of edges into i with `normalize`, else 1.
    """
    index, weight = kernel_corners(ball_to_cube(tau, mapping), kernel_size)
    weight = weight * window_weight(tau.square().sum(dim=-1), window)[:, None]
    if normalize:
        count = torch.bincount(receivers, minlength=num_nodes).clamp_min(1)
        weight = weight / count.index_select(0, receivers).to(weight.dtype)[:, None]
    return index, weight


@dataclass(frozen=True, eq=False)
class Neighbourhood:
    """The geometry of one forward pass, shared by every layer: each edge's kernel cells and
    weights (see corner_weights), and with implementation "fast" the same as one sparse
    (N * cells, N) matrix, so each layer's sums are one sparse-dense product.

    `cell_sums(features)` is (N, cells * C): for receiver i and cell c, the sum over edges
    j -> i of weight * f_j (zero where no edge touches the cell). Both implementations give it
    up to float round-off: "plain" scatters each corner's weighted sender features with
    index_add_ (2^D calls), "fast" multiplies by the coalesced matrix (on a 2-core CPU about
    twice as fast over a whole forward and backward pass, the build included).
    """

    num_nodes: int
    cells: int
    senders: Tensor
    receivers: Tensor
    corner_index: Tensor
    corner_weight: Tensor
    matrix: Tensor | None = None

    def cell_sums(self, features: Tensor) -> Tensor:
        n, channels = features.shape
        if n != self.num_nodes:
            raise ValueError(f"features must have {self.num_nodes} rows, got {n}")
        # In at least float32 even under autocast: a bfloat16 sum would round away the small
        # contributions of far neighbours; only the kernel's matmul runs in bfloat16.
        dtype = torch.promote_types(features.dtype, torch.float32)
        with torch.autocast(features.device.type, enabled=False):
            features = features.to(dtype)
            if self.matrix is not None:
                sums = torch.sparse.mm(self.matrix.to(dtype), features)
            else:
                gathered = features.index_select(0, self.senders)
                weight = self.corner_weight.to(dtype)
                slots = self.receivers * self.cells
                sums = features.new_zeros(n * self.cells, channels)
                for corner in range(self.corner_index.shape[1]):
                    source = gathered * weight[:, corner, None]
                    sums.index_add_(0, slots + self.corner_index[:, corner], source)
        return sums.reshape(n, self.cells * channels)


def neighbourhood(
    tau: Tensor,
    senders: Tensor,
    receivers: Tensor,
    num_nodes: int,
    settings: CConvConfig,
    implementation: Implementation = "fast",
) -> Neighbourhood:
    """The Neighbourhood of a graph: tau (E, D) the displacements / R, senders and receivers
    (E,) int64, num_nodes N; settings: model.cconv; implementation "fast" or "plain"."""
    if implementation not in IMPLEMENTATIONS:
        raise ValueError(f"implementation must be 'fast' or 'plain', got {implementation!r}")
    index, weight = corner_weights(
        tau,
        receivers,
        num_nodes,
        settings.kernel_size,
        settings.coordinate_mapping,
        settings.window,
        settings.normalize,
    )
    cells = settings.kernel_size ** tau.shape[1]
    matrix = None
    if implementation == "fast":
        rows = (receivers[:, None] * cells + index).reshape(-1)
        columns = senders[:, None].expand_as(index).reshape(-1)
        matrix = torch.sparse_coo_tensor(
            torch.stack([rows, columns]),
            weight.reshape(-1),
            (num_nodes * cells, num_nodes),
            check_invariants=False,  # built from valid indices; the check costs a pass
        ).coalesce()  # sums the duplicates of kernel_size 1 and sorts the rows, once
    return Neighbourhood(num_nodes, cells, senders, receivers, index, weight, matrix)


# ---------------------------------------------------------------------------------- layers


class ContinuousConv(nn.Module):
    """One continuous convolution: f'_i = b + sum over edges j -> i and their 2^D cells c of
    weight W_c f_j (see corner_weights), i.e. cell_sums (N, cells * in) times the kernel.

    kernel: (kernel_size,) * D + (in_channels, out_channels), one matrix per grid cell,
    initialised like nn.Linear (uniform within 1 / sqrt(in_channels)) cell by cell.
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int, dim: int) -> None:
        super().__init__()
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        self.kernel = nn.Parameter(torch.empty((kernel_size,) * dim + (in_channels, out_channels)))
        self.bias = nn.Parameter(torch.empty(out_channels))
        bound = 1.0 / math.sqrt(in_channels)
        nn.init.uniform_(self.kernel, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, features: Tensor, neighbourhood: Neighbourhood) -> Tensor:
        """features (N, in) -> (N, out)."""
        *grid, channels, _ = self.kernel.shape
        if neighbourhood.cells != math.prod(grid) or features.shape[-1] != channels:
            raise ValueError(
                f"this layer has a {'x'.join(map(str, grid))} kernel over {channels} channels; "
                f"got {neighbourhood.cells} cells and {features.shape[-1]} channels"
            )
        kernel = self.kernel.reshape(-1, self.kernel.shape[-1])
        return F.linear(neighbourhood.cell_sums(features), kernel.t(), self.bias)


# ---------------------------------------------------------------------------------- network


class CConv(nn.Module):
    """Section D.1's CConv baseline with the call contract of EncodeProcessDecode.

    node_input_size: width of the node features (from the scene, see simulator.py).
    output_size: D, the acceleration's dimension; the edge features' first D columns must be
        the displacement x_sender - x_receiver divided by the connectivity radius.
    config: the ModelConfig (model.cconv, model.implementation and model.precision are read).

    How it runs may be changed on the module, as on EncodeProcessDecode: `implementation`
    ("fast": the neighbourhood as one sparse matrix; "plain": index_add_, the readable
    reference; the same function and parameters) and `precision` ("auto", "fp32", "bf16").
    """

    def __init__(self, node_input_size: int, output_size: int, config: ModelConfig) -> None:
        super().__init__()
        if output_size not in (2, 3):
            raise ValueError(f"CConv works in 2 or 3 dimensions, got output_size {output_size}")
        settings = config.cconv
        self.config = config
        self.dim = output_size
        self.precision: Precision = config.precision
        self.implementation: Implementation = config.implementation
        dim, size = output_size, settings.kernel_size
        inputs = node_input_size + 1  # the constant 1 (see the module docstring)
        first = settings.layer_channels[0]
        self.conv0 = ContinuousConv(inputs, first, size, dim)
        self.dense0 = nn.Linear(inputs, first)
        widths = [2 * first, *settings.layer_channels[1:], output_size]
        pairs = list(itertools.pairwise(widths))
        self.convs = nn.ModuleList(ContinuousConv(a, b, size, dim) for a, b in pairs)
        self.denses = nn.ModuleList(nn.Linear(a, b) for a, b in pairs)

    def forward(
        self,
        node_features: Tensor,
        edge_features: Tensor,
        senders: Tensor,
        receivers: Tensor,
        global_features: Tensor | None = None,
        n_node: Tensor | None = None,
    ) -> Tensor:
        """node_features (N, node_input_size), edge_features (E, >= D) whose first D columns
        are the displacements / R, senders and receivers (E,) int64. Returns the normalised
        acceleration (N, D), at least float32. n_node is accepted for EncodeProcessDecode's
        contract and unused (several graphs are one disjoint graph); there is no global input
        (the simulator appends the context to the nodes unless model.global_latent)."""
        if global_features is not None:
            raise ValueError(
                "CConv has no global input; the context is appended to the node features "
                "(model.global_latent is a GNS setting)"
            )
        if edge_features.ndim != 2 or edge_features.shape[1] < self.dim:
            raise ValueError(
                f"edge_features must be (E, >= {self.dim}) with the displacement / R in the "
                f"first {self.dim} columns, got {tuple(edge_features.shape)}"
            )
        n = node_features.shape[0]
        tau = edge_features[:, : self.dim]
        graph = neighbourhood(tau, senders, receivers, n, self.config.cconv, self.implementation)
        with gns.model.precision_context(self.precision, node_features.device):
            x = torch.cat([node_features.new_ones(n, 1), node_features], dim=-1)
            h = torch.cat([self.conv0(x, graph), self.dense0(x)], dim=-1)
            h = gns.model.at_least_fp32(h)
            for conv, dense in zip(self.convs, self.denses, strict=True):
                y = torch.relu(h)
                update = gns.model.at_least_fp32(conv(y, graph) + dense(y))
                # A residual wherever a layer keeps the width, as in the original.
                h = h + update if update.shape == h.shape else update
        return h
