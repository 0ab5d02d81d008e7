"""The 3D presets of `gns generate` (water-3d, sand-3d, goop-3d, boxbath): what issue 25 asks a
user to see from `gns generate --preset P --out D --n-train 1 --n-test 1 --frames 40`, checked
against free fall and the box; the rigid cube keeps its shape; --scale multiplies particles."""

from __future__ import annotations

import json

import numpy as np
import pytest
from gns import mpm
from gns.cli import main
from gns.data import open_dataset
from gns.data.validate import validate_dataset
from gns.mpm import presets

PRESETS_3D = ["water-3d", "sand-3d", "goop-3d", "boxbath"]


@pytest.fixture(scope="module", params=PRESETS_3D)
def dataset(request, tmp_path_factory):
    """The issue's command, through the CLI: 1 train and 1 test trajectory of 40 frames."""
    out = tmp_path_factory.mktemp("gen3d") / request.param
    argv = ["generate", "--preset", request.param, "--out", str(out), "--n-train", "1"]
    assert main([*argv, "--n-test", "1", "--frames", "40", "--quiet"]) == 0
    return request.param, out


def falling(trajectory, preset):
    """The particles that start in the air: all but boxbath's pool (whose water rests)."""
    if preset == "boxbath":
        return trajectory.particle_type == mpm.RIGID_TYPE
    return np.ones(trajectory.n_particles, bool)


def test_positions_are_3d_finite_inside_the_box_and_readable(dataset):
    preset, out = dataset
    assert [str(problem) for problem in validate_dataset(out)] == []
    for split in ("train", "test"):
        (trajectory,) = open_dataset(out, split)
        metadata = open_dataset(out, split).metadata
        assert metadata.dim == 3 and len(metadata.bounds) == 3
        x = trajectory.positions
        assert x.shape == (40, trajectory.n_particles, 3) and np.isfinite(x).all()
        box = np.array(metadata.bounds)
        # The metadata box is the walls' innermost grid nodes, which no particle passes by
        # more than half a cell (gns.mpm.generate.confinement).
        half_cell = 0.5 / presets.preset_scene(preset, 0, split)[0].grid
        assert np.all(x.min(axis=(0, 1)) >= box[:, 0] - half_cell)
        assert np.all(x.max(axis=(0, 1)) <= box[:, 1] + half_cell)


def test_material_in_the_air_falls_at_g_in_the_first_frames(dataset):
    """The mean vertical acceleration of what starts in the air, over frames 1-4, is -g (to
    5%; the blocks are thrown, so only the acceleration is known) and nothing sideways."""
    preset, out = dataset
    (trajectory,) = open_dataset(out, "train")
    dt = open_dataset(out, "train").metadata.dt
    x = trajectory.positions[:6, falling(trajectory, preset)].astype(np.float64).mean(axis=1)
    acceleration = (x[2:] - 2 * x[1:-1] + x[:-2]) / dt**2  # frames 1-4
    np.testing.assert_allclose(acceleration[:, 1], -9.81, rtol=0.05)
    np.testing.assert_allclose(acceleration[:, [0, 2]], 0.0, atol=0.05 * 9.81)


def test_the_metadata_names_the_preset_and_a_3d_radius(dataset):
    preset, out = dataset
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["generator"]["preset"] == preset and "scale" not in meta["generator"]
    scene = presets.preset_scene(preset, 0)[0]
    assert meta["default_connectivity_radius"] == pytest.approx(1.5 * scene.spacing)
    assert meta["dt"] == pytest.approx(scene.frame_dt)


