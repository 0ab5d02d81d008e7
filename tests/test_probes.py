"""gns.probes on hand-made cases whose answers are known without the probe: graph distances
from scipy, the exact reach of a network of M message-passing steps, the floor seen no farther
than the wall clip plus M hops, and a block whose landing is written by hand."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from gns import probes, radius_graph
from gns.config import Config, ModelConfig
from gns.mpm import lattice
from gns.simulator import LearnedSimulator, Scene
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import shortest_path
from scipy.spatial import cKDTree

pytestmark = pytest.mark.usefixtures("torch_one_thread")

RADIUS = 0.015
SPACING = 1 / 128
DT = 0.0075
G = 9.81 * DT**2


def untrained(steps: int, wall_clip: float = 1.0, seed: int = 0, dim: int = 2) -> LearnedSimulator:
    """A GNS of `steps` message-passing steps with fresh weights in sand2d-taichi's box (a
    cube of the same span in 3D)."""
    scene = Scene(
        dim=dim,
        radius=RADIUS,
        particle_types=(6,),
        bounds=((0.1, 0.9),) * dim,
        walls=True,
        wall_clip=wall_clip,
        dt=DT,
    )
    model = ModelConfig(latent_size=16, mlp_hidden_size=16, message_passing_steps=steps)
    torch.manual_seed(seed)
    return LearnedSimulator(scene, Config(model=model)).eval()


@pytest.mark.parametrize("dim", [2, 3])
def test_a_block_history_falls_at_g_along_y_with_the_last_velocity_asked(dim):
    block = lattice((0.4,) * dim, (0.05,) * dim, SPACING)
    history = probes.block_history(block, 6, G, last_velocity=-0.3 * G)
    assert history.shape == (len(block), 6, dim)
    acceleration = history[:, 2:] - 2 * history[:, 1:-1] + history[:, :-2]
    np.testing.assert_allclose(acceleration[..., 1], -G, rtol=1e-9)
    np.testing.assert_allclose(np.delete(acceleration, 1, axis=-1), 0.0, atol=1e-15)
    np.testing.assert_allclose(
        history[:, -1] - history[:, -2], [[0, -0.3 * G, 0][:dim]] * len(block)
    )
    np.testing.assert_array_equal(history[:, -1], block)


def test_hop_counts_are_scipys_shortest_paths_on_a_radius_graph():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.random((299, 2)) * 0.12, [[0.5, 0.5]]])  # the last one alone
    senders, receivers = radius_graph(x, RADIUS, self_edges=False)
    targets = [0, 17, 299]
    ours = probes.hop_counts(senders, receivers, len(x), targets)
    # Messages run sender -> receiver: the hops to a target are paths from each particle to it.
    graph = coo_matrix((np.ones(len(senders)), (senders, receivers)), shape=(len(x),) * 2)
    to_target = shortest_path(graph.T, unweighted=True, indices=targets, directed=True)
    expected = np.where(np.isinf(to_target), -1, to_target).astype(np.int64)
    np.testing.assert_array_equal(ours, expected)
    assert (ours > 3).any() and (ours == -1).any()


def test_hop_counts_follow_the_direction_of_the_edges():
    # A chain 0 -> 1 -> 2 -> 3: everything reaches 3, nothing reaches 0 but itself.
    hops = probes.hop_counts(np.array([0, 1, 2]), np.array([1, 2, 3]), 4, [3, 0])
    np.testing.assert_array_equal(hops, [[3, 2, 1, 0], [0, -1, -1, -1]])


@pytest.mark.parametrize("steps", [1, 2, 3])
def test_a_network_of_m_message_passing_steps_reaches_exactly_m_hops(steps):
    simulator = untrained(steps)
    block = lattice((0.4, 0.4), (0.1, 0.1), SPACING)
    history = probes.block_history(block, 6, G)
    targets = np.argsort(np.linalg.norm(block - block.mean(axis=0), axis=1))[:3]
    reach = probes.reach_by_hop(simulator, history, 6, None, targets, max_hop=steps + 3)
    assert reach["mean"][0] == reach["total"][0] == 1.0
    assert (reach["total"][1 : steps + 1] > 1e-6).all(), reach
    assert (reach["total"][steps + 1 :] == 0).all(), reach
    # Every hop up to steps + 3 is populated in a 13 x 13 block around its centre.
    assert (reach["pairs"] > 0).all()
    # The mean over a hop's particles is its total over their count.
    ratio = reach["total"] / reach["pairs"] * reach["pairs"][0]
    np.testing.assert_allclose(reach["mean"], ratio, rtol=1e-9)


def test_the_reach_in_3d_ends_at_m_hops_too():
    simulator = untrained(2, dim=3)
    block = lattice((0.4,) * 3, (0.08,) * 3, SPACING)  # 10 x 10 x 10
    history = probes.block_history(block, 6, G)
    targets = np.argsort(np.linalg.norm(block - block.mean(axis=0), axis=1))[:2]
    reach = probes.reach_by_hop(simulator, history, 6, None, targets, max_hop=3)
    assert (reach["total"][1:3] > 1e-6).all() and reach["total"][3] == 0, reach
    assert reach["pairs"][3] > 0


@pytest.mark.parametrize("dim", [2, 3])
def test_the_probe_block_sits_in_the_middle_of_the_box_or_on_its_floor(dim):
    scene = untrained(1, dim=dim).scene  # the box is [0.1, 0.9] on every axis
    middle = probes.probe_block(scene, 0.2, 0.01)
    assert middle.shape == (20**dim, dim)
    np.testing.assert_allclose(middle.mean(axis=0), 0.5, atol=1e-12)
    on_floor = probes.probe_block(scene, 0.2, 0.01, "floor")
    assert on_floor[:, 1].min() == pytest.approx(0.1 + 0.005)  # half a spacing above it
    np.testing.assert_allclose(np.delete(on_floor.mean(axis=0), 1), 0.5, atol=1e-12)
    with pytest.raises(ValueError, match="a block 0.9 wide does not fit the box"):
        probes.probe_block(scene, 0.9, 0.01)
    with pytest.raises(ValueError, match="where must be 'middle' or 'floor'"):
        probes.probe_block(scene, 0.2, 0.01, "top")


def test_an_untrained_copy_keeps_the_normalisers_and_redraws_the_network():
    simulator = untrained(2)
    simulator.velocity_normalizer.update(torch.randn(50, 2))
    fresh = probes.untrained_copy(simulator, seed=3)
    for (name, ours), theirs in zip(
        simulator.state_dict().items(), fresh.state_dict().values(), strict=True
    ):
        if name.startswith("model."):
            if name.endswith("weight") and ours.dim() == 2:
                assert not torch.equal(ours, theirs), name
        else:
            assert torch.equal(ours, theirs), name


def test_an_untrained_variant_has_the_changed_setting_and_its_reach():
    simulator = untrained(3)
    variant = probes.untrained_copy(simulator, model={"message_passing_steps": 1})
    assert variant.config.model.message_passing_steps == 1
    block = lattice((0.4, 0.4), (0.06, 0.06), SPACING)
    history = probes.block_history(block, 6, G)
    reach = probes.reach_by_hop(variant, history, 6, None, [0], max_hop=3)
    assert reach["total"][1] > 0 and (reach["total"][2:] == 0).all()
    wider = probes.untrained_copy(simulator, scene={"radius": 2 * RADIUS})
    assert wider.scene.radius == 2 * RADIUS


@pytest.mark.parametrize(("steps", "wall_clip", "dim"), [(1, 2.0, 2), (2, 3.0, 2), (1, 2.0, 3)])
def test_the_floor_is_seen_no_higher_than_the_wall_clip_plus_m_hops(steps, wall_clip, dim):
    simulator = untrained(steps, wall_clip, dim=dim)
    side = 0.16 if dim == 2 else 0.07
    block = probes.probe_block(simulator.scene, side, SPACING, "floor")  # the floor: y = 0.1
    up = np.eye(dim)[1]
    history = probes.block_history(block + 0.5 * RADIUS * up, 6, G, -1.25 * DT)
    scene = simulator.scene
    change = probes.floor_shift(simulator, history, 6, None, shift=1.0)
    assert simulator.scene is scene  # put back
    height = (history[:, -1, 1] - 0.1) / RADIUS
    # A particle sees its own wall distances up to the clip, and each message-passing step
    # carries them at most one radius further.
    assert (change[height > wall_clip + steps] == 0).all()
    assert (change[height < wall_clip] > 0).all()
    assert change.max() > 0.01


def test_the_floor_probe_refuses_a_model_without_a_floor():
    simulator = untrained(1)
    simulator.scene = Scene(dim=2, radius=RADIUS, particle_types=(6,), dt=DT)
    with pytest.raises(ValueError, match="wall features on the vertical axis"):
        probes.floor_shift(simulator, np.zeros((4, 6, 2)), 6, None)


class Restorer:
    """A stand-in that continues its input at constant velocity and moves each particle back
    by `share` of its last input frame's offset from `reference` (N, D)."""

    def __init__(self, reference: np.ndarray, share: float):
        self.reference, self.share = torch.as_tensor(reference), share

    def predict_positions(self, positions, particle_type, context=None):
        last, before = positions[:, -1].double(), positions[:, -2].double()
        return 2 * last - before - self.share * (last - self.reference)


