"""Config: the paper's defaults, TOML loading, unknown keys and bad values rejected."""

from __future__ import annotations

import pytest
from gns.config import (
    Config,
    ModelConfig,
    NoiseConfig,
    SceneConfig,
    from_dict,
    load_config,
    to_dict,
)
from gns.simulator import Scene


def test_defaults_are_the_papers():
    c = Config()
    m = c.model
    assert (m.latent_size, m.mlp_hidden_size, m.mlp_hidden_layers) == (128, 128, 2)
    assert m.message_passing_steps == 10 and m.velocity_history == 5
    assert m.particle_type_embedding_size == 16 and m.layer_norm and m.edge_latent_updates
    assert m.mlp_encoder_decoder and not m.global_latent and not m.add_gravity
    assert (c.noise.type, c.noise.std, c.noise.correct_position_fraction) == (
        "random_walk",
        3e-4,
        0.0,
    )
    assert c.normalization.source == "running"
    assert c.scene.kinematic_particle_types is None  # the dataset's, default {3}


def test_toml_overrides_only_what_it_names(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text(
        """
[model]
latent_size = 64
message_passing_steps = 5
global_latent = true

[noise]
type = "uncorrelated"
std = 6.7e-4

[scene]
kinematic_particle_types = [1, 2, -1]
gravity = [0, -9.81]
"""
    )
    c = load_config(path)
    assert c.model.latent_size == 64 and c.model.message_passing_steps == 5
    assert c.model.global_latent and c.model.mlp_hidden_size == 128
    assert c.noise == NoiseConfig(type="uncorrelated", std=6.7e-4)
    assert c.scene.kinematic_particle_types == (1, 2, -1)
    assert c.scene.gravity == (0.0, -9.81) and isinstance(c.scene.gravity[0], float)
    assert from_dict(Config, to_dict(c)) == c


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[model]\nlatnet_size = 64\n", "unknown setting 'model.latnet_size'"),
        ("[modle]\nlatent_size = 64\n", "unknown setting 'modle'"),
        ("[model]\nlatent_size = 64.5\n", "model.latent_size must be a whole number"),
        ("[model]\nlayer_norm = 1\n", "model.layer_norm must be true or false"),
        ("[noise]\ntype = 'brownian'\n", "noise.type must be one of"),
        ("[model]\nmessage_passing_steps = 0\n", "message_passing_steps must be positive"),
        ("[noise]\ncorrect_position_fraction = 2.0\n", r"must be in \[0, 1\]"),
        ("[scene]\ngravity = 'down'\n", "scene.gravity must be a list"),
        ("model = 3\n", "model must be a table"),
        ("[model\n", "not valid TOML"),
    ],
)
def test_bad_files_fail_with_a_message_naming_the_problem(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        load_config(path)


def test_configs_are_frozen():
    with pytest.raises(AttributeError):
        ModelConfig().latent_size = 3  # type: ignore[misc]


def test_a_scene_round_trips_through_a_plain_dict():
    scene = Scene(
        dim=2,
        radius=0.015,
        particle_types=(6, 3),
        bounds=((0.1, 0.9), (0.1, 0.9)),
        walls=True,
        context_size=1,
        gravity=(0.0, -6e-5),
    )
    again = from_dict(Scene, to_dict(scene))
    assert again == scene and again.particle_types == (3, 6)
    with pytest.raises(ValueError, match="unknown setting 'radus'"):
        from_dict(Scene, {**to_dict(scene), "radus": 1.0})
    assert from_dict(SceneConfig, {}) == SceneConfig()