def test_the_boxbath_cube_keeps_its_shape_and_types():
    """BOXBATH's box is rigid: its particles' pairwise distances stay those of frame 0 while it
    falls into the water and floats; the water is DeepMind's type 5, the box type 0."""
    scene, _, lattice_seed = presets.preset_scene("boxbath", 0)
    result = mpm.simulate(scene, 60, seed=lattice_seed)
    types = result.particle_type
    assert set(np.unique(types)) == {mpm.RIGID_TYPE, 5}
    cube = result.positions[:, types == mpm.RIGID_TYPE].astype(np.float64)
    assert cube.shape[1] == 64  # 4 x 4 x 4, as the paper's BOXBATH
    start = np.linalg.norm(cube[0, :, None] - cube[0, None], axis=-1)
    for frame in cube[1:]:
        # float32 positions: their round-off, not the simulator's, bounds the agreement.
        np.testing.assert_allclose(
            np.linalg.norm(frame[:, None] - frame[None], axis=-1), start, atol=1e-5
        )
    # It did move: it fell into the pool.
    assert cube[-1, :, 1].mean() < cube[0, :, 1].mean() - 0.1
    assert 800 <= (types == 5).sum() <= 1700


def test_3d_blocks_start_apart_inside_the_walls_above_the_floor():
    for preset in ("water-3d", "sand-3d", "goop-3d"):
        for index in range(12):
            scene, _, _ = presets.preset_scene(preset, 3, "train", index)
            assert scene.dim == 3 and 1 <= len(scene.blocks) <= 3
            boxes = [(np.array(b.lower), np.array(b.size)) for b in scene.blocks]
            for lower, size in boxes:
                assert lower[1] >= 0.1 + presets.FLOOR_GAP_3D - 1e-12
                assert np.all(lower >= 0.1 + presets.MARGIN - 1e-12)
                assert np.all(lower + size <= 0.9 - presets.MARGIN + 1e-12)
            for i, (lo_a, size_a) in enumerate(boxes):
                for lo_b, size_b in boxes[i + 1 :]:
                    apart = (lo_a + size_a + presets.GAP <= lo_b) | (
                        lo_b + size_b + presets.GAP <= lo_a
                    )
                    assert apart.any()


def test_scale_multiplies_the_particles_and_shrinks_the_radius(tmp_path):
    """--scale 3.375 makes the grid 1.5 times finer in 3D (24 -> 36 cells): 1.5^3 times the
    particles of the same blocks, and a radius 1.5 times smaller, so the same neighbours."""
    scene, _, seed = presets.preset_scene("sand-3d", 4)
    fine, _, fine_seed = presets.preset_scene("sand-3d", 4, scale=3.375)
    assert (scene.grid, fine.grid) == (24, 36) and fine.blocks == scene.blocks
    n, n_fine = (
        len(mpm.particles(s, k)["positions"]) for s, k in ((scene, seed), (fine, fine_seed))
    )
    assert n_fine / n == pytest.approx(3.375, rel=0.15)
    radius = presets.connectivity_radius("sand-3d")
    assert presets.connectivity_radius("sand-3d", 3.375) == pytest.approx(radius / 1.5)
    out = tmp_path / "fine"
    assert (
        main(
            [
                "generate",
                "--preset",
                "sand-3d",
                "--out",
                str(out),
                "--n-train",
                "1",
                "--frames",
                "3",
                "--scale",
                "3.375",
                "--quiet",
                "--seed",
                "4",
            ]
        )
        == 0
    )
    meta = json.loads((out / "metadata.json").read_text())
    assert meta["generator"]["scale"] == 3.375
    assert meta["default_connectivity_radius"] == pytest.approx(radius / 1.5)


@pytest.mark.parametrize("scale", ["0", "-1", "nan", "x"])
def test_a_bad_scale_is_refused_by_name(tmp_path, scale, capsys):
    argv = ["generate", "--preset", "sand-3d", "--out", str(tmp_path / "d"), "--n-train", "1"]
    assert main([*argv, "--scale", scale]) == 2
    assert f"--scale: must be a positive number, got {scale}" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()
    with pytest.raises(ValueError, match="scale must be a positive number"):
        presets.preset_scene("sand-3d", 0, scale=float(scale) if scale != "x" else scale)