@pytest.mark.parametrize("share", [0.0, 0.1, 1.0])
def test_shift_undone_reads_the_share_of_a_squeeze_or_a_shuffle_put_back(share):
    """The squeeze (heights above the floor times 0.9) and a random shift of 1e-3: the share
    read is the stand-in's; had the shift reached the last frame only (a changed velocity),
    a model at constant velocity would read -1, not 0."""
    block = lattice((0.4, 0.45), (0.2, 0.2), SPACING)
    history = probes.block_history(block, 6, G, last_velocity=-0.01)
    types = torch.zeros(len(block), dtype=torch.long)
    floor = 0.1
    squeeze = probes.squeeze_toward_floor(history[:, -1], floor, 0.9)
    squeezed = history[:, -1] + squeeze
    np.testing.assert_allclose(squeezed[:, 0], history[:, -1, 0], rtol=0, atol=0)
    np.testing.assert_allclose(squeezed[:, 1] - floor, 0.9 * (history[:, -1, 1] - floor))
    shuffle = np.random.default_rng(0).normal(0.0, 1e-3, block.shape)
    stand_in = Restorer(history[:, -1], share)
    for shift in (squeeze, shuffle):
        # float32 positions near 0.5 against shifts of 1e-3: round-off below 1e-4 of them
        assert probes.shift_undone(stand_in, history, shift, types) == pytest.approx(
            share, abs=1e-3
        )


