"""CConv (section D.1's baseline, gns.cconv): kernel interpolation against hand-computed values,
the ball-to-cube mappings (onto the cube, continuous, centre to centre, radial ordering, volume
preservation, 90-degree rotations permuting the kernel's cells), a layer with one non-zero
kernel cell against a brute-force message sum, the two implementations, permutation
equivariance, config parsing and its errors, the multi-step loss by hand, and training,
checkpoints, rollout, eval and report with a CConv."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from data_helpers import metadata_dict, write_metadata
from gns import cli
from gns.cconv import (
    CConv,
    ContinuousConv,
    ball_to_cube,
    corner_weights,
    kernel_corners,
    neighbourhood,
    window_weight,
)
from gns.checkpoints import load_checkpoint, load_simulator
from gns.config import (
    CConvConfig,
    Config,
    ModelConfig,
    NoiseConfig,
    TrainConfig,
    from_dict,
    load_config,
    to_dict,
)
from gns.data.h5 import write_h5
from gns.report import report
from gns.rollout import rollout
from gns.simulator import LearnedSimulator, Scene
from gns.train import TrainingStep, train
from test_train import damped_motion

pytestmark = pytest.mark.usefixtures("torch_one_thread")

ROOT = Path(__file__).resolve().parents[1]
MAPPINGS = ("ball_to_cube_volume_preserving", "ball_to_cube_radial")
SMALL = CConvConfig(layer_channels=(8, 8), kernel_size=3)
TINY = ModelConfig(kind="cconv", cconv=SMALL, precision="fp32")


def in_ball(rng: np.random.Generator, count: int, dim: int) -> torch.Tensor:
    """Uniform points in the unit ball (float64)."""
    direction = rng.normal(size=(count, dim))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = rng.uniform(size=(count, 1)) ** (1 / dim)
    return torch.from_numpy(direction * radius)


def random_graph(rng: np.random.Generator, n: int, radius: float, dim: int = 2):
    """Particles in a box and every pair within the radius (self edges too): senders,
    receivers and the displacements / radius."""
    x = rng.uniform(0, 3 * radius, size=(n, dim))
    pairs = [(j, i) for i in range(n) for j in range(n) if np.linalg.norm(x[j] - x[i]) <= radius]
    senders = torch.tensor([p[0] for p in pairs])
    receivers = torch.tensor([p[1] for p in pairs])
    tau = torch.from_numpy((x[senders] - x[receivers]) / radius)
    return x, senders, receivers, tau


# ---------------------------------------------------------------------------------- interpolation


def test_kernel_corners_match_hand_computed_cells_and_weights():
    # 4 cells per axis over [-1, 1] with the outer cells on the faces: grid coordinate
    # g = (u + 1) / 2 * 3, cells floor(g) and floor(g) + 1, weights 1 - frac and frac.
    cube = torch.tensor([[0.0, 0.0], [0.5, -0.5], [1.0, 1.0], [-1.0, 1 / 3]], dtype=torch.float64)
    index, weight = kernel_corners(cube, 4)
    # Flat index = 4 i + j; corners in the order (lo, lo), (lo, hi), (hi, lo), (hi, hi).
    # (0, 0): g = (1.5, 1.5), the four middle cells, 1/4 each.
    assert index[0].tolist() == [5, 6, 9, 10]
    assert weight[0].tolist() == [0.25] * 4
    # (0.5, -0.5): g = (2.25, 0.75): cells (2, 0), (2, 1), (3, 0), (3, 1), weights
    # 0.75 * 0.25, 0.75 * 0.75, 0.25 * 0.25, 0.25 * 0.75.
    assert index[1].tolist() == [8, 9, 12, 13]
    torch.testing.assert_close(weight[1], torch.tensor([0.1875, 0.5625, 0.0625, 0.1875]).double())
    # The cube's corner (1, 1) is the last cell alone.
    assert float(weight[2][index[2] == 15].sum()) == 1.0
    # (-1, 1/3): g = (0, 2): exactly cell (0, 2).
    assert float(weight[3][index[3] == 2].sum()) == pytest.approx(1.0)
    # 3D: the centre is the 8 middle cells of 4 x 4 x 4, 1/8 each; (-1, 0, 1/3) has
    # g = (0, 1.5, 2): cells (0, 1, 2) and (0, 2, 2), half each (flat 16 i + 4 j + k).
    index, weight = kernel_corners(torch.tensor([[0.0, 0.0, 0.0], [-1.0, 0.0, 1 / 3]]), 4)
    assert sorted(index[0].tolist()) == [21, 22, 25, 26, 37, 38, 41, 42]
    assert weight[0].tolist() == [0.125] * 8
    nonzero = {int(i): float(w) for i, w in zip(index[1], weight[1], strict=True) if w > 1e-6}
    assert nonzero == pytest.approx({6: 0.5, 10: 0.5})


@pytest.mark.parametrize("dim", [2, 3])
def test_interpolation_reproduces_a_kernel_linear_in_the_cell_index(dim):
    # Bilinear / trilinear interpolation is exact for linear functions: a kernel whose cell
    # (i, j[, k]) holds 100 i + 10 j (+ k) reads 100 g_0 + 10 g_1 (+ g_2) at grid point g.
    size = 5
    cells = torch.tensor(list(itertools.product(range(size), repeat=dim)), dtype=torch.float64)
    coefficients = torch.tensor([100.0, 10.0, 1.0][:dim], dtype=torch.float64)
    kernel = cells @ coefficients  # flat, row-major like kernel_corners' indices
    cube = torch.from_numpy(np.random.default_rng(0).uniform(-1, 1, size=(50, dim)))
    index, weight = kernel_corners(cube, size)
    interpolated = (kernel[index] * weight).sum(dim=1)
    grid = (cube + 1) / 2 * (size - 1)
    torch.testing.assert_close(interpolated, grid @ coefficients)
    torch.testing.assert_close(weight.sum(dim=1), torch.ones(50, dtype=torch.float64))


def test_window_and_neighbourhood_normalisation_by_hand():
    r2 = torch.tensor([0.0, 0.25, 1.0, 1.2])
    torch.testing.assert_close(window_weight(r2, "poly6"), torch.tensor([1.0, 0.421875, 0, 0]))
    assert window_weight(r2, "none").tolist() == [1.0] * 4
    # Receiver 0 has three edges, receiver 1 one: psi = 3 and 1.
    tau = torch.tensor([[0.0, 0.0], [0.5, 0.0], [0.0, -0.5], [0.0, 0.0]])
    receivers = torch.tensor([0, 0, 0, 1])
    _, plain = corner_weights(tau, receivers, 2, 4, "ball_to_cube_radial", "poly6")
    _, normal = corner_weights(tau, receivers, 2, 4, "ball_to_cube_radial", "poly6", True)
    torch.testing.assert_close(plain.sum(dim=1), torch.tensor([1.0, 0.421875, 0.421875, 1.0]))
    torch.testing.assert_close(normal, plain / torch.tensor([3.0, 3.0, 3.0, 1.0])[:, None])
    with pytest.raises(ValueError, match="window must be 'poly6' or 'none', got 'gauss'"):
        window_weight(r2, "gauss")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="kernel_size must be a whole number >= 1, got 0"):
        kernel_corners(tau, 0)


# ---------------------------------------------------------------------------------- mapping


def concentric_by_sector(x: float, y: float) -> tuple[float, float]:
    """The volume-preserving 2D map by hand: a point at radius rho and angle theta goes to the
    square of half-width rho, the angle spread evenly along the side it faces."""
    rho, theta = math.hypot(x, y), math.atan2(y, x)
    if abs(x) >= abs(y) and x > 0:  # theta in [-pi/4, pi/4]: the right side
        return rho, rho * theta / (math.pi / 4)
    if abs(y) > abs(x) and y > 0:  # theta in (pi/4, 3pi/4): the top side, x from rho to -rho
        return rho * (math.pi / 2 - theta) / (math.pi / 4), rho
    if rho == 0:
        return 0.0, 0.0
    mirrored = concentric_by_sector(-x, -y)  # the left and bottom sides by point symmetry
    return -mirrored[0], -mirrored[1]


def test_volume_preserving_mapping_matches_the_map_by_hand():
    tau = in_ball(np.random.default_rng(1), 200, 2)
    expected = torch.tensor([concentric_by_sector(*map(float, p)) for p in tau]).double()
    torch.testing.assert_close(ball_to_cube(tau, "ball_to_cube_volume_preserving"), expected)
    # 3D: the poles and the equator stay, the equator's diagonal goes to the cube's edge.
    r = 0.8
    s = r / math.sqrt(2)
    points = torch.tensor([[0, 0, r], [0, 0, -r], [r, 0, 0], [s, s, 0], [0, -r, 0]])
    cube = ball_to_cube(points.double(), "ball_to_cube_volume_preserving")
    expected = torch.tensor([[0, 0, r], [0, 0, -r], [r, 0, 0], [r, r, 0], [0, -r, 0]])
    torch.testing.assert_close(cube, expected.double())


@pytest.mark.parametrize("mapping", MAPPINGS)
@pytest.mark.parametrize("dim", [2, 3])
def test_mapping_sends_spheres_to_cube_surfaces_and_the_centre_to_the_centre(mapping, dim):
    tau = in_ball(np.random.default_rng(dim), 2000, dim)
    cube = ball_to_cube(tau, mapping)
    # The sphere of radius r lands on the cube's surface of half-width r: the unit ball inside
    # [-1, 1]^D, and a nearer neighbour always nearer the centre (radial ordering).
    torch.testing.assert_close(cube.abs().amax(dim=1), tau.norm(dim=1))
    assert ball_to_cube(torch.zeros(1, dim), mapping).tolist() == [[0.0] * dim]
    # The gradient exists at the centre too (no 0/0).
    zero = torch.zeros(1, dim, requires_grad=True)
    ball_to_cube(zero, mapping).sum().backward()
    assert torch.isfinite(zero.grad).all()


@pytest.mark.parametrize("mapping", MAPPINGS)
@pytest.mark.parametrize("dim", [2, 3])
def test_mapping_is_onto_the_cube_and_the_volume_preserving_one_is_uniform(mapping, dim):
    count, bins = 40_000 if dim == 2 else 80_000, 6
    cube = ball_to_cube(in_ball(np.random.default_rng(7), count, dim), mapping).numpy()
    histogram, _ = np.histogramdd(cube, bins=bins, range=[(-1, 1)] * dim)
    assert (histogram > 0).all()  # every part of the cube is reached
    expected = count / bins**dim
    if mapping == "ball_to_cube_volume_preserving":
        # Uniform in the ball, uniform in the cube: every bin within 5 standard deviations.
        assert np.abs(histogram - expected).max() < 5 * math.sqrt(expected)
    else:  # radial stretching crowds the cube's corners out: not uniform
        assert np.abs(histogram - expected).max() > 10 * math.sqrt(expected)


@pytest.mark.parametrize("mapping", MAPPINGS)
@pytest.mark.parametrize("dim", [2, 3])
def test_mapping_is_continuous_across_its_branches(mapping, dim):
    rng = np.random.default_rng(3)
    points = in_ball(rng, 3000, dim)
    # Points on the branch boundaries: the diagonals |x| = |y|, the 3D map's polar-cap
    # boundary 5/4 z^2 = x^2 + y^2, the axes and the centre.
    t = torch.from_numpy(rng.uniform(-0.7, 0.7, size=(200, 1)))
    if dim == 2:
        special = [torch.cat([t, t], 1), torch.cat([t, -t], 1), torch.cat([t, 0 * t], 1)]
    else:
        cap = torch.cat([t * math.sqrt(5 / 8), t * math.sqrt(5 / 8), t], 1)
        special = [cap, torch.cat([t, t, 0.5 * t], 1), torch.cat([0 * t, 0 * t, t], 1)]
    points = torch.cat([points, *special, torch.zeros(1, dim)])
    step = 1e-6
    moved = points + step * torch.from_numpy(rng.normal(size=points.shape))
    stretch = (ball_to_cube(moved, mapping) - ball_to_cube(points, mapping)).norm(dim=1)
    stretch /= (moved - points).norm(dim=1)
    # Lipschitz with a small constant: no jump anywhere, the branch boundaries included.
    assert float(stretch.max()) < 4.0


def rotate90(points: torch.Tensor, axes: tuple[int, int]) -> torch.Tensor:
    """Rotation by 90 degrees in the plane of `axes`: (a, b) -> (-b, a)."""
    a, b = axes
    out = points.clone()
    out[:, a], out[:, b] = -points[:, b], points[:, a]
    return out


ROTATIONS = [
    ("ball_to_cube_volume_preserving", 2, (0, 1)),
    ("ball_to_cube_radial", 2, (0, 1)),
    ("identity", 2, (0, 1)),
    # Griepentrog's map singles out the z axis: rotations about it only.
    ("ball_to_cube_volume_preserving", 3, (0, 1)),
    ("ball_to_cube_radial", 3, (0, 1)),
    ("ball_to_cube_radial", 3, (1, 2)),
]


@pytest.mark.parametrize(("mapping", "dim", "axes"), ROTATIONS)
def test_a_90_degree_rotation_permutes_the_kernel_cells(mapping, dim, axes):
    tau = in_ball(np.random.default_rng(5), 300, dim)
    rotated = rotate90(tau, axes)
    # The mapping commutes with the rotation ...
    torch.testing.assert_close(
        ball_to_cube(rotated, mapping), rotate90(ball_to_cube(tau, mapping), axes)
    )
    # ... so each displacement's cells are rotated on the grid: cell index (.., i_a, .., i_b, ..)
    # becomes (.., K - 1 - i_b, .., i_a, ..), with the same weights.
    size = 4
    index, weight = kernel_corners(ball_to_cube(tau, mapping), size)
    index_r, weight_r = kernel_corners(ball_to_cube(rotated, mapping), size)

    def rotate_cell(flat: int) -> int:
        cell = list(np.unravel_index(flat, (size,) * dim))
        a, b = axes
        cell[a], cell[b] = size - 1 - cell[b], cell[a]
        return int(np.ravel_multi_index(cell, (size,) * dim))

    for e in range(len(tau)):
        before = {rotate_cell(int(i)): float(w) for i, w in zip(index[e], weight[e], strict=True)}
        after = {int(i): float(w) for i, w in zip(index_r[e], weight_r[e], strict=True)}
        before = {k: v for k, v in before.items() if v > 1e-9}
        after = {k: v for k, v in after.items() if v > 1e-9}
        assert before.keys() == after.keys()
        assert list(after.values()) == pytest.approx([before[k] for k in after], abs=1e-9)


def test_a_rotated_neighbourhood_with_the_rotated_kernel_gives_the_same_output():
    rng = np.random.default_rng(11)
    _, senders, receivers, tau = random_graph(rng, 12, 0.5)
    n, settings = 12, CConvConfig(kernel_size=4)
    torch.manual_seed(0)
    layer = ContinuousConv(3, 5, 4, 2).double()
    features = torch.randn(n, 3, dtype=torch.float64)
    out = layer(features, neighbourhood(tau, senders, receivers, n, settings))
    # Cell (i, j) of the original geometry is cell (3 - j, i) of the rotated one.
    turned = ContinuousConv(3, 5, 4, 2).double()
    with torch.no_grad():
        turned.bias.copy_(layer.bias)
        for i, j in itertools.product(range(4), repeat=2):
            turned.kernel[3 - j, i] = layer.kernel[i, j]
    rotated = neighbourhood(rotate90(tau, (0, 1)), senders, receivers, n, settings)
    torch.testing.assert_close(turned(features, rotated), out)


# ---------------------------------------------------------------------------------- one cell


def cube_by_hand(t: np.ndarray, mapping: str) -> np.ndarray:
    if mapping == "identity":
        return t
    if mapping == "ball_to_cube_radial":
        largest = np.abs(t).max()
        return t * np.linalg.norm(t) / largest if largest > 0 else t
    return np.array(concentric_by_sector(*t))


@pytest.mark.parametrize("implementation", ["fast", "plain"])
@pytest.mark.parametrize("mapping", ["ball_to_cube_volume_preserving", "ball_to_cube_radial"])
@pytest.mark.parametrize("normalize", [False, True])
def test_one_nonzero_kernel_cell_is_the_matching_message_sum(implementation, mapping, normalize):
    rng = np.random.default_rng(2)
    radius, size, n = 0.4, 4, 15
    x, senders, receivers, tau = random_graph(rng, n, radius)
    settings = CConvConfig(kernel_size=size, coordinate_mapping=mapping, normalize=normalize)
    torch.manual_seed(1)
    layer = ContinuousConv(3, 2, size, 2).double()
    cell = (1, 2)
    with torch.no_grad():
        matrix = layer.kernel[cell].clone()
        layer.kernel.zero_()
        layer.kernel[cell] = matrix
        layer.bias.zero_()
    features = torch.randn(n, 3, dtype=torch.float64)
    graph = neighbourhood(tau, senders, receivers, n, settings, implementation)
    out = layer(features, graph)

    # Brute force: every ordered pair within the radius, the cell's bilinear weight written
    # as the hat function prod_d max(0, 1 - |g_d - c_d|), the poly6 window, psi by counting.
    expected = np.zeros((n, 2))
    f, w = features.numpy(), matrix.numpy()
    for i in range(n):
        neighbours = [j for j in range(n) if np.linalg.norm(x[j] - x[i]) <= radius]
        for j in neighbours:
            t = (x[j] - x[i]) / radius
            g = (cube_by_hand(t, mapping) + 1) / 2 * (size - 1)
            hat = np.prod([max(0.0, 1 - abs(g[d] - cell[d])) for d in range(2)])
            window = (1 - t @ t) ** 3
            psi = len(neighbours) if normalize else 1
            expected[i] += window * hat / psi * (f[j] @ w)
    np.testing.assert_allclose(out.detach().numpy(), expected, atol=1e-12)
    assert np.abs(expected).max() > 0.01  # the cell is really used


# ---------------------------------------------------------------------------------- network


def network_inputs(rng: np.random.Generator, n: int = 40, dim: int = 2):
    _, senders, receivers, tau = random_graph(rng, n, 0.3, dim)
    distance = tau.norm(dim=1, keepdim=True)
    edges = torch.cat([tau, distance], dim=1).float()
    return torch.randn(n, 7), edges, senders, receivers


@pytest.mark.parametrize("dim", [2, 3])
def test_fast_and_plain_are_one_function_with_one_set_of_parameters(dim):
    torch.manual_seed(0)
    model = CConv(7, dim, dataclasses.replace(TINY, cconv=CConvConfig(kernel_size=3)))
    inputs = network_inputs(np.random.default_rng(dim), dim=dim)
    model.implementation = "plain"
    plain = model(*inputs)
    plain.square().sum().backward()
    plain_grads = [p.grad.clone() for p in model.parameters()]
    model.zero_grad()
    model.implementation = "fast"
    fast = model(*inputs)
    fast.square().sum().backward()
    assert fast.shape == (40, dim) and fast.dtype == torch.float32
    torch.testing.assert_close(fast, plain, rtol=1e-5, atol=1e-5)
    for p, g in zip(model.parameters(), plain_grads, strict=True):
        torch.testing.assert_close(p.grad, g, rtol=1e-4, atol=1e-5)
    # Every layer's kernel gets a gradient: the convolutions are really in the network.
    assert all(float(conv.kernel.grad.abs().sum()) > 0 for conv in [model.conv0, *model.convs])


def test_bf16_precision_runs_close_to_fp32():
    torch.manual_seed(0)
    model = CConv(7, 2, TINY)
    inputs = network_inputs(np.random.default_rng(0))
    with torch.no_grad():
        reference = model(*inputs)
        model.precision = "bf16"
        low = model(*inputs)
    assert low.dtype == torch.float32
    error = float((low - reference).abs().max())
    assert error < 0.05 * float(reference.abs().max())


def test_cconv_is_permutation_equivariant_and_batches_as_a_disjoint_graph():
    torch.manual_seed(0)
    model = CConv(7, 2, TINY)
    nodes, edges, senders, receivers = network_inputs(np.random.default_rng(4))
    out = model(nodes, edges, senders, receivers)
    # Relabel the particles and shuffle the edges: the output follows the particles.
    order = torch.randperm(40)
    new_label = torch.empty_like(order)
    new_label[order] = torch.arange(40)
    shuffle = torch.randperm(len(senders))
    permuted = model(
        nodes[order], edges[shuffle], new_label[senders[shuffle]], new_label[receivers[shuffle]]
    )
    torch.testing.assert_close(permuted, out[order], rtol=1e-5, atol=1e-6)
    # Two graphs in one batch: each particle's output as if alone.
    batched = model(
        torch.cat([nodes, nodes]),
        torch.cat([edges, edges]),
        torch.cat([senders, senders + 40]),
        torch.cat([receivers, receivers + 40]),
        n_node=torch.tensor([40, 40]),
    )
    torch.testing.assert_close(batched, torch.cat([out, out]), rtol=1e-5, atol=1e-6)


def test_bad_inputs_name_what_was_expected():
    model = CConv(7, 2, TINY)
    nodes, edges, senders, receivers = network_inputs(np.random.default_rng(0))
    with pytest.raises(ValueError, match=r"edge_features must be \(E, >= 2\)"):
        model(nodes, edges[:, :1], senders, receivers)
    with pytest.raises(ValueError, match="CConv has no global input"):
        model(nodes, edges, senders, receivers, torch.zeros(1, 2))
    with pytest.raises(ValueError, match="coordinate mapping must be .* got 'polar'"):
        ball_to_cube(edges[:, :2], "polar")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="implementation must be 'fast' or 'plain'"):
        neighbourhood(edges[:, :2], senders, receivers, 40, SMALL, "fused")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"displacements must be \(E, 2\) or \(E, 3\)"):
        ball_to_cube(torch.zeros(3, 4), "ball_to_cube_radial")


# ---------------------------------------------------------------------------------- config


def test_config_selects_cconv_from_toml_and_round_trips(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text(
        '[model]\nkind = "cconv"\nself_edges = false\n'
        "[model.cconv]\nkernel_size = 3\nlayer_channels = [16, 16]\nnormalize = true\n"
        'coordinate_mapping = "ball_to_cube_radial"\nwindow = "none"\n'
        "[train]\nloss_steps = 2\n"
    )
    config = load_config(path)
    assert config.model.kind == "cconv" and not config.model.self_edges
    assert config.model.cconv == CConvConfig(
        layer_channels=(16, 16),
        kernel_size=3,
        coordinate_mapping="ball_to_cube_radial",
        window="none",
        normalize=True,
    )
    assert config.train.loss_steps == 2
    assert from_dict(Config, to_dict(config)) == config
    # The shipped comparison config parses, and a config without `kind` is the GNS.
    assert load_config(ROOT / "configs/sand2d-cconv.toml").model.kind == "cconv"
    assert load_config(ROOT / "configs/sand2d.toml").model.kind == "gns"


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('[model]\nkind = "mlp"\n', r"model.kind must be one of \['gns', 'cconv'\], got 'mlp'"),
        (
            '[model]\nkind = "cconv"\nlatent_size = 64\nmessage_passing_steps = 5\n',
            "model.latent_size, model.message_passing_steps: GNS settings, but model.kind is",
        ),
        ("[model.cconv]\nkernel_size = 3\n", "model.cconv shapes the CConv only"),
        (
            '[model]\nkind = "cconv"\n[model.cconv]\nlayer_channels = []\n',
            "layer_channels must be one or more positive widths, got",
        ),
        (
            '[model]\nkind = "cconv"\n[model.cconv]\ncoordinate_mapping = "polar"\n',
            "model.cconv.coordinate_mapping must be one of",
        ),
        ('[model]\nkind = "cconv"\n[model.cconv]\nkernel_size = 0\n', "kernel_size must be"),
        ('[model]\nkind = "cconv"\n[model.cconv]\nradius = 2\n', "unknown setting"),
        ("[train]\nloss_steps = 0\n", "TrainConfig.loss_steps must be positive, got 0"),
    ],
)
def test_bad_model_settings_are_errors_naming_the_value(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        load_config(path)


def test_unknown_kind_in_python_is_an_error_too():
    with pytest.raises(ValueError, match=r"ModelConfig.kind must be one of .* got 'pointnet'"):
        ModelConfig(kind="pointnet")  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------- training


def scene() -> Scene:
    return Scene(dim=2, radius=0.1, particle_types=(3, 5), bounds=((0.1, 0.9),) * 2, walls=True)


def small_batch(frames: int = 9, particles: int = 30):
    trajectory = damped_motion(np.random.default_rng(0), frames, particles, key=0)
    positions = torch.from_numpy(trajectory.positions.transpose(1, 0, 2).copy())
    return positions, torch.from_numpy(trajectory.particle_type)


def test_multi_step_loss_feeds_the_prediction_back_as_by_hand():
    torch.manual_seed(0)
    config = Config(model=TINY, noise=NoiseConfig(std=1e-4))
    simulator = LearnedSimulator(scene(), config)
    positions, types = small_batch()
    sequence, truth = positions[:, :6], positions[:, 6:8]
    step = TrainingStep(simulator)
    noise = simulator.sample_noise(sequence, types, torch.Generator().manual_seed(1))
    one, count = step(sequence, truth[:, 0], noise, types)
    simulator.eval()  # the statistics are now fixed (the first call added this batch)
    one, _ = step(sequence, truth[:, 0], noise, types)
    two, count_two = step(sequence, truth[:, 0], noise, types, later_positions=truth[:, 1:])
    assert int(count) == int(count_two) == 28  # the two kinematic particles are left out

    # By hand: predict, append the prediction (kinematic particles: the ground truth), predict
    # again; the target reaches the next ground truth shifted by the last input noise.
    free = ~simulator.kinematic_mask(types)
    noisy = sequence + noise
    first = simulator(noisy, types)
    reached = simulator.decoder_postprocess(first, noisy)
    reached[~free] = truth[~free, 0]
    fed_back = torch.cat([noisy[:, 1:], reached[:, None]], dim=1)
    acceleration = truth[:, 1] + noise[:, -1] - 2 * fed_back[:, -1] + fed_back[:, -2]
    normalizer = simulator.acceleration_normalizer
    target = (acceleration.double() - normalizer.mean) / normalizer.std
    second = (simulator(fed_back, types).double() - target).square().sum(dim=-1)[free].sum()
    assert float((two - one).detach()) == pytest.approx(float(second.detach()), rel=1e-4)
    # The gradient of the second step runs back through the first prediction.
    simulator.zero_grad()
    two.backward()
    through = [p.grad.clone() for p in simulator.parameters() if p.grad is not None]
    simulator.zero_grad()
    detached = torch.cat([noisy[:, 1:], reached.detach()[:, None]], dim=1)
    one_more = (simulator(detached, types).double() - target.detach()).square().sum(-1)[free].sum()
    (one + one_more).backward()
    cut = [p.grad for p in simulator.parameters() if p.grad is not None]
    assert any(not torch.allclose(a, b) for a, b in zip(through, cut, strict=True))


def test_cconv_learns_on_a_fixed_batch_and_rolls_out():
    torch.manual_seed(0)
    simulator = LearnedSimulator(scene(), Config(model=TINY))
    positions, types = small_batch()
    sequence, target = positions[:, :6], positions[:, 6]
    step = TrainingStep(simulator)
    optimizer = torch.optim.Adam(simulator.parameters(), lr=1e-2)
    noise = torch.zeros_like(sequence)
    losses = []
    for _ in range(40):
        squared, count = step(sequence, target, noise, types)
        loss = squared / count
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.1 * losses[0]
    trajectory = damped_motion(np.random.default_rng(0), 12, 30, key=0)
    result = rollout(simulator, trajectory, num_steps=5)
    assert result.predicted_rollout.shape == (5, 30, 2)
    assert np.isfinite(result.predicted_rollout).all() and result.timings["model"].min() > 0


def write_dataset(folder: Path, frames: int = 10) -> Path:
    rng = np.random.default_rng(0)
    items = [damped_motion(rng, frames, 16, k) for k in range(3)]
    # A radius of 0.1 gives the 16 particles in [0.3, 0.7]^2 a few neighbours each.
    write_metadata(
        folder, metadata_dict(sequence_length=frames - 1, default_connectivity_radius=0.1)
    )
    write_h5(folder / "train.h5", items)
    write_h5(folder / "valid.h5", items[:1])
    write_h5(folder / "test.h5", items[1:2])
    return folder


def run_config(model: ModelConfig, **train_settings: object) -> Config:
    settings: dict = dict(steps=3, log_every=1, checkpoint_every=3, validate_every=0)
    settings.update(train_settings)
    return Config(model=model, train=TrainConfig(**settings))


def test_checkpoints_rebuild_the_cconv_for_rollout_eval_and_report(tmp_path, capsys):
    data = write_dataset(tmp_path / "data")
    trained = train(data, tmp_path / "cconv", run_config(TINY, loss_steps=2), progress=False)
    saved = json.loads((tmp_path / "cconv/config.json").read_text())
    assert saved["model"]["kind"] == "cconv" and saved["train"]["loss_steps"] == 2
    state = load_checkpoint(tmp_path / "cconv/checkpoints/step_000000003.pt")
    assert state["config"]["model"]["cconv"]["kernel_size"] == 3
    loaded = load_simulator(tmp_path / "cconv")
    assert isinstance(loaded.model, CConv)
    for key, value in trained.state_dict().items():
        assert torch.equal(loaded.state_dict()[key].cpu(), value.cpu()), key

    # The command line: rollout and eval rebuild the CConv from the run folder.
    common = ["--run", str(tmp_path / "cconv"), "--data", str(data), "--device", "cpu"]
    assert cli.main(["rollout", *common, "--split", "test"]) == 0
    assert cli.main(["eval", *common, "--split", "test", "--every", "2"]) == 0
    figures = json.loads((tmp_path / "cconv/eval_test.json").read_text())["mean"]["model"]
    assert math.isfinite(figures["one_step_mse"]) and math.isfinite(figures["mse@full"])
    assert "ms/step" in capsys.readouterr().out

    # A GNS run and the CConv checkpoint side by side in one report, named by their kind.
    gns = ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=1, precision="fp32")
    train(data, tmp_path / "gns", run_config(gns), progress=False)
    result = report(
        tmp_path / "gns",
        data,
        checkpoints=["latest", str(tmp_path / "cconv/checkpoints/step_000000003.pt")],
        out=tmp_path / "report",
        horizons=(1, None),
        every=2,
        mpm=["none"],
        animation_frames=0,
        vtk_every=0,
        progress=False,
    )
    assert [r.method for r in result.rows] == ["GNS", "CConv", "constant velocity", "static"]
    cconv_row = result.rows[1]
    assert cconv_row.status == "ok" and cconv_row.seconds_per_frame > 0
    assert math.isfinite(cconv_row.values["mse@full"])
    assert "| CConv | step_000000003.pt (step 3)" in (tmp_path / "report/table.md").read_text()


def test_multi_step_windows_are_longer(tmp_path):
    # 7 frames are one window for C = 5 and one step, none for two steps.
    data = write_dataset(tmp_path / "data", frames=7)
    train(data, tmp_path / "one", run_config(TINY, steps=1), progress=False)
    with pytest.raises(ValueError, match="no training windows"):
        train(data, tmp_path / "two", run_config(TINY, steps=1, loss_steps=2), progress=False)
