"""The reference simulator against physics and against real data made by another MPM code."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from data_helpers import SAND as SAND2D
from gns import _core
from gns.mpm import (
    Block,
    Goop,
    MpmResult,
    MpmScene,
    Rigid,
    Sand,
    Segment,
    Shake,
    Water,
    particles,
    simulate,
)

G_FRAME = -9.81 * 0.0025**2  # free fall per frame^2


def final_shape(positions: np.ndarray, floor: float = 0.1) -> tuple[float, float, float]:
    """(leftmost x, rightmost x, pile height: 99th percentile of y above the floor)."""
    return positions[:, 0].min(), positions[:, 0].max(), np.percentile(positions[:, 1], 99) - floor


def test_free_fall_drops_by_g_dt_squared_per_frame_squared():
    scene = MpmScene([Block(Water(), (0.4, 0.6), (0.1, 0.1))])
    y = simulate(scene, 12).positions[:, :, 1].astype(np.float64).mean(axis=1)
    np.testing.assert_allclose(np.diff(y, 2), G_FRAME, rtol=1e-2)


def test_a_settled_water_layer_keeps_its_area():
    # Wall to wall, so the layer cannot spread: its area is its width times its height, and
    # for a uniform layer the height is twice the mean height of the particles above the floor
    # (robust to the few particles that ride the surface waves).
    height = 0.1
    scene = MpmScene([Block(Water(), (0.1, 0.1), (0.8, height))], wall="slip")
    positions = simulate(scene, 200).positions.astype(np.float64)
    layer = 2.0 * (positions[:, :, 1].mean(axis=1) - 0.1)
    assert layer[0] == pytest.approx(height, rel=1e-6)
    np.testing.assert_allclose(layer, height, rtol=0.02)


def column(friction_angle_deg: float, height: float) -> np.ndarray:
    """Final positions of a 0.1-wide sand column against the left wall."""
    sand = Sand(friction_angle_deg=friction_angle_deg)
    return simulate(MpmScene([Block(sand, (0.1, 0.1), (0.1, height))]), 300).positions[-1]


def surface_slope_deg(positions: np.ndarray) -> float:
    """The deposit's surface angle: a line fitted to the highest particle of each x bin,
    leaving out the bins next to the wall and the tip."""
    x, y = positions[:, 0].astype(np.float64), positions[:, 1].astype(np.float64)
    edges = np.linspace(0.1, x.max(), 12)
    tops = [y[(x >= a) & (x < b)].max() for a, b in zip(edges[:-1], edges[1:], strict=True)]
    centres = 0.5 * (edges[:-1] + edges[1:])
    slope = -np.polyfit(centres[2:-2], np.array(tops[2:-2]), 1)[0]
    return float(np.degrees(np.arctan(slope)))


def test_sand_column_collapse_runout_grows_with_aspect_ratio_and_the_slope_follows_friction():
    runouts = [column(30.0, h)[:, 0].max() - 0.2 for h in (0.05, 0.1, 0.2)]
    assert runouts[0] < runouts[1] < runouts[2]
    # More friction, shorter runout and a steeper deposit, never steeper than the friction angle
    # (a collapse leaves a deposit flatter than the angle of repose).
    deposits = {phi: column(phi, 0.1) for phi in (20.0, 30.0)}
    assert deposits[20.0][:, 0].max() > deposits[30.0][:, 0].max()
    slopes = {phi: surface_slope_deg(p) for phi, p in deposits.items()}
    assert slopes[20.0] < slopes[30.0]
    for phi, slope in slopes.items():
        assert phi - 10.0 < slope < phi, (phi, slope)


# The parameters are plain names, so collection never reads ../shared: a fresh clone without it
# skips these four with the reason below instead of failing on a missing file.
@pytest.mark.skipif(
    not (SAND2D / "manifest.json").is_file(), reason="../shared/data/sand2d-taichi not present"
)
@pytest.mark.parametrize("name", ["sand_00.npz", "sand_13.npz", "sand_30.npz", "sand_44.npz"])
def test_sand_matches_the_independent_taichi_run_it_copies(name):
    """The same block, velocity, friction angle and wall friction as a trajectory of the real
    data: runout and pile height within 15%."""
    manifest = json.loads((SAND2D / "manifest.json").read_text())
    entry = next(t for t in manifest["trajectories"] if t["file"] == name)
    x, y, w, h = entry["cube"]
    sand = Sand(friction_angle_deg=entry["friction_angle_deg"])
    velocity = tuple(entry["initial_velocity"])
    scene = MpmScene(
        [Block(sand, (x, y), (w, h), velocity)], wall_friction=manifest["wall_friction"]
    )
    ours = simulate(scene, manifest["frames"]).positions[-1]
    with np.load(SAND2D / name, allow_pickle=True) as archive:
        theirs = archive["trajectory0"][0][-1]
    (l0, r0, h0), (l1, r1, h1) = final_shape(theirs), final_shape(ours)
    assert r1 - l1 == pytest.approx(r0 - l0, rel=0.15)
    assert h1 == pytest.approx(h0, rel=0.15)


def test_stiff_fast_and_plastic_materials_stay_finite_and_inside_the_walls():
    blocks = [
        Block(Sand(youngs_modulus=1e8), (0.15, 0.5), (0.1, 0.1), (4.0, -3.0)),
        Block(Water(), (0.5, 0.5), (0.1, 0.1), (-4.0, 2.0)),
        Block(Goop(), (0.7, 0.2), (0.1, 0.1), (0.0, -4.0)),
    ]
    result = simulate(MpmScene(blocks), 30)
    assert np.isfinite(result.positions).all()
    margin = 0.02  # the walls act on grid nodes, so particles may sit a little past them
    assert result.positions.min() > 0.1 - margin and result.positions.max() < 0.9 + margin
    assert result.substeps.max() > 50  # the CFL bound follows the stiff sand's wave speed
    assert (result.seconds > 0).all()
    assert set(result.particle_type.tolist()) == {5, 6, 7}


def test_obstacles_hold_material_and_never_move():
    ramp = Segment((0.1, 0.5), (0.6, 0.3))
    scene = MpmScene([Block(Sand(), (0.15, 0.55), (0.1, 0.1))], obstacles=[ramp])
    result = simulate(scene, 120)
    kinematic = result.particle_type == 3
    assert kinematic.any()
    np.testing.assert_array_equal(result.positions[-1, kinematic], result.positions[0, kinematic])
    # The sand spread down the ramp (a 22 degree slope, sticky) and stays on top of it.
    sand = result.positions[-1, ~kinematic].astype(np.float64)
    ramp_y = 0.5 + (sand[:, 0] - 0.1) * (0.3 - 0.5) / 0.5
    assert sand[:, 0].mean() > result.positions[0, ~kinematic, 0].mean() + 0.02
    assert (sand[:, 1] > ramp_y - 0.02)[sand[:, 0] < 0.55].all()


def test_runs_are_reproducible_and_bad_input_is_rejected():
    scene = MpmScene([Block(Water(), (0.3, 0.3), (0.1, 0.1), (1.0, 0.0))], jitter=0.5)
    a, b = simulate(scene, 5, seed=1), simulate(scene, 5, seed=1)
    np.testing.assert_array_equal(a.positions, b.positions)
    assert not np.array_equal(a.positions, simulate(scene, 5, seed=2).positions)
    with pytest.raises(ValueError, match="poisson_ratio must be in"):
        simulate(MpmScene([Block(Sand(poisson_ratio=0.5), (0.3, 0.3), (0.1, 0.1))]), 2)
    with pytest.raises(ValueError, match="outside the simulation domain"):
        simulate(MpmScene([Block(Water(), (-0.2, 0.3), (0.1, 0.1))]), 2)
    with pytest.raises(ValueError, match="wall must be"):
        simulate(MpmScene([Block(Water(), (0.3, 0.3), (0.1, 0.1))], wall="glue"), 2)
    with pytest.raises(ValueError, match="more than max_substeps"):
        simulate(MpmScene([Block(Water(), (0.3, 0.3), (0.1, 0.1))], max_substeps=3), 2)


def test_a_progress_callback_sees_every_frame_and_can_stop_the_run():
    seen: list[int] = []
    scene = MpmScene([Block(Water(), (0.3, 0.3), (0.1, 0.1))])
    simulate(scene, 4, progress=seen.append)
    assert seen == [1, 2, 3]

    def stop(frame: int) -> None:
        if frame == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        simulate(scene, 10, progress=stop)


def test_given_positions_that_are_the_lattice_give_the_lattices_run_bit_for_bit():
    # Sizes that are whole multiples of the spacing 1/128 (grid 64, 4 particles per cell): the
    # blocks' area over their points is then exactly spacing^2, the lattice's volume.
    blocks = [
        Block(Sand(friction_angle_deg=25.0), (0.3, 0.1), (0.25, 0.125), (0.5, 0.0)),
        Block(Water(), (0.6, 0.4), (0.125, 0.125), (0.0, -1.0)),
    ]
    scene = MpmScene(blocks)
    ours = simulate(scene, 40)
    start = particles(scene)
    given = simulate(scene, 40, positions=start["positions"])
    np.testing.assert_array_equal(given.positions, ours.positions)
    np.testing.assert_array_equal(given.particle_type, ours.particle_type)
    # Shuffled, each point still takes its own block's material and velocity.
    order = np.random.default_rng(0).permutation(len(start["positions"]))
    shuffled = particles(scene, positions=start["positions"][order])
    for key in ("positions", "velocities", "material", "particle_type"):
        np.testing.assert_array_equal(shuffled[key], start[key][order], key)
    assert shuffled["particle_volume"] == start["particle_volume"] == (1 / 128) ** 2


def test_given_positions_keep_the_datas_volume_whatever_the_grid():
    scene = MpmScene([Block(Sand(), (0.4, 0.1), (0.2, 0.2))])
    points = np.random.default_rng(0).uniform((0.4, 0.1), (0.6, 0.3), (500, 2))
    for grid in (64, 32, 20):
        start = particles(replace(scene, grid=grid), positions=points)
        assert start["particle_volume"] == pytest.approx(0.04 / 500, rel=1e-12)
        np.testing.assert_array_equal(start["positions"], points)
    assert particles(replace(scene, grid=32))["particle_volume"] != scene.spacing**2


def test_given_positions_outside_every_block_are_refused_by_name():
    scene = MpmScene(
        [Block(Sand(), (0.4, 0.1), (0.2, 0.2)), Block(Water(), (0.7, 0.5), (0.2, 0.1))]
    )
    points = np.array([[0.5, 0.2], [0.75, 0.55], [0.65, 0.2]])
    message = r"given point 2 at \(0\.65, 0\.2\) is in no block .*lower \(0\.4, 0\.1\), size"
    with pytest.raises(ValueError, match=message):
        simulate(scene, 2, positions=points)
    # Within the margin it belongs to the nearest block.
    start = particles(scene, positions=points, margin=0.06)
    assert start["particle_type"].tolist() == [6, 5, 6]
    with pytest.raises(ValueError, match="block 1 .* holds no given point"):
        particles(scene, positions=points[[0, 2]], margin=0.06)
    # One volume for all: blocks filled at different densities would get the wrong masses.
    with pytest.raises(ValueError, match="different densities"):
        particles(scene, positions=np.vstack([points[:2], [[0.45, 0.15], [0.55, 0.25]]]))


# ------------------------------------------------------------------- per-frame gravity, Shake


def core_run(scene: MpmScene, frames: int, **extra):
    """mpm_simulate on the scene's lattice, as simulate calls it, plus `extra`."""
    start = particles(scene)
    assert scene.bounds is not None and scene.gravity is not None
    return _core.mpm_simulate(
        start["positions"],
        start["velocities"],
        start["material"],
        [m.core() for m in start["materials"]],
        start["particle_volume"],
        frames,
        grid=scene.grid,
        bounds=[list(b) for b in scene.bounds],
        wall=scene.wall,
        wall_friction=scene.wall_friction,
        gravity=list(scene.gravity),
        frame_dt=scene.frame_dt,
        cfl=scene.cfl,
        max_substeps=scene.max_substeps,
        **extra,
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_frame_gravity_equal_to_gravity_is_the_constant_gravity_run_bit_for_bit(dim):
    # Thrown at a wall and with a rigid body, so walls and bodies are part of the run.
    blocks = [
        Block(Water(), (0.12,) * dim, (0.2,) * dim, (-1.0, 0.5, 0.3)[:dim]),
        Block(Rigid(), (0.5,) * dim, (0.1,) * dim, (0.5, 0.0, 0.0)[:dim]),
    ]
    # Gravity -9.75, exact in float32 too, so that float32 rows give the same run.
    gravity = (0.0, -9.75, 0.0)[:dim]
    scene = MpmScene(blocks, grid=32 if dim == 2 else 24, gravity=gravity)
    frames = 25
    constant = core_run(scene, frames)
    rows = np.tile(np.asarray(scene.gravity, np.float64), (frames - 1, 1))
    per_frame = core_run(scene, frames, frame_gravity=rows)
    for a, b in zip(constant, per_frame, strict=True):
        if a.dtype != np.float64:  # seconds differ, positions and substeps must not
            np.testing.assert_array_equal(a, b)
    # float32 rows of the same values are the same run too.
    np.testing.assert_array_equal(
        core_run(scene, frames, frame_gravity=rows.astype(np.float32))[0], constant[0]
    )


def test_bad_frame_gravity_is_refused_by_name():
    scene = MpmScene([Block(Water(), (0.4, 0.5), (0.05, 0.05))])
    good = np.tile([0.0, -9.81], (4, 1))
    shape = r"frame_gravity must have shape \(frames - 1, D\) = \(4, 2\)"
    with pytest.raises(ValueError, match=shape + r".*got \(5, 2\)"):
        core_run(scene, 5, frame_gravity=np.tile([0.0, -9.81], (5, 1)))
    with pytest.raises(ValueError, match=shape + r".*got \(4, 3\)"):
        core_run(scene, 5, frame_gravity=np.zeros((4, 3)))
    with pytest.raises(ValueError, match="frame_gravity must be a 2-D float32 or float64"):
        core_run(scene, 5, frame_gravity=np.array([0.0, -9.81]))
    with pytest.raises(ValueError, match="frame_gravity must be C-contiguous"):
        core_run(scene, 5, frame_gravity=np.asfortranarray(good))
    for bad in (np.nan, np.inf):
        rows = good.copy()
        rows[2, 1] = bad
        with pytest.raises(ValueError, match=r"frame_gravity\[2, 1\] = (NaN|inf) is not finite"):
            core_run(scene, 5, frame_gravity=rows)
    assert core_run(scene, 5, frame_gravity=good)[0].shape[0] == 5


def test_a_shake_gives_the_containers_motion_per_frame_and_only_one_context_source():
    water = [Block(Water(), (0.3, 0.4), (0.1, 0.1))]
    shake = Shake(amplitude=0.02, frequency_hz=2.0, phase=0.5)
    result = simulate(MpmScene(water, shake=shake), 6)
    t = np.arange(6) * 0.0025
    omega = 2 * np.pi * 2.0
    expected = np.zeros((6, 6))
    expected[:, 0] = 0.02 * np.sin(omega * t + 0.5)
    expected[:, 2] = 0.02 * omega * np.cos(omega * t + 0.5)
    expected[:, 4] = -0.02 * omega**2 * np.sin(omega * t + 0.5)
    assert result.context.shape == (6, 6) and result.context.dtype == np.float32
    np.testing.assert_allclose(result.context, expected, rtol=1e-6, atol=1e-9)
    # A per-frame context is the trajectory's step context as is; a per-trajectory one tiled.
    np.testing.assert_array_equal(result.to_trajectory().step_context, result.context)
    fixed = simulate(MpmScene(water, context=[0.5, 2.0]), 4).to_trajectory().step_context
    np.testing.assert_array_equal(fixed, np.tile(np.float32([0.5, 2.0]), (4, 1)))
    wrong = MpmResult(result.positions, result.particle_type, result.seconds, result.substeps,
                      result.context[:-1])  # fmt: skip
    with pytest.raises(ValueError, match=r"\(frames, K\) = \(6, K\) per frame, got shape"):
        wrong.to_trajectory()
    # 3D: shaken along z, the context is (frames, 9).
    cube = [Block(Water(), (0.4, 0.5, 0.4), (0.1, 0.1, 0.1))]
    context = simulate(MpmScene(cube, grid=24, shake=Shake(0.01, 1.0, axis=2)), 3).context
    assert context.shape == (3, 9) and not np.delete(context, [2, 5, 8], axis=1).any()

    with pytest.raises(ValueError, match="both shake = .* and context = "):
        MpmScene(water, shake=shake, context=[1.0])
    with pytest.raises(ValueError, match=r"Shake.axis = 2 but the scene is 2D"):
        MpmScene(water, shake=Shake(0.02, 2.0, axis=2))
    with pytest.raises(ValueError, match="Shake.frequency_hz must be > 0, got 0"):
        Shake(0.02, 0.0)
    with pytest.raises(ValueError, match="Shake.amplitude must be finite, got nan"):
        Shake(float("nan"), 1.0)
    with pytest.raises(ValueError, match="Shake.amplitude must be >= 0"):
        Shake(-0.01, 1.0)