def test_shift_undone_refuses_a_shift_it_cannot_read():
    history = probes.block_history(lattice((0.4, 0.45), (0.05, 0.05), SPACING), 6, G)
    types = torch.zeros(len(history), dtype=torch.long)
    stand_in = Restorer(history[:, -1], 0.5)
    with pytest.raises(ValueError, match=r"shift must be \(36, 2\), got \(36, 3\)"):
        probes.shift_undone(stand_in, history, np.ones((36, 3)), types)
    with pytest.raises(ValueError, match="not all zero, got a squared size of 0.0"):
        probes.shift_undone(stand_in, history, np.zeros((36, 2)), types)
    with pytest.raises(ValueError, match="factor must be a finite number > 0, got 0.0"):
        probes.squeeze_toward_floor(history[:, -1], 0.1, 0.0)


def falling_block(frames: int, landing: int) -> np.ndarray:
    """(frames, N, 2): a 16 x 16 lattice falling at g from rest that stops dead at frame
    `landing` and stays there."""
    block = lattice((0.4, 0.1), (0.125, 0.125), SPACING)
    t = np.minimum(np.arange(frames), landing - 1)
    drop = 0.5 * G * t * (t + 1)
    return np.stack([block + [0.0, (landing - 1) * landing * G / 2 - d] for d in drop])


def density_by_thirds(frame: np.ndarray, first: np.ndarray) -> np.ndarray:
    """Neighbours within R of each particle (scipy), averaged over thirds of the particles by
    their height in `first`: the landing timeline's density, counted independently."""
    tree = cKDTree(frame)
    counts = np.array([len(n) - 1 for n in tree.query_ball_point(frame, RADIUS * (1 + 1e-9))])
    thirds = np.array_split(np.argsort(first[:, 1], kind="stable"), 3)
    return np.array([counts[third].mean() for third in thirds])


def test_the_landing_timeline_of_a_block_that_stops_dead():
    truth = falling_block(20, landing=12)
    r = probes.landing_timeline(truth, truth, truth, RADIUS, G, bands=3, before=3, after=4)
    assert r["landing"] == 12
    np.testing.assert_array_equal(r["frames"], np.arange(9, 17))
    # Before the landing every band falls at g; at it, each stops from the speed 11 g.
    np.testing.assert_allclose(r["truth"][:3], -1.0, atol=1e-6)
    np.testing.assert_allclose(r["truth"][3], 11.0, rtol=1e-6)
    np.testing.assert_allclose(r["truth"][4:], 0.0, atol=1e-6)
    # A model that reproduces the truth reads as the truth, one step and rollout alike.
    np.testing.assert_allclose(r["one_step"], r["truth"], atol=1e-9)
    np.testing.assert_allclose(r["rollout"], r["truth"], atol=1e-9)
    # Density: neighbours within R of each particle (scipy), by thirds of the height.
    expected = density_by_thirds(truth[12], truth[0])
    np.testing.assert_allclose(r["density_truth"][3], expected, rtol=1e-12)
    np.testing.assert_allclose(r["density_rollout"], r["density_truth"], rtol=1e-12)
    # The stop is frame 12's 11 g in each band, all of it given; density never departs.
    np.testing.assert_allclose(r["stopping_truth"], 11.0, rtol=1e-6)
    np.testing.assert_allclose(r["stopping_one_step"], r["stopping_truth"], rtol=1e-9)
    assert r["density_ratio"] == pytest.approx(1.0, rel=1e-12)


def test_surface_finds_the_top_and_bottom_rows_of_a_lattice_and_a_lone_particle():
    block = lattice((0.4, 0.4), (0.05, 0.05), SPACING)  # 7 x 7
    alone = np.array([[0.7, 0.7]])
    place = probes.surface(np.concatenate([block, alone]), RADIUS)
    y = block[:, 1]
    expected = np.where(y == y.max(), 1, np.where(y == y.min(), -1, 0))
    np.testing.assert_array_equal(place[:-1], expected)
    assert place[-1] == 1
    # A particle right beside another (outside the 45-degree cone) leaves it on top.
    pair = np.array([[0.5, 0.5], [0.5 + 0.9 * RADIUS, 0.5 + 0.1 * RADIUS]])
    np.testing.assert_array_equal(probes.surface(pair, RADIUS), [1, 1])


