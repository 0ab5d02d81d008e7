"""Settings as frozen dataclasses with the paper's defaults, loaded from TOML, never executed.

    [model]          the network: the GNS's encoder-processor-decoder (section C.1), or with
                     kind = "cconv" the continuous-convolution baseline of section D.1, whose
                     own settings are [model.cconv]
    [noise]          input noise (sections B.3 and C.2)
    [normalization]  running statistics (B.2) or the dataset's metadata.json
    [scene]          how a dataset's facts become the model's inputs (walls, context, ...)
    [train]          optimiser, learning-rate schedule, batches, validation and checkpoints

`from_dict` builds any of these dataclasses (or `Scene`) from a plain dict, checking every value's
type and rejecting keys it does not know with a ValueError that names the key, so a typo in a
config file fails loudly instead of silently training the default model.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, TypeVar

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

__all__ = [
    "CConvConfig",
    "Config",
    "IMPLEMENTATIONS",
    "MODEL_KINDS",
    "MODEL_NAMES",
    "ModelConfig",
    "NoiseConfig",
    "NormalizationConfig",
    "SceneConfig",
    "TrainConfig",
    "NOISE_TYPES",
    "from_dict",
    "load_config",
    "to_dict",
]

# Each Literal's values as a tuple too (typing.get_args), for the checks that a value is one.
NoiseType = Literal["random_walk", "only_last", "correlated", "uncorrelated"]
NOISE_TYPES: tuple[NoiseType, ...] = typing.get_args(NoiseType)
NormalizationSource = Literal["running", "metadata"]
NORMALIZATION_SOURCES: tuple[NormalizationSource, ...] = typing.get_args(NormalizationSource)
Implementation = Literal["fast", "plain"]
IMPLEMENTATIONS: tuple[Implementation, ...] = typing.get_args(Implementation)
Precision = Literal["auto", "fp32", "bf16"]
PRECISIONS: tuple[Precision, ...] = typing.get_args(Precision)
ModelKind = Literal["gns", "cconv"]
MODEL_KINDS: tuple[ModelKind, ...] = typing.get_args(ModelKind)
# How reports and logs name each kind of model.
MODEL_NAMES = {"gns": "GNS", "cconv": "CConv"}
CoordinateMapping = Literal["ball_to_cube_volume_preserving", "ball_to_cube_radial", "identity"]
COORDINATE_MAPPINGS: tuple[CoordinateMapping, ...] = typing.get_args(CoordinateMapping)
Window = Literal["poly6", "none"]
WINDOWS: tuple[Window, ...] = typing.get_args(Window)


def _positive(owner: object, *names: str) -> None:
    for name in names:
        value = getattr(owner, name)
        if not value > 0:
            raise ValueError(f"{type(owner).__name__}.{name} must be positive, got {value!r}")


@dataclass(frozen=True)
class CConvConfig:
    """The continuous convolutions of Ummenhofer et al. (2020), section D.1's CConv baseline
    (model.kind = "cconv"; see gns.cconv).

    layer_channels: the output width of every layer but the last, whose width is D (the
        acceleration): (32, 64, 64) is the original's 32/64/64/3. The first layer runs a
        convolution and a dense layer side by side, each layer_channels[0] wide, and
        concatenates them.
    kernel_size: cells per axis of the grid of weight matrices (4: 4 x 4 in 2D, 4 x 4 x 4 in
        3D, as the original).
    coordinate_mapping: Lambda, how a displacement / R (in the unit ball) is placed in the
        kernel's cube [-1, 1]^D before interpolating: "ball_to_cube_volume_preserving" (the
        original's: equal volumes of the ball get equal shares of the cells),
        "ball_to_cube_radial" (radial stretching) or "identity" (the ball's corners unused).
    window: a(x_j, x_i), the weight of a neighbour by distance: "poly6", (1 - r^2)^3 with
        r = |x_j - x_i| / R (the original's; smooth as neighbours enter and leave), or "none".
    normalize: divide each receiver's sum by its number of neighbours, psi(x_i); the original
        (and D.1) set psi = 1.
    """

    layer_channels: tuple[int, ...] = (32, 64, 64)
    kernel_size: int = 4
    coordinate_mapping: CoordinateMapping = "ball_to_cube_volume_preserving"
    window: Window = "poly6"
    normalize: bool = False

    def __post_init__(self) -> None:
        if not self.layer_channels or any(
            isinstance(c, bool) or not isinstance(c, int) or c < 1 for c in self.layer_channels
        ):
            raise ValueError(
                "CConvConfig.layer_channels must be one or more positive widths, got "
                f"{list(self.layer_channels)}"
            )
        if isinstance(self.kernel_size, bool) or not (
            isinstance(self.kernel_size, int) and self.kernel_size >= 1
        ):
            raise ValueError(
                f"CConvConfig.kernel_size must be a whole number >= 1, got {self.kernel_size!r}"
            )
        if self.coordinate_mapping not in COORDINATE_MAPPINGS:
            raise ValueError(
                f"CConvConfig.coordinate_mapping must be one of {list(COORDINATE_MAPPINGS)}, "
                f"got {self.coordinate_mapping!r}"
            )
        if self.window not in WINDOWS:
            raise ValueError(f"CConvConfig.window must be 'poly6' or 'none', got {self.window!r}")


# ModelConfig fields that only the GNS reads: set with kind = "cconv" they would do nothing.
GNS_ONLY = (
    "latent_size",
    "mlp_hidden_size",
    "mlp_hidden_layers",
    "message_passing_steps",
    "layer_norm",
    "mlp_encoder_decoder",
    "global_latent",
    "edge_latent_updates",
    "torch_compile",
)


@dataclass(frozen=True)
class ModelConfig:
    """The network: the encoder-processor-decoder and its section C.1 options, or CConv.

    kind: "gns" (EncodeProcessDecode) or "cconv" (section D.1's baseline, gns.cconv.CConv,
        set up by `cconv`). Both read the same features and predict the same normalised
        acceleration, so everything around the network is shared. With "cconv", setting a
        GNS-only field is an error, as is setting `cconv` with "gns": a setting that would do
        nothing fails loudly. Shared by both: velocity_history, self_edges, add_gravity,
        particle_type_embedding_size, implementation and precision (for CConv "fast" sums over
        neighbourhoods with one sparse matrix, "plain" with index_add_; see gns.cconv).

    velocity_history: C, the number of input velocities (the model reads C + 1 positions).
    mlp_encoder_decoder: False replaces the encoder and decoder MLPs by single linear layers.
    self_edges: include the edge i -> i in the radius graph.
    global_latent: a latent of the whole scene, updated at every message-passing step from the
        sums of the node updates and messages and read by every node and edge at the next: the
        scene's global context is its input when there is one (False appends the context to
        every node instead), a learned vector otherwise. It reaches every particle within two
        steps, where a particle's own neighbourhood fades within 2-3 hops (docs/probes.md).
    edge_latent_updates: False keeps the encoded edge latents fixed through the processor.
    add_gravity: add the scene's gravity to the decoded acceleration, so the network predicts
        only the deviation from free fall.

    How the network runs; none of these changes its parameters (checkpoints load either way):
    implementation: "fast" (split first edge layer, see gns.model.InteractionNetwork) or
        "plain", the readable reference; the same function up to float round-off.
    precision: "bf16" runs the network under bfloat16 autocast (losses, statistics and the
        integration stay float32), "fp32" never. "auto" trains in fp32 (the paper's; bf16
        gradients are not always faster and round more), and in rollouts tries bf16 where it is
        native (CUDA with bf16, CPUs with AVX512-BF16 or AMX), keeping it only when it runs
        this model measurably faster and within gns.rollout.BF16_TOLERANCE of fp32.
    torch_compile: torch.compile the fast path (dynamic shapes); opt-in because compiling takes
        tens of seconds, and it falls back to eager with a warning where it cannot compile.
    """

    latent_size: int = 128
    mlp_hidden_size: int = 128
    mlp_hidden_layers: int = 2
    message_passing_steps: int = 10
    layer_norm: bool = True
    mlp_encoder_decoder: bool = True
    self_edges: bool = True
    global_latent: bool = False
    edge_latent_updates: bool = True
    add_gravity: bool = False
    particle_type_embedding_size: int = 16
    velocity_history: int = 5
    implementation: Implementation = "fast"
    precision: Precision = "auto"
    torch_compile: bool = False
    kind: ModelKind = "gns"
    cconv: CConvConfig = field(default_factory=CConvConfig)

    def __post_init__(self) -> None:
        if self.kind not in MODEL_KINDS:
            raise ValueError(
                f"ModelConfig.kind must be one of {list(MODEL_KINDS)}, got {self.kind!r}"
            )
        defaults = {f.name: f.default for f in dataclasses.fields(self)}
        if self.kind == "cconv":
            changed = [name for name in GNS_ONLY if getattr(self, name) != defaults[name]]
            if changed:
                raise ValueError(
                    f"model.{', model.'.join(changed)}: GNS settings, but model.kind is 'cconv' "
                    "(whose settings are model.cconv); remove them or set model.kind = 'gns'"
                )
        elif self.cconv != CConvConfig():
            raise ValueError(
                f"model.cconv shapes the CConv only, but model.kind is {self.kind!r}; set "
                "model.kind = 'cconv' or remove model.cconv"
            )
        _positive(
            self,
            "latent_size",
            "mlp_hidden_size",
            "message_passing_steps",
            "particle_type_embedding_size",
            "velocity_history",
        )
        if self.mlp_hidden_layers < 0:
            raise ValueError(
                f"ModelConfig.mlp_hidden_layers must be >= 0, got {self.mlp_hidden_layers}"
            )
        if self.implementation not in IMPLEMENTATIONS:
            raise ValueError(
                f"ModelConfig.implementation must be 'fast' or 'plain', got {self.implementation!r}"
            )
        if self.precision not in PRECISIONS:
            raise ValueError(
                f"ModelConfig.precision must be 'auto', 'fp32' or 'bf16', got {self.precision!r}"
            )


@dataclass(frozen=True)
class NoiseConfig:
    """Input noise.

    type: how velocity noise accumulates over the C input steps (section C.2).
    std: standard deviation of the velocity noise at the last input step (every type is scaled
        so this is the same, as in C.2), per frame.
    correct_position_fraction: 0 trains the model to cancel the noise in the input velocity
        (the paper's default), 1 to cancel the noise in the input position.
    wall_push: 0 (off), or the std, in radii, of a shift into the wall given to every free
        particle within one radius of a wall, whose target stays the true next position
        (gns.noise.wall_push). The data never puts a particle inside a wall, so without it a
        model learns no force that pushes one back out.
    wall_push_through_only: shift only the particles whose shift takes them past the wall;
        the others keep their inputs and targets (otherwise every particle within one radius
        is shifted, and the layer at a wall learns a push the data does not have).
    exact_last_position: shift the noise of every input position by that of the most recent
        one, so the velocities carry the configured noise and the most recent position, from
        which neighbours and walls are read, carries none: the model is taught to take back
        noise in a particle's velocity without being shown a packing or a surface the data
        does not have (correct_position_fraction then has nothing to correct).
    std_min: None (every window gets `std`), or the lower end of a std drawn for each training
        window uniformly from [std_min, std]. A model trained at one std is never shown inputs
        cleaner than that, and a rollout's are (`probe.py fall --noise-draws` reads what that
        changes); with std_min = 0 the clean end is part of training (on sand2d-taichi that
        kept the rows of a falling block as uneven and lost the landing: sand-ablation.md,
        session 43).
    """

    type: NoiseType = "random_walk"
    std: float = 3e-4
    std_min: float | None = None
    correct_position_fraction: float = 0.0
    wall_push: float = 0.0
    wall_push_through_only: bool = False
    exact_last_position: bool = False

    def __post_init__(self) -> None:
        if self.type not in NOISE_TYPES:
            raise ValueError(f"NoiseConfig.type must be one of {NOISE_TYPES}, got {self.type!r}")
        if not (math.isfinite(self.std) and self.std >= 0):
            raise ValueError(f"NoiseConfig.std must be finite and >= 0, got {self.std}")
        if self.std_min is not None and not 0 <= self.std_min <= self.std:
            raise ValueError(
                f"NoiseConfig.std_min must be in [0, std = {self.std}], got {self.std_min}"
            )
        if not (math.isfinite(self.wall_push) and self.wall_push >= 0):
            raise ValueError(f"NoiseConfig.wall_push must be finite and >= 0, got {self.wall_push}")
        if not 0.0 <= self.correct_position_fraction <= 1.0:
            raise ValueError(
                "NoiseConfig.correct_position_fraction must be in [0, 1], got "
                f"{self.correct_position_fraction}"
            )


@dataclass(frozen=True)
class NormalizationConfig:
    """source: "running" accumulates exact statistics of everything seen in training, after
    noise (B.2); "metadata" uses metadata.json's statistics with the velocity and acceleration
    std inflated by the noise std (docs/formats.md, "Statistics").
    min_std: a std below this is treated as 1 (a constant feature is centred, not blown up).
    """

    source: NormalizationSource = "running"
    min_std: float = 1e-7

    def __post_init__(self) -> None:
        if self.source not in NORMALIZATION_SOURCES:
            raise ValueError(
                f"NormalizationConfig.source must be 'running' or 'metadata', got {self.source!r}"
            )
        if not self.min_std >= 0:
            raise ValueError(f"NormalizationConfig.min_std must be >= 0, got {self.min_std}")


@dataclass(frozen=True)
class SceneConfig:
    """How a dataset's metadata becomes the model's inputs (see simulator.Scene.from_metadata).

    radius: connectivity radius; None takes metadata's default_connectivity_radius.
    walls: add clipped wall distances when the metadata has bounds (non-periodic axes only).
    context: use the dataset's global context (step_context) when it has one.
    material_property: use the per-particle material property; None uses it only when the
        dataset has no context (sand2d-taichi carries the friction angle as both).
    kinematic_particle_types: None takes the dataset's (default {3}).
    gravity: physical gravity (m/s^2, one value per axis) for model.add_gravity; converted to
        per-frame units with the dataset's dt.
    wall_clip: wall distances are clipped to [-wall_clip, wall_clip] radii; None takes the
        metadata's boundary_augment (1, the paper's clip at the radius, when absent). A larger
        clip lets the model see a wall coming when particles move more than a radius a step.
    obstacles: add the nearest static obstacle shape of each trajectory (metadata.json's
        "obstacles", as `gns generate` writes for ramps) as D node features; None: when the
        dataset has obstacles.
    obstacle_clip: how many radii away an obstacle is seen; None takes the wall clip.
    enforce_walls: in rollouts (validation's among them), put every free particle that a step
        takes past a wall (the bounds of a non-periodic axis) back on it, as a simulator's
        walls do; each correction is counted in the rollout's metadata (gns.rollout). Off, the
        paper's way: the network alone keeps the sand in the box. Training targets are the
        data's either way.
    overburden: add what lies in the column above each particle (gns.overburden; needs
        gravity): not the paper's, an input for the weight a 2-3 hop neighbourhood cannot see.
    wall_basis: K > 0 adds, for every wall, K Gaussians of the distance (in radii) from that
        wall to where a free step would take the particle (its last velocity plus gravity),
        centred at 0, 1, ..., K - 1 radii, std half a radius (gns.simulator.wall_basis). A
        landing decelerates a particle only in the step that would take it within a radius or
        two of the floor: a step in that distance, which the clipped distance feeds the network
        only as a slope to fit. 0 (the paper's): none. On the sand model's first stage (K = 6,
        two seeds, 16000 steps) it halved the braking of slower sand 2-4 R above the floor,
        not of the fastest, and packed the landings more (docs/sand-ablation.md, session 44).
    """

    radius: float | None = None
    walls: bool = True
    context: bool = True
    material_property: bool | None = None
    kinematic_particle_types: tuple[int, ...] | None = None
    gravity: tuple[float, ...] | None = None
    wall_clip: float | None = None
    obstacles: bool | None = None
    obstacle_clip: float | None = None
    enforce_walls: bool = False
    overburden: bool = False
    wall_basis: int = 0

    def __post_init__(self) -> None:
        for name in ("radius", "wall_clip", "obstacle_clip"):
            if getattr(self, name) is not None:
                _positive(self, name)
        if isinstance(self.wall_basis, bool) or not (
            isinstance(self.wall_basis, int) and self.wall_basis >= 0
        ):
            raise ValueError(
                f"SceneConfig.wall_basis must be an integer >= 0, got {self.wall_basis!r}"
            )
        if self.wall_basis and not self.walls:
            raise ValueError(f"SceneConfig.wall_basis = {self.wall_basis} needs walls = true")


@dataclass(frozen=True)
class TrainConfig:
    """Training (section B.4 of the paper for the optimiser and schedule).

    steps: gradient steps in all (the paper trains for up to 20M).
    learning_rate, learning_rate_final, learning_rate_decay_steps: Adam with
        lr(j) = final + (start - final) * 0.1 ** (j / decay_steps).
    batch_size: windows (graphs) per batch, the paper's 2. batch_particles: also cap a batch at
        this many particles (0: no particle budget), so large scenes do not exhaust memory.
    trajectories_in_memory: how many trajectories are loaded and shuffled together; each epoch
        visits trajectories in a fresh random order, this many at a time.
    log_every: steps between loss lines in the logs. validate_every: steps between validations
        (0: never) on the valid split: one-step MSE over validation_windows fixed windows and
        rollouts of validation_rollout_steps steps on validation_rollouts trajectories.
    checkpoint_every: steps between checkpoints (one is always written at the end);
        keep_checkpoints: how many of the newest to keep.
    seed: data order, noise, mirroring and initial weights.
    mirror_axes: axes along which each training window is mirrored with probability 1/2 (about
        the box's centre; gns.augment), for scenes symmetric along them; none by default, as
        in the paper. Positions and obstacle shapes are mirrored, the global context is not:
        a scene whose context has a direction (fluidshake's container state) must not mirror.
    spike_factor: a step whose loss exceeds this many times the median loss of the previous
        100 steps (once there are 20) is reported as a loss spike, on stderr and in spikes.csv,
        with the batch's windows; training goes on. 0 turns the check off. (Non-finite losses
        and gradients always stop training.)
    loss_steps: the loss of each window adds up this many steps: the first from the (noisy)
        input as always, each later one from the model's own prediction fed back, so the
        gradient runs through the predictions (Ummenhofer et al. 2020 train CConv on 2, and
        input noise stays on). 1, the GNS paper's loss, by default. Windows are then
        loss_steps - 1 frames longer; the step context is taken at a window's last input frame
        and serves every step (where it changes within a trajectory, the earlier steps see the
        context of a frame up to loss_steps - 1 frames after their own).
    pushforward: the pushforward trick (Brandstetter et al. 2022; LagrangeBench's unrolled
        noise): weights w_0, w_1, ... such that each batch's input is first pushed k steps
        forward by the model itself, without gradient, with probability w_k / sum(w); the loss
        is then the one step from there to the ground truth (shifted by the kept input noise,
        as always). The model so trains on inputs with its own errors in them, which noise
        alone only imitates. E.g. [18, 2, 1, 1], LagrangeBench's mix once all its stages are
        on. Empty (the paper's): no pushforward. Windows are len - 1 frames longer; not with
        loss_steps > 1. k is drawn from (seed, step), so a resumed run pushes the same.
    max_grad_norm: clip each step's gradient to this 2-norm (over all parameters) before Adam
        applies it; None (the paper's) does not clip. On a dataset with rare impacts (blocks
        of sand landing) a few percent of batches carry most of the gradient's energy, and
        Adam's step size shrinks for all the others; train.csv logs the median norm
        (grad_norm) and the share of steps clipped, to choose the value from. On the sand
        model, clipping at 3 (about the median norm) kept every validation rollout from
        diverging and lowered test MSE over 3 seeds, but fitted the landings less and cut the
        runout (docs/sand-ablation.md).
    huber_delta: the loss per particle and dimension is the Huber loss of the normalised
        acceleration error with this delta, scaled to equal the squared error below it
        (r^2 for |r| <= delta, 2 delta |r| - delta^2 beyond); None (the paper's): the squared
        error everywhere. For data where a few impacts hold most of the acceleration's
        variance and so drive the gradient (sand: the largest 1% of the accelerations hold
        about 80% of their squares, the moments of landing). It fits towards the majority
        of what the network cannot tell apart, not the mean: on the sand model, trained from
        the start with delta 1, sand falling near the floor no longer brakes for a landing
        that may come, but the few large stops are treated as outliers (a landing fitted
        at a third of its size by 16000 steps), and the landings pack more
        (docs/sand-ablation.md, session 45).
    target_weight: each particle's loss is multiplied by 1 + target_weight |a|, |a| the 2-norm
        of its normalised target acceleration, so that impacts count more than their square
        alone; 0 (the paper's): every particle alike. On the sand model neither this nor
        huber_delta helped: each moved the fit between the flow and the landings and rolled
        out worse than the squared error (docs/sand-ablation.md).
    early_steps, early_repeat: the windows whose first target is among a trajectory's first
        early_steps predicted frames are drawn early_repeat times per epoch, the others once,
        for data whose motion is mostly at the start (a block falls, lands and spreads, then
        rests); 0 and 1 (the paper's): every window alike. On the sand model (30 steps, 3
        times) it fitted the flow better and moved neither runout nor density (one seed,
        docs/sand-ablation.md).
    """

    steps: int = 20_000_000
    learning_rate: float = 1e-4
    learning_rate_final: float = 1e-6
    learning_rate_decay_steps: float = 5e6
    batch_size: int = 2
    batch_particles: int = 0
    trajectories_in_memory: int = 64
    log_every: int = 100
    validate_every: int = 10_000
    validation_windows: int = 256
    validation_rollouts: int = 2
    validation_rollout_steps: int = 50
    checkpoint_every: int = 10_000
    keep_checkpoints: int = 3
    seed: int = 0
    mirror_axes: tuple[int, ...] = ()
    spike_factor: float = 10.0
    loss_steps: int = 1
    pushforward: tuple[float, ...] = ()
    max_grad_norm: float | None = None
    huber_delta: float | None = None
    target_weight: float = 0.0
    early_steps: int = 0
    early_repeat: int = 1

    @property
    def extra_frames(self) -> int:
        """How many frames past the first target a window holds (loss_steps, pushforward)."""
        return max(self.loss_steps, len(self.pushforward)) - 1

    def __post_init__(self) -> None:
        _positive(
            self,
            "steps",
            "learning_rate",
            "learning_rate_decay_steps",
            "batch_size",
            "trajectories_in_memory",
            "log_every",
            "checkpoint_every",
            "keep_checkpoints",
            "loss_steps",
            "early_repeat",
        )
        if self.pushforward and not (
            all(math.isfinite(w) and w >= 0 for w in self.pushforward) and sum(self.pushforward) > 0
        ):
            raise ValueError(
                "TrainConfig.pushforward must be weights >= 0 with a positive sum, got "
                f"{list(self.pushforward)}"
            )
        if self.pushforward and self.loss_steps > 1:
            raise ValueError(
                "TrainConfig.pushforward and loss_steps > 1 are alternatives (both lengthen the "
                f"windows); got pushforward {list(self.pushforward)} with loss_steps "
                f"{self.loss_steps}"
            )
        if not 0 <= self.learning_rate_final <= self.learning_rate:
            raise ValueError(
                "TrainConfig.learning_rate_final must be in [0, learning_rate], got "
                f"{self.learning_rate_final}"
            )
        for name in (
            "batch_particles",
            "validate_every",
            "validation_windows",
            "validation_rollouts",
            "validation_rollout_steps",
            "early_steps",
        ):
            if getattr(self, name) < 0:
                raise ValueError(f"TrainConfig.{name} must be >= 0, got {getattr(self, name)}")
        if len(set(self.mirror_axes)) != len(self.mirror_axes) or any(
            a < 0 for a in self.mirror_axes
        ):
            raise ValueError(
                f"TrainConfig.mirror_axes must be distinct axes >= 0, got {list(self.mirror_axes)}"
            )
        if not (self.spike_factor == 0 or self.spike_factor > 1):  # NaN fails both
            raise ValueError(
                f"TrainConfig.spike_factor must be 0 (off) or above 1, got {self.spike_factor}"
            )
        if self.max_grad_norm is not None:
            _positive(self, "max_grad_norm")
        if self.huber_delta is not None:
            _positive(self, "huber_delta")
        if not self.target_weight >= 0:  # NaN fails too
            raise ValueError(f"TrainConfig.target_weight must be >= 0, got {self.target_weight!r}")

    def learning_rate_at(self, step: int) -> float:
        """The learning rate of gradient step `step` (0-based)."""
        decay = 0.1 ** (step / self.learning_rate_decay_steps)
        return self.learning_rate_final + (self.learning_rate - self.learning_rate_final) * decay


@dataclass(frozen=True)
class Config:
    model: ModelConfig = field(default_factory=ModelConfig)
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    normalization: NormalizationConfig = field(default_factory=NormalizationConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    train: TrainConfig = field(default_factory=TrainConfig)


# The sections of a Config that define the model (its network and inputs); [noise] and [train]
# say only how its weights were trained. Fine-tuning keeps these (gns.train), and checkpoints
# average only when these agree (gns.checkpoints.export_model).
MODEL_SECTIONS = ("model", "scene", "normalization")

T = TypeVar("T")


def _convert(value: Any, hint: Any, where: str) -> Any:
    """`value` checked (and lists made tuples) against the type hint `hint`."""
    origin = typing.get_origin(hint)
    args = typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors = []
        for option in args:
            if option is type(None):
                continue
            try:
                return _convert(value, option, where)
            except ValueError as err:
                errors.append(str(err))
        raise ValueError(errors[0] if len(errors) == 1 else f"{where}: got {value!r}")
    if origin is Literal:
        if value not in args:
            raise ValueError(f"{where} must be one of {list(args)}, got {value!r}")
        return value
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{where} must be a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(v, args[0], f"{where}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ValueError(f"{where} must have {len(args)} items, got {len(value)}")
        pairs = enumerate(zip(args, value, strict=True))
        return tuple(_convert(v, a, f"{where}[{i}]") for i, (a, v) in pairs)
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if isinstance(value, hint):
            return value
        if not isinstance(value, Mapping):
            raise ValueError(f"{where} must be a table of settings, got {value!r}")
        return from_dict(hint, value, where)
    if hint is bool:
        if not isinstance(value, bool):
            raise ValueError(f"{where} must be true or false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{where} must be a whole number, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"{where} must be a number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ValueError(f"{where} must be a string, got {value!r}")
        return value
    raise TypeError(f"{where}: unsupported setting type {hint!r}")


def from_dict(cls: type[T], data: Mapping[str, Any], where: str = "") -> T:
    """Build the dataclass `cls` from a (possibly nested) dict; unknown keys raise ValueError."""
    if not isinstance(data, Mapping):
        raise ValueError(f"{where or cls.__name__} must be a table of settings, got {data!r}")
    hints = typing.get_type_hints(cls)
    fields = {f.name for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]
    prefix = f"{where}." if where else ""
    for key in data:
        if key not in fields:
            raise ValueError(
                f"unknown setting '{prefix}{key}' for {cls.__name__}; "
                f"known: {', '.join(sorted(fields))}"
            )
    kwargs = {key: _convert(value, hints[key], f"{prefix}{key}") for key, value in data.items()}
    return cls(**kwargs)


def to_dict(obj: Any) -> dict[str, Any]:
    """A dataclass as a plain dict (tuples become lists) that `from_dict` reads back."""

    def plain(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items()}
        if isinstance(value, (tuple, list)):
            return [plain(v) for v in value]
        if isinstance(value, (frozenset, set)):
            return sorted(plain(v) for v in value)
        return value

    return plain(dataclasses.asdict(obj))


def load_config(path: str | os.PathLike[str]) -> Config:
    """Read a TOML file (or a run's config.json) into a Config; missing settings keep the
    paper's defaults."""
    with open(path, "rb") as f:
        try:
            if os.fspath(path).endswith(".json"):
                data = json.load(f)
            else:
                data = tomllib.load(f)
        except (tomllib.TOMLDecodeError, json.JSONDecodeError) as err:
            raise ValueError(f"{os.fspath(path)}: not valid TOML/JSON: {err}") from err
    try:
        return from_dict(Config, data)
    except ValueError as err:
        raise ValueError(f"{os.fspath(path)}: {err}") from err