def test_falling_in_data_takes_the_frames_that_fall_through_the_input_only():
    """A block falling at g that stops dead at frame 12; a stand-in model that predicts 0.8 g
    at every step. With 6 input frames, frames 6-12 follow inputs that all fall: the truth
    reads 1 until the landing (frame 12: it stops from 11 g a step), the model 0.8."""
    truth = falling_block(20, landing=12)
    one_step = np.full_like(truth, np.nan)
    one_step[6:] = 2 * truth[5:-1] - truth[4:-2]
    one_step[6:, :, 1] -= 0.8 * G
    bounds = np.array([[0.1, 0.9], [0.1, 0.9]])
    r = probes.falling_in_data(truth, one_step, G, 6, bounds, RADIUS)
    n = truth.shape[1]
    assert probes.falling_frames(truth, G, 6) == list(range(6, 13))
    frames = np.repeat(np.arange(6, 13), n)
    assert len(r["truth"]) == len(frames)
    np.testing.assert_allclose(r["truth"], np.where(frames == 12, -11.0, 1.0), atol=1e-6)
    np.testing.assert_allclose(r["model"], 0.8, atol=1e-6)
    np.testing.assert_allclose(r["speed"], (frames - 1) * G, rtol=1e-9)
    last = truth[frames - 1, np.tile(np.arange(n), 7)]
    wall = np.min(np.concatenate([last - 0.1, 0.9 - last], axis=1), axis=1)
    np.testing.assert_allclose(r["wall"], wall, atol=1e-12)
    np.testing.assert_allclose(r["floor"], last[:, 1] - 0.1, atol=1e-12)
    # At its last input frame the lowest row has the rest of a fall at g to go before it
    # stops at frame 11, (11 * 12 - (t - 1) t) / 2 steps of g, above where it stops.
    bottom = r["surface"] == -1
    t = frames[bottom]
    stop = truth[-1, :, 1].min() - 0.1
    np.testing.assert_allclose(r["floor"][bottom], stop + (132 - (t - 1) * t) * G / 2, atol=1e-12)
    y = truth[0, :, 1]
    place = np.where(y == y.max(), 1, np.where(y == y.min(), -1, 0))
    np.testing.assert_array_equal(r["surface"], np.tile(place, 7))
    # Without walls along x only the floor and ceiling count.
    open_x = probes.falling_in_data(truth, one_step, G, 6, [[-np.inf, np.inf], [0.1, 0.9]], RADIUS)
    np.testing.assert_allclose(
        open_x["wall"], np.minimum(last[:, 1] - 0.1, 0.9 - last[:, 1]), atol=1e-12
    )
    # Sand at rest falls through no input: nothing is taken.
    rest = probes.falling_in_data(truth[12:], truth[12:], G, 6, bounds, RADIUS)
    assert all(len(v) == 0 for v in rest.values())
    # The model's frames are read where a sample is taken only.
    elsewhere = np.full_like(one_step, np.nan)
    elsewhere[6:13] = one_step[6:13]
    again = probes.falling_in_data(truth, elsewhere, G, 6, bounds, RADIUS)
    np.testing.assert_array_equal(again["model"], r["model"])
    with pytest.raises(ValueError, match="must be \\(T, N, D\\) alike"):
        probes.falling_in_data(truth, one_step[:, :5], G, 6, bounds, RADIUS)
    with pytest.raises(ValueError, match="history must be at least 3 frames"):
        probes.falling_frames(truth, G, 2)


def test_approach_to_floor_bins_the_falling_by_steps_to_the_floor_and_what_follows():
    """The block that stops dead at frame 12 with the 0.8 g stand-in model: every sample
    before the landing falls on (the model 0.8 there), the landing's (-11 g) are the rest.
    Each (bin, place) is checked against a loop over the samples, the floor 0.1 below."""
    truth = falling_block(20, landing=12)
    one_step = np.full_like(truth, np.nan)
    one_step[6:] = 2 * truth[5:-1] - truth[4:-2]
    one_step[6:, :, 1] -= 0.8 * G
    r = probes.falling_in_data(truth, one_step, G, 6, [[0.1, 0.9], [0.1, 0.9]], RADIUS)
    edges = [1, 2, 4, 8]
    within, min_speed = 0.05, 6.5 * G  # frames 6 (5 g a step) and the top rows miss out
    rows = probes.approach_to_floor(r, within, min_speed, edges, tol=0.1)
    n = truth.shape[1]
    y0 = truth[0, :, 1]
    place = np.where(y0 == y0.max(), 1, np.where(y0 == y0.min(), -1, 0))
    expected = {}
    for t in range(6, 13):
        for i in range(n):
            height, speed = truth[t - 1, i, 1] - 0.1, (t - 1) * G
            if height >= within or speed <= min_speed:
                continue
            b = sum(height / speed >= e for e in edges)
            expected.setdefault((b, place[i]), []).append(t)
    assert [(row["bin"], row["place"]) for row in rows] == sorted(expected)
    for row in rows:
        frames = np.array(expected[row["bin"], row["place"]])
        assert row["samples"] == len(frames)
        assert row["kept"] == pytest.approx(np.mean(frames < 12))
        if np.any(frames < 12):
            assert row["model_kept"] == pytest.approx(0.8, abs=1e-6)
        else:
            assert np.isnan(row["model_kept"])
        if np.any(frames == 12):  # stops from 11 g a step
            assert row["truth_rest"] == pytest.approx(-11.0, abs=1e-6)
            assert row["model_rest"] == pytest.approx(0.8, abs=1e-6)
        else:
            assert np.isnan(row["truth_rest"]) and np.isnan(row["model_rest"])
    # The bottom row stops half a spacing above the floor, coming at 11 g a step: under one
    # step of travel from it, all of it landing.
    assert (rows[0]["bin"], rows[0]["place"], rows[0]["kept"]) == (0, -1, 0.0)


def test_approach_by_height_bins_each_place_by_height_and_speed():
    """The block that stops dead at frame 12 with the 0.8 g stand-in model, against a loop
    over the samples: per (height, speed) bin the share falling on, the truth's mean (1 before
    the landing, -11 at it) and the model's (0.8)."""
    truth = falling_block(20, landing=12)
    one_step = np.full_like(truth, np.nan)
    one_step[6:] = 2 * truth[5:-1] - truth[4:-2]
    one_step[6:, :, 1] -= 0.8 * G
    r = probes.falling_in_data(truth, one_step, G, 6, [[0.1, 0.9], [0.1, 0.9]], RADIUS)
    heights, speeds = [0.01, 0.03, 0.06], [7.5 * G, 9.5 * G]
    y0 = truth[0, :, 1]
    place = np.where(y0 == y0.max(), 1, np.where(y0 == y0.min(), -1, 0))
    for where in (-1, 0, 1):
        rows = probes.approach_by_height(r, where, heights, speeds, tol=0.1)
        expected = {}
        for t in range(6, 13):
            for i in np.flatnonzero(place == where):
                height, speed = truth[t - 1, i, 1] - 0.1, (t - 1) * G
                key = (sum(height >= e for e in heights), sum(speed >= e for e in speeds))
                expected.setdefault(key, []).append(-11.0 if t == 12 else 1.0)
        assert [(row["height"], row["speed"]) for row in rows] == sorted(expected)
        for row in rows:
            a = np.array(expected[row["height"], row["speed"]])
            assert row["samples"] == len(a)
            assert row["kept"] == pytest.approx(np.mean(a == 1.0))
            assert row["truth"] == pytest.approx(a.mean(), abs=1e-6)
            assert row["model"] == pytest.approx(0.8, abs=1e-6)
    # The bins are used: the bottom row spans several heights and speeds, the landing's in one.
    bottom = probes.approach_by_height(r, -1, heights, speeds, tol=0.1)
    assert len({row["height"] for row in bottom}) > 1 and len({row["speed"] for row in bottom}) > 1
    assert 0 < sum(row["kept"] < 1 for row in bottom) < len(bottom)


def test_the_landing_timeline_tells_a_top_that_falls_through_from_one_that_stops():
    truth = falling_block(20, landing=12)
    rollout = truth.copy()
    top = probes.height_bands(truth[0], 3) == 2
    # The model's top third keeps falling at g after the landing: into the stopped base.
    for t in range(12, 20):
        rollout[t, top] = 2 * rollout[t - 1, top] - rollout[t - 2, top] - [0.0, G]
    r = probes.landing_timeline(truth, rollout, truth, RADIUS, G)
    at = list(r["frames"]).index(12)
    assert r["rollout"][at, 2] == pytest.approx(-1.0, abs=1e-6)
    assert r["rollout"][at, 0] == pytest.approx(11.0, rel=1e-6)
    assert r["density_rollout"][at + 3, 2] > r["density_truth"][at + 3, 2]
    # The largest density ratio, counted by hand (scipy) at every frame and third.
    ratios = [
        density_by_thirds(rollout[t], truth[0]) / density_by_thirds(truth[t], truth[0])
        for t in r["frames"]
    ]
    assert r["density_ratio"] == pytest.approx(np.max(ratios), rel=1e-12)
    assert r["density_ratio"] > 1.5


def test_the_landing_timeline_gives_each_band_its_share_of_the_stop():
    """One step from the truth, a stand-in model stops the bottom third whole, the middle by
    half and the top not at all (it falls on at g): shares 1, 1/2 and -1/11."""
    truth = falling_block(20, landing=12)
    band = probes.height_bands(truth[0], 3)
    one_step = truth.copy()
    free = 2 * truth[11] - truth[10] - [0.0, G]  # where frame 12 is without the stop
    one_step[12, band == 1] = (truth[12, band == 1] + free[band == 1]) / 2
    one_step[12, band == 2] = free[band == 2]
    r = probes.landing_timeline(truth, truth, one_step, RADIUS, G)
    np.testing.assert_allclose(r["stopping_truth"], 11.0, rtol=1e-6)
    np.testing.assert_allclose(r["stopping_one_step"], [11.0, 5.0, -1.0], rtol=1e-6, atol=1e-6)
    # A rollout that ends before the landing's last frame has no density there: NaN, not 1.
    cut = truth.copy()
    cut[15:] = np.nan
    assert np.isnan(probes.landing_timeline(truth, cut, truth, RADIUS, G)["density_ratio"])


def test_a_trajectory_without_a_landing_says_so():
    block = lattice((0.4, 0.4), (0.1, 0.1), SPACING)
    still = np.repeat(block[None], 10, axis=0)
    assert probes.landing_timeline(still, still, still, RADIUS, G)["landing"] is None


def test_height_bands_split_the_particles_into_equal_thirds_by_height():
    rng = np.random.default_rng(1)
    frame = rng.random((99, 2))
    band = probes.height_bands(frame, 3)
    assert np.bincount(band).tolist() == [33, 33, 33]
    assert frame[band == 0, 1].max() < frame[band == 1, 1].min()
    assert frame[band == 1, 1].max() < frame[band == 2, 1].min()


@pytest.mark.parametrize("dim", [2, 3])
def test_rest_by_height_bins_each_particle_by_its_height_above_the_floor(dim):
    floor = 0.1
    # Five particles at 0.5, 2, 2.5, 4 and 10 radii above the floor and one 0.2 R under it,
    # at rest in the history; the "model" pushes each by a known number of g.
    heights = np.array([0.5, 2.0, 2.5, 4.0, 10.0, -0.2])
    frame = np.full((6, dim), 0.5)
    frame[:, 0], frame[:, 1] = np.linspace(0.3, 0.6, 6), floor + heights * RADIUS
    history = np.repeat(frame[:, None], 6, axis=1)
    pushed = np.array([0.3, -0.1, -0.3, 2.0, -1.0, 0.5])
    predicted = frame + np.outer(pushed * G, np.eye(dim)[1])
    r = probes.rest_by_height(history, predicted, floor, RADIUS, G, edges=(1.0, 3.0, 6.0, 20.0))
    np.testing.assert_array_equal(r["count"], [2, 2, 1, 1, 0])
    np.testing.assert_allclose(r["acceleration"][:4], [0.4, -0.2, 2.0, -1.0], rtol=1e-9)
    assert np.isnan(r["acceleration"][4])  # nobody above 20 R
    np.testing.assert_allclose(r["truth"][:4], 0.0, atol=1e-12)
    # A history that falls at g reads -1 in the truth's column, at every height.
    falling = probes.block_history(frame, 6, G)
    r = probes.rest_by_height(falling, predicted, floor, RADIUS, G, edges=(1.0, 3.0, 6.0, 20.0))
    np.testing.assert_allclose(r["truth"][:4], -1.0, rtol=1e-9)


def test_rest_by_height_refuses_frames_of_the_wrong_shape():
    with pytest.raises(ValueError, match=r"history must be \(N, C \+ 1 >= 3, D = 2 or 3\)"):
        probes.rest_by_height(np.zeros((4, 2, 2)), np.zeros((4, 2)), 0.0, RADIUS, G)
    with pytest.raises(ValueError, match=r"history must be .*got \(4, 6, 4\)"):
        probes.rest_by_height(np.zeros((4, 6, 4)), np.zeros((4, 4)), 0.0, RADIUS, G)
    with pytest.raises(ValueError, match=r"predicted must be \(4, 2\)"):
        probes.rest_by_height(np.zeros((4, 6, 2)), np.zeros((3, 2)), 0.0, RADIUS, G)


def test_spreading_reads_the_outward_braking_of_the_outer_particles_only():
    # 50 particles on a row about x = 0.5: the outer fifth (10, the 5 farthest each side) glide
    # outward from speed v, braking at a; the inner 40 stay put (they must not dilute it). The
    # "model" brakes the outer ones twice as hard, from the truth's frames.
    x0 = np.linspace(0.3, 0.7, 50)
    side = np.sign(x0 - 0.5)
    outer = np.abs(x0 - 0.5) >= np.sort(np.abs(x0 - 0.5))[-10]
    v, a, frames = 0.004, 0.3 * G, 12
    t = np.arange(frames)[:, None]
    moved = np.where(outer, side * (v * t - 0.5 * a * t**2), 0.0)
    truth = np.stack([x0 + moved, np.full_like(moved, 0.2)], axis=-1)
    one_step = truth.copy()
    one_step[2:, :, 0] -= np.where(outer, side * a, 0.0)
    r = probes.spreading(truth, one_step, G, outer=0.2)
    assert np.isnan(r["truth"][:2]).all()
    np.testing.assert_allclose(r["truth"][2:], -0.3, rtol=1e-6)
    np.testing.assert_allclose(r["one_step"][2:], -0.6, rtol=1e-6)
    k = np.arange(2, frames)
    np.testing.assert_allclose(r["speed"][2:], v - a * (2 * k - 3) / 2, rtol=1e-6)
    with pytest.raises(ValueError, match="outer must be a fraction in"):
        probes.spreading(truth, one_step, G, outer=0.0)
    with pytest.raises(ValueError, match="the same"):
        probes.spreading(truth, one_step[1:], G)


def test_launch_and_braking_split_a_front_at_its_peak_speed():
    # The outer particles of a row are launched outward at +2 g for 6 frames (a landing), then
    # brake at -0.5 g until they stop; a model gives half the launch and brakes as the truth.
    x0 = np.linspace(0.3, 0.7, 50)
    side = np.sign(x0 - 0.5)
    outer = np.abs(x0 - 0.5) >= np.sort(np.abs(x0 - 0.5))[-10]
    frames, launch_end = 40, 8
    accel = np.where(np.arange(frames) < launch_end, 2.0, -0.5) * G
    accel[:2] = 0.0  # frames 0 and 1 carry no acceleration (it arrives at t >= 2)
    speed = np.maximum(np.cumsum(accel), 0.0)  # x_t - x_{t-1}; it stops at rest
    path = np.cumsum(speed)
    truth = np.stack(
        [x0 + np.where(outer, side * path[:, None], 0.0), np.full((frames, 50), 0.2)], axis=-1
    )
    one_step = np.full_like(truth, np.nan)
    one_step[3:] = truth[3:]
    launched = 3 <= np.arange(frames)
    one_step[launched & (np.arange(frames) < launch_end), :, 0] -= np.where(outer, side * G, 0.0)
    rows = probes.spreading(truth, one_step, G)
    r = probes.launch_and_braking(rows, flowing=0.1 * G)
    assert r["peak"] == launch_end and r["peak_speed"] == pytest.approx(12 * G)
    # From frame 3 (the first with a prediction) to the peak: 5 frames of +2 g, the model's +1 g.
    assert r["launch_truth"] == pytest.approx(10.0) and r["launch_one_step"] == pytest.approx(5.0)
    assert r["braking_truth"] == pytest.approx(-0.5)
    assert r["braking_one_step"] == pytest.approx(-0.5)
    with pytest.raises(ValueError, match="no frame has a one-step prediction"):
        probes.launch_and_braking(probes.spreading(truth, truth * np.nan, G), 0.1 * G)


def test_starts_near_floor_takes_a_low_slow_block_only():
    # A 0.2 block on a lattice, its lowest row 0.02 above a floor at 0.1, two frames.
    block = lattice((0.3, 0.12), (0.2, 0.2), SPACING)

    def frames(velocity):  # per frame
        return np.stack([block, block + np.asarray(velocity)])

    at_rest, thrown = frames((0.0, 0.0)), frames((0.006, -0.0045))  # 1 m/s at 7.5 ms
    assert probes.starts_near_floor(at_rest, 0.1, gap=0.025, speed=0.5 * DT)
    assert not probes.starts_near_floor(at_rest, 0.1, gap=0.015, speed=0.5 * DT)
    assert not probes.starts_near_floor(thrown, 0.1, gap=0.025, speed=0.5 * DT)
    assert probes.starts_near_floor(thrown, 0.1, gap=0.025, speed=1.01 * DT)
    with pytest.raises(ValueError, match=r"\(T >= 2, N, D >= 2\)"):
        probes.starts_near_floor(at_rest[:1], 0.1, 0.025, 0.0)
    with pytest.raises(ValueError, match="gap and speed must be >= 0, got -0.1 and 0.0"):
        probes.starts_near_floor(at_rest, 0.1, -0.1, 0.0)


SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "probe.py"


def run_probe(*args: str) -> list[str]:
    done = subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, check=True
    )
    return done.stdout.splitlines()


def test_the_probe_script_runs_each_probe_on_a_trained_model(strided):
    run, native, _ = strided
    reach = run_probe(
        "reach", str(run), "--untrained", "--variant", "model.layer_norm=false", "--max-hop", "4"
    )
    rows = [line for line in reach if line.startswith("| trained") or line.startswith("| untr")]
    assert len(rows) == 6 and all(row.count("|") == 8 for row in rows), reach
    assert rows[-1].startswith("| untrained, model.layer_norm=false | hop | 1 |"), reach
    floor = run_probe("floor", str(run))
    assert [line.split("|")[1].strip() for line in floor[3:]] == ["at rest", "landing"], floor
    landing = run_probe("landing", str(run), str(native), "test", "--trajectories", "0")
    assert re.match(rf"{re.escape(str(run))} on test trajectory 0: ", landing[0]), landing
    assert landing[-1].endswith("no landing (the lowest band never decelerates by 3 g)")
    # Any acceleration over -1000 g is a "landing": its table, then the summary of all landings.
    landing = run_probe(
        "landing", str(run), str(native), "test", "--trajectories", "0", "--threshold", "-1000"
    )
    share = r"(-?\d+\.\d\d|nan|-)"
    assert re.fullmatch(
        rf"{re.escape(str(run))}: [01] of 1 landings within 1\.5 of the truth's density "
        rf"\(largest (\d+\.\d\d|nan)\); share of the truth's stop one step from it, bands low "
        rf"to high: {share} / {share} / {share}",
        landing[-1],
    ), landing
    rest = run_probe("rest", str(run), "--data", str(native), "--split", "test")
    assert rest[2].startswith("| model | below R | 1-3 R | 3-6 R | above 6 R |"), rest
    assert rest[4].startswith(f"| {run} | ") and rest[4].count("|") == 7, rest
    fall = run_probe(
        "fall", str(run), "--data", str(native), "--speeds", "0.5", "--trajectories", "0"
    )
    assert fall[1].startswith("| model | walls | speed | bottom | inside | top |"), fall
    rows = [line.split(" | ")[1:3] for line in fall[3:]]
    # Every particle falls within 1000 g of g; the mean under the model's training noise comes
    # after the model's own figure, the truth's and the model's unchanged.
    args = ["fall", str(run), "--data", str(native), "--tol", "1000", "--trajectories", "0"]
    every, shaken = run_probe(*args), run_probe(*args, "--noise-draws", "2")

    def cells(lines: list[str]) -> list[str]:  # the first table's bottom, inside, top
        return [c.strip(" |") for line in lines[3 : lines.index("")] for c in line.split(" | ")[3:]]

    # The third table, by place, height and speed, of every particle.
    third = every.index("", every.index("") + 1) + 1
    assert (
        every[third + 1]
        == "| model | place | height | "
        + " | ".join(["under 0.25", "0.25-0.5", "0.5-1", "over 1"])
        + " |"
    ), every
    grid = [line.split(" | ") for line in every[third + 3 :]]
    assert grid and all(
        row[0] == f"| {run}" and row[1] in ("bottom", "inside", "top") for row in grid
    )
    assert all(len(row) == 7 for row in grid), every
    every, shaken = cells(every), cells(shaken)
    assert any(cell != "-" for cell in every), every
    for plain, noisy in zip(every, shaken, strict=True):
        if plain == "-":
            assert noisy == "-"
            continue
        match = re.fullmatch(r"(\S+) / (\S+) \((\d+)\)", plain)
        assert match, (plain, every)
        truth, model, n = match.groups()
        assert re.fullmatch(rf"{truth} / {model} / -?\d+\.\d\d \({n}\)", noisy), noisy
    table = fall.index("") + 1  # the second table, by steps to the floor, after a blank line
    assert rows[: table - 4] == [
        [w, s] for w in ("seen", "none") for s in ("under 0.5", "over 0.5")
    ], fall
    assert fall[table + 1].startswith("| model | steps to floor | place | samples |"), fall
    third = fall.index("", table) + 1  # by height and speed
    assert all(line.startswith(f"| {run} | ") for line in fall[table + 3 : third - 1]), fall
    assert fall[third + 1] == "| model | place | height | under 0.5 | over 0.5 |", fall
    spread = run_probe("spread", str(run), "--data", str(native), "--flowing", "0")
    assert spread[1].startswith("| model | trajectory | peak speed (m/s, step) | launch"), spread
    assert spread[-1].startswith(f"| {run} | all (sum; mean) | "), spread
    # Every trajectory starts within 10 of the floor slower than 100 m/s: the same table.
    near = run_probe(
        "spread",
        str(run),
        "--data",
        str(native),
        "--flowing",
        "0",
        "--near-floor",
        "10",
        "--start-speed",
        "100",
    )
    assert near == spread
    for shift in ([], ["--random", "1e-3"]):
        squeeze = run_probe("squeeze", str(run), "--data", str(native), "--every", "4", *shift)
        assert squeeze[1] == "| model | step | speed (m/s) | undone |", squeeze
        number = r"[+-]\d+\.\d{3}"
        cells = rf"\d+ \| \d+\.\d\d \| {number} \({number} to {number}\)"
        steps = squeeze[3:-1]
        assert steps and all(
            re.fullmatch(rf"\| {re.escape(str(run))} \| {cells} \|", line) for line in steps
        ), squeeze
        assert squeeze[-1].startswith(f"| {run} | all | | "), squeeze


@pytest.mark.parametrize(
    "option, message",
    [
        (["--every", "0"], "--every must be at least 1 step, got 0"),
        (["--random", "-0.001"], "--random must be a finite std > 0, got -0.001"),
    ],
)
def test_the_squeeze_probe_refuses_what_it_cannot_step_by(strided, option, message):
    run, native, _ = strided
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "squeeze", str(run), "--data", str(native), *option],
        capture_output=True,
        text=True,
    )
    assert done.returncode != 0 and f"probe.py squeeze: {message}" in done.stderr, done.stderr


def test_the_collapse_probe_reads_a_taller_block_collapsing_harder_in_the_mpm():
    """The physics is the oracle: sand (30 degrees) standing 0.2 high on a 0.2 base is past its
    angle of repose and collapses sideways; 0.05 high, it hardly moves."""
    lines = run_probe("collapse", "sand2d-taichi", "--heights", "0.05", "0.2", "--frames", "120")
    assert lines[1] == "| height | MPM (peak speed m/s, step) | sand2d-taichi |", lines
    rows = [line.split("|")[1:-1] for line in lines[3:]]
    assert [row[0].strip() for row in rows] == ["0.05", "0.2"], lines
    low, tall = (float(row[1].split()[0]) for row in rows)
    assert 0.0 <= low < 0.1 and tall > 0.3, lines
    assert all(np.isfinite(float(row[2])) for row in rows), lines


def test_the_runout_probe_spreads_loose_sand_further_in_the_mpm():
    """The physics is the oracle: the same block at rest just above the floor spreads further
    and ends lower at 20 degrees than at 45 (the looser, the further it runs)."""
    lines = run_probe("runout", "sand2d-taichi", "--angles", "20", "45", "--frames", "120")
    assert lines[1] == "| angle | MPM runout | MPM height | sand2d-taichi |", lines
    rows = [[cell.strip() for cell in line.split("|")[1:-1]] for line in lines[3:]]
    assert [row[0] for row in rows] == ["20", "45"], lines
    (loose_runout, loose_height), (firm_runout, firm_height) = (
        (float(row[1]), float(row[2])) for row in rows
    )
    assert loose_runout > 1.3 * firm_runout and loose_height < firm_height, lines
    ratios = [float(x) for row in rows for x in row[3].split(" / ")]
    assert len(ratios) == 4 and all(0.0 < r < 10.0 for r in ratios), lines
