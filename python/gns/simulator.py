"""LearnedSimulator: positions in, positions out, with the network (EncodeProcessDecode, or the
CConv baseline of section D.1 when model.kind = "cconv") in between.

    preprocess   position sequence (N, C + 1, D) -> velocities, radius graph (Rust), wall and
                 obstacle distances, type embedding, context -> normalised node / edge features
    model        EncodeProcessDecode or CConv -> normalised acceleration (N, D); both read the
                 same node and edge features (CConv takes its displacements from the edges')
    postprocess  de-normalise (+ gravity) -> semi-implicit Euler with dt = 1 frame -> (N, D)

`target_normalized_acceleration` is the inverse of the postprocess, next to its twin.

What the model is built from is a `Scene`, the facts of one dataset: a scene without walls gets
no wall features, one particle type gets no embedding, no context gets no global input. Every
input width follows from the scene; nothing here knows a particular dataset.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch
from torch import Tensor, nn

import gns.ops as ops
from gns.cconv import CConv
from gns.config import Config, SceneConfig
from gns.data.stride import frame_stride
from gns.model import EncodeProcessDecode
from gns.noise import sample_noise, wall_push
from gns.normalization import FixedNormalizer, Normalizer, RunningNormalizer
from gns.overburden import overburden

__all__ = ["LearnedSimulator", "Scene", "edge_capacity", "pad_edges"]


def wall_basis(
    positions: Tensor,
    bounds: Sequence[tuple[float, float]],
    axes: Sequence[int],
    radius: float,
    k: int,
) -> Tensor:
    """(N, 2 A K): for each of the A `axes`, the distance of `positions` (N, D) to the lower
    then the upper bound (`bounds`, D pairs), in radii, through K Gaussians centred at 0, 1,
    ..., K - 1 radii with std 1/2 (exp(-2 (d - k)^2)); columns: the lower bounds of `axes`,
    then the upper bounds, each K wide. Given where a free step takes a particle, a network
    reads off in one layer whether that step lands it (scene.wall_basis)."""
    lower = [positions[:, a] - bounds[a][0] for a in axes]
    upper = [bounds[a][1] - positions[:, a] for a in axes]
    distance = torch.stack(lower + upper, dim=1) / radius
    centres = torch.arange(k, dtype=positions.dtype, device=positions.device)
    basis = torch.exp(-2.0 * (distance[:, :, None] - centres) ** 2)
    return basis.reshape(len(positions), -1)


class _Statistics(Protocol):
    """metadata.json's statistics: gns.data.Metadata or gns.data.Statistics."""

    vel_mean: Any
    vel_std: Any
    acc_mean: Any
    acc_std: Any
    context_mean: Any
    context_std: Any


@dataclass(frozen=True)
class Scene:
    """The facts of a dataset that shape the model's inputs.

    dim: D. radius: connectivity radius R. particle_types: the type ids that occur (an
    embedding only when there are several). bounds: D pairs (lo, hi), or None; walls: add the
    clipped distances to the bounds on every non-periodic axis (2 features per axis).
    periodic: per-axis flags (the box is `bounds`). context_size: width of the per-graph global
    context (0: none). material_property_size: width of the per-particle material property.
    kinematic_particle_types: no noise, no loss, ground truth in rollouts. gravity: per-frame
    acceleration (D,), used by model.add_gravity. wall_clip: wall distances are clipped to
    [-wall_clip, wall_clip] radii. obstacles: add the nearest static obstacle shape (D
    features, gns.ops.nearest_obstacle_features), seen from obstacle_clip radii; the shapes
    come with the data (each trajectory's, metadata.json's "obstacles"). dt: seconds between
    the data's frames (metadata.json's dt), so one step of the model, which is applied to
    frames that far apart (see LearnedSimulator.frame_stride_for); None in checkpoints
    written before it was recorded. overburden: add the count and the upward momentum of the
    free particles in the column above each particle (gns.overburden, 2 features, half-width
    R / 2, up against `gravity`). wall_basis: K Gaussians per wall of where a free step takes
    each particle (wall_basis(), 2 K features per wall axis; needs walls).
    """

    dim: int
    radius: float
    particle_types: tuple[int, ...]
    bounds: tuple[tuple[float, float], ...] | None = None
    walls: bool = False
    periodic: tuple[bool, ...] = ()
    context_size: int = 0
    material_property_size: int = 0
    kinematic_particle_types: tuple[int, ...] = (3,)
    gravity: tuple[float, ...] | None = None
    wall_clip: float = 1.0
    dt: float | None = None
    obstacles: bool = False
    obstacle_clip: float = 1.0
    overburden: bool = False
    wall_basis: int = 0

    def __post_init__(self) -> None:
        if self.dim not in (2, 3):
            raise ValueError(f"Scene.dim must be 2 or 3 (the radius graph's), got {self.dim}")
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"Scene.radius must be positive, got {self.radius}")
        if not self.particle_types:
            raise ValueError("Scene.particle_types must name at least one type")
        object.__setattr__(self, "particle_types", tuple(sorted(set(self.particle_types))))
        object.__setattr__(
            self, "kinematic_particle_types", tuple(sorted(set(self.kinematic_particle_types)))
        )
        if self.bounds is not None and len(self.bounds) != self.dim:
            raise ValueError(f"Scene.bounds has {len(self.bounds)} pairs for dim {self.dim}")
        if not self.periodic:
            object.__setattr__(self, "periodic", (False,) * self.dim)
        if len(self.periodic) != self.dim:
            raise ValueError(f"Scene.periodic has {len(self.periodic)} flags for dim {self.dim}")
        if (self.walls or any(self.periodic)) and self.bounds is None:
            raise ValueError("walls and periodic axes need Scene.bounds")
        if self.gravity is not None and len(self.gravity) != self.dim:
            raise ValueError(f"Scene.gravity has {len(self.gravity)} values for dim {self.dim}")
        if self.context_size < 0 or self.material_property_size < 0:
            raise ValueError("context_size and material_property_size must be >= 0")
        for name in ("wall_clip", "obstacle_clip"):
            if not getattr(self, name) > 0:
                raise ValueError(f"Scene.{name} must be positive, got {getattr(self, name)}")
        if self.overburden and (self.gravity is None or any(self.periodic)):
            raise ValueError(
                "Scene.overburden needs the scene's gravity (scene.gravity, for which way is up)"
                " and no periodic axis (the column above a particle does not wrap)"
            )
        if self.dt is not None and not (math.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"Scene.dt must be a positive number of seconds, got {self.dt}")
        if self.wall_basis < 0 or (self.wall_basis and not self.walls):
            raise ValueError(f"Scene.wall_basis = {self.wall_basis} needs walls and K >= 0")

    @property
    def wall_axes(self) -> tuple[int, ...]:
        """Axes that get wall features: all non-periodic ones when the scene has walls."""
        if not self.walls:
            return ()
        return tuple(a for a in range(self.dim) if not self.periodic[a])

    def kinematic_mask(self, particle_type: np.ndarray) -> np.ndarray:
        """(N,) bool on the host: particles of a kinematic type (LearnedSimulator's
        kinematic_mask is the same on the model's device)."""
        return np.isin(np.asarray(particle_type), self.kinematic_particle_types)

    @classmethod
    def from_metadata(
        cls,
        metadata: Any,
        particle_types: Iterable[int],
        config: SceneConfig | None = None,
        context_size: int | None = None,
    ) -> Scene:
        """A scene from a gns.data.Metadata and the particle types that occur in the data.

        context_size: the width of the data's step_context (None: metadata's context_mean)."""
        config = config or SceneConfig()
        if context_size is None:
            context_size = 0 if metadata.context_mean is None else len(metadata.context_mean)
        if not config.context:
            context_size = 0
        use_material = config.material_property
        if use_material is None:
            use_material = context_size == 0
        gravity = None
        if config.gravity is not None:
            if len(config.gravity) != metadata.dim:
                raise ValueError(
                    f"scene.gravity has {len(config.gravity)} values for dim {metadata.dim}"
                )
            # The model works per frame: an acceleration in m/s^2 times dt^2.
            gravity = tuple(g * metadata.dt**2 for g in config.gravity)
        kinematic = config.kinematic_particle_types
        if kinematic is None:
            kinematic = tuple(metadata.kinematic_particle_types)
        obstacles = config.obstacles
        if obstacles is None:
            obstacles = bool(getattr(metadata, "has_obstacles", False))
        wall_clip = config.wall_clip or metadata.boundary_augment
        return cls(
            dim=metadata.dim,
            radius=config.radius or metadata.default_connectivity_radius,
            particle_types=tuple(int(t) for t in particle_types),
            bounds=tuple(tuple(pair) for pair in metadata.bounds),
            walls=config.walls,
            periodic=tuple(metadata.periodic_boundary_conditions),
            context_size=context_size,
            material_property_size=metadata.material_feature_len if use_material else 0,
            kinematic_particle_types=tuple(kinematic),
            gravity=gravity,
            wall_clip=wall_clip,
            dt=metadata.dt,
            obstacles=obstacles,
            # Without obstacles the clip means nothing: the default, so that the scene equals
            # that of a model saved before obstacle features existed (fine-tuning compares them).
            obstacle_clip=(config.obstacle_clip or wall_clip) if obstacles else 1.0,
            overburden=config.overburden,
            wall_basis=config.wall_basis,
        )

    @classmethod
    def from_dataset(cls, dataset: Any, config: SceneConfig | None = None) -> Scene:
        """A scene from a gns.data.Dataset (reads every trajectory once for its particle types
        and context width)."""
        types: set[int] = set()
        widths: set[int] = set()
        for trajectory in dataset:
            types.update(int(t) for t in np.unique(trajectory.particle_type))
            context = trajectory.step_context
            widths.add(0 if context is None else int(context.shape[1]))
        if len(widths) > 1:
            raise ValueError(f"trajectories disagree on the step_context width: {sorted(widths)}")
        return cls.from_metadata(dataset.metadata, sorted(types), config, widths.pop())


# Each graph's static obstacle shapes (one sequence per graph), or None for the simulator's own.
GraphObstacles = Sequence[Sequence[ops.Obstacle]] | None


def edge_capacity(num_edges: int, bucket: int) -> int:
    """The static capacity of an edge list of num_edges edges: the next multiple of `bucket`.
    A rollout's E drifts by a few percent from step to step; within one bucket the padded
    shapes stay the same, so a captured step (CUDA graphs) is replayed, not recaptured."""
    if bucket < 1:
        raise ValueError(f"the edge bucket must be a positive number of edges, got {bucket}")
    return -(-num_edges // bucket) * bucket


def pad_edges(
    senders: Tensor, receivers: Tensor, edge_features: Tensor, n: int, capacity: int
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The edge list padded to `capacity` edges: (senders, receivers, edge_features, edge_mask),
    edge_mask (capacity,) 1 for the E real edges, which come first and unchanged, 0 for the
    padding. Padding edges have zero features and join particle k mod n to itself (spread
    over the nodes, so that no one row takes every padding edge's atomic add on a GPU); the
    network zeroes their messages (EncodeProcessDecode's edge_mask), so no node's result
    depends on them."""
    num_edges = senders.shape[0]
    if capacity < num_edges:
        raise ValueError(f"edge capacity {capacity} is below the graph's {num_edges} edges")
    padding = capacity - num_edges
    if padding and n < 1:
        raise ValueError("padding edges need at least one node to point at")
    pad = torch.arange(padding, device=senders.device) % max(n, 1)
    mask = torch.ones(capacity, device=edge_features.device, dtype=edge_features.dtype)
    mask[num_edges:] = 0.0
    zeros = edge_features.new_zeros(padding, edge_features.shape[1])
    return (
        torch.cat([senders, pad]),
        torch.cat([receivers, pad]),
        torch.cat([edge_features, zeros]),
        mask,
    )


def _as_rows(x: Tensor | np.ndarray | float, rows: int, width: int, name: str) -> Tensor:
    """x as (rows, width): a scalar or a (width,) vector is shared by all rows, a (rows,)
    vector is one value per row when width is 1."""
    t = torch.as_tensor(x)
    if t.ndim == 0:
        t = t.reshape(1, 1)
    elif t.ndim == 1:
        t = t[:, None] if width == 1 else t[None, :]
    if t.ndim == 2 and t.shape[0] == 1:
        t = t.expand(rows, -1)
    if t.shape != (rows, width):
        raise ValueError(
            f"{name} must be ({rows}, {width}), got shape {tuple(torch.as_tensor(x).shape)}"
        )
    return t


class LearnedSimulator(nn.Module):
    """The GNS: features from positions, EncodeProcessDecode (or CConv, by model.kind), Euler
    update.

    scene: the dataset's facts (Scene.from_metadata / from_dataset).
    config: gns.config.Config (model, noise and normalisation sections are used here).
    statistics: metadata.json's statistics (a gns.data.Metadata or Statistics); required when
        config.normalization.source == "metadata", ignored otherwise.
    obstacles: static gns.Obstacle shapes for every graph that a call gives none for (calls
        give each graph's shapes as `obstacles`, one list per graph); they turn the scene's
        obstacle features on. Not saved: pass them again when restoring a checkpoint.

    Velocities, accelerations and the context are normalised (running or metadata statistics);
    the material property is appended as given (an O(1) quantity such as tan(friction angle),
    as geoelements does; metadata.json has no statistics for it).

    Shapes: position_sequence (N, C + 1, D), most recent last; particle_type (N,) int64;
    n_node (G,) particles per graph (default one graph); context (G, K) or (K,);
    material_property (), (N,) or (N, M).

    edge_bucket: 0 (the default) runs each step on its own edge list; a positive number pads
    the edge list to the next multiple of it (edge_capacity, pad_edges) with edges the network
    ignores, so that a rollout's steps keep the same tensor shapes (what CUDA graphs need).
    The results are the unpadded ones to float32 round-off. Set on the instance; not saved.
    """

    edge_bucket: int = 0

    particle_type_ids: Tensor
    kinematic_type_ids: Tensor
    gravity: Tensor
    up: Tensor
    bounds: Tensor
    periodic_axes: Tensor

    def __init__(
        self,
        scene: Scene,
        config: Config | None = None,
        *,
        statistics: _Statistics | None = None,
        obstacles: Sequence[ops.Obstacle] = (),
    ) -> None:
        super().__init__()
        config = config or Config()
        self.obstacles = tuple(obstacles)
        if self.obstacles and not scene.obstacles:
            scene = dataclasses.replace(scene, obstacles=True)
        self.scene, self.config = scene, config
        dim, model_config = scene.dim, config.model
        if model_config.add_gravity and scene.gravity is None:
            raise ValueError("model.add_gravity needs the scene's gravity (scene.gravity)")
        if scene.overburden and config.normalization.source != "running":
            raise ValueError(
                "scene.overburden needs normalization.source = 'running' (no dataset "
                "statistics describe it)"
            )
        for o in self.obstacles:
            if o.dim != dim:
                raise ValueError(f"obstacle {o!r} is {o.dim}D but the scene is {dim}D")

        long = torch.int64
        self.register_buffer("particle_type_ids", torch.tensor(scene.particle_types, dtype=long))
        kinematic = torch.tensor(scene.kinematic_particle_types, dtype=long)
        self.register_buffer("kinematic_type_ids", kinematic)
        gravity = scene.gravity if model_config.add_gravity else None
        self.register_buffer("gravity", torch.tensor(gravity or (0.0,) * dim, dtype=torch.float64))
        if scene.bounds is not None:
            bounds = torch.tensor(scene.bounds, dtype=torch.float64)
        else:
            bounds = torch.zeros(dim, 2, dtype=torch.float64)
        self.register_buffer("bounds", bounds)
        # Not saved: it follows from the scene, and checkpoints predate it.
        self.register_buffer("periodic_axes", torch.tensor(scene.periodic), persistent=False)
        # Which way is up for the overburden: against gravity (follows from the scene too).
        up = [-g for g in scene.gravity] if scene.overburden and scene.gravity else [0.0] * dim
        self.register_buffer("up", torch.tensor(up, dtype=torch.float64), persistent=False)
        # One radius-graph search for every step, keeping its buffers between them: 4-9% less
        # time in the graph part than a fresh search per call at 1,100-8,000 2D particles
        # (docs/performance.md, "One searcher between steps"). Not state: copies start empty.
        # One thread at a time: a second concurrent search of the same simulator raises.
        self._searcher = ops.RadiusSearcher()

        self.particle_type_embedding: nn.Embedding | None = None
        embedding_size = 0
        if len(scene.particle_types) > 1:
            embedding_size = model_config.particle_type_embedding_size
            self.particle_type_embedding = nn.Embedding(len(scene.particle_types), embedding_size)

        self.velocity_normalizer, self.acceleration_normalizer = self._normalizers(statistics)
        self.context_normalizer: Normalizer | None = None
        if scene.context_size:
            self.context_normalizer = self._context_normalizer(statistics)

        self.overburden_normalizer: Normalizer | None = None
        if scene.overburden:  # no dataset statistics describe it (checked above)
            self.overburden_normalizer = RunningNormalizer(2, config.normalization.min_std)

        global_size = scene.context_size if model_config.global_latent else 0
        self.node_input_size = (
            model_config.velocity_history * dim
            + 2 * len(scene.wall_axes)
            + (dim if scene.obstacles else 0)
            + (2 if scene.overburden else 0)
            + 2 * len(scene.wall_axes) * scene.wall_basis
            + (scene.context_size - global_size)
            + scene.material_property_size
            + embedding_size
        )
        self.edge_input_size = dim + 1
        self.model: EncodeProcessDecode | CConv
        if model_config.kind == "cconv":
            self.model = CConv(self.node_input_size, dim, model_config)
        else:
            self.model = EncodeProcessDecode(
                self.node_input_size, self.edge_input_size, dim, model_config, global_size
            )

    # ------------------------------------------------------------------ construction helpers

    @classmethod
    def from_metadata(
        cls,
        metadata: Any,
        particle_types: Iterable[int],
        config: Config | None = None,
        **kwargs: Any,
    ) -> LearnedSimulator:
        """Scene and (in metadata mode) statistics from one gns.data.Metadata."""
        config = config or Config()
        scene = Scene.from_metadata(metadata, particle_types, config.scene)
        return cls(scene, config, statistics=metadata, **kwargs)

    def _normalizers(self, statistics: _Statistics | None) -> tuple[Normalizer, Normalizer]:
        dim, norm = self.scene.dim, self.config.normalization
        if norm.source == "running":
            return RunningNormalizer(dim, norm.min_std), RunningNormalizer(dim, norm.min_std)
        missing = [
            name
            for name in ("vel_mean", "vel_std", "acc_mean", "acc_std")
            if getattr(statistics, name, None) is None
        ]
        if missing:
            raise ValueError(
                "normalization.source = 'metadata' needs the dataset's statistics; missing "
                + ", ".join(missing)
            )
        assert statistics is not None
        noise = self.config.noise.std
        # The network predicts acceleration - gravity, so that is what gets normalised.
        acc_mean = torch.as_tensor(statistics.acc_mean, dtype=torch.float64) - self.gravity
        return (
            FixedNormalizer(
                statistics.vel_mean, statistics.vel_std, noise_std=noise, min_std=norm.min_std
            ),
            FixedNormalizer(acc_mean, statistics.acc_std, noise_std=noise, min_std=norm.min_std),
        )

    def _context_normalizer(self, statistics: _Statistics | None) -> Normalizer:
        norm, size = self.config.normalization, self.scene.context_size
        if norm.source == "running":
            return RunningNormalizer(size, norm.min_std)
        mean = getattr(statistics, "context_mean", None)
        std = getattr(statistics, "context_std", None)
        if mean is None or std is None or len(mean) != size:
            raise ValueError(
                f"normalization.source = 'metadata' needs context_mean / context_std of length "
                f"{size} for the scene's context"
            )
        return FixedNormalizer(mean, std, min_std=norm.min_std)

    # ------------------------------------------------------------------ time

    @property
    def frame_dt(self) -> float | None:
        """Seconds per step of the model: the frame spacing of the data it was trained on
        (None for checkpoints written before it was recorded)."""
        return self.scene.dt

    def frame_stride_for(self, metadata: Any) -> int:
        """Every how many frames of a dataset (a gns.data.Metadata, or anything with its dt)
        this model reads: frame_dt / metadata.dt, a whole number >= 1 (gns.data.frame_stride;
        1 when frame_dt is unknown). ValueError when the data's spacing does not divide the
        model's step. Give gns.data.at_frame_stride the result."""
        return frame_stride(self.frame_dt, metadata.dt)

    # ------------------------------------------------------------------ particles and geometry

    def kinematic_mask(self, particle_type: Tensor) -> Tensor:
        """(N,) bool: particles of a kinematic type (no noise, no loss, ground truth in rollout).
        particle_type must be on the simulator's device (Scene.kinematic_mask takes numpy)."""
        return torch.isin(particle_type.to(torch.int64), self.kinematic_type_ids)

    def _type_index(self, particle_type: Tensor) -> Tensor:
        ids, particle_type = self.particle_type_ids, particle_type.to(torch.int64)
        index = torch.searchsorted(ids, particle_type).clamp(max=ids.shape[0] - 1)
        known = ids.index_select(0, index) == particle_type
        if not bool(known.all()):
            unknown = sorted(set(particle_type[~known].tolist()))
            raise ValueError(
                f"particle types {unknown} are not in the scene's types {ids.tolist()}"
            )
        return index

    def _box(self, dtype: torch.dtype) -> Tensor:
        return (self.bounds[:, 1] - self.bounds[:, 0]).to(dtype)

    def displacement(self, a: Tensor, b: Tensor) -> Tensor:
        """a - b, the minimum image on periodic axes (a particle crossing the box is not fast)."""
        d = a - b
        if not any(self.scene.periodic):
            return d
        box = self._box(d.dtype)
        return torch.where(self.periodic_axes, d - box * torch.round(d / box), d)

    def wrap(self, x: Tensor) -> Tensor:
        """Positions folded back into the box on periodic axes."""
        if not any(self.scene.periodic):
            return x
        lo, box = self.bounds[:, 0].to(x.dtype), self._box(x.dtype)
        return torch.where(self.periodic_axes, lo + torch.remainder(x - lo, box), x)

    def velocity_sequence(self, position_sequence: Tensor) -> Tensor:
        """(N, C, D) finite differences of (N, C + 1, D) positions, per frame."""
        return self.displacement(position_sequence[:, 1:], position_sequence[:, :-1])

    def graph(
        self, most_recent_position: Tensor, n_node: Tensor | None = None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Radius graph of the most recent positions (Rust core): senders, receivers (E,) and
        the displacements x[senders] - x[receivers] (E, D), minimum image on periodic axes;
        all on the positions' device."""
        x = most_recent_position.detach()
        return self._graph(x.cpu(), x, n_node)

    def _graph(
        self, host: Tensor, most_recent_position: Tensor, n_node: Tensor | None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """graph() from `host`, the positions already copied to the CPU (the Rust core reads
        host memory): the edges go back to the positions' device once, and the displacements
        are taken there from the (detached) positions themselves."""
        x = most_recent_position
        periodic = any(self.scene.periodic)
        kwargs: dict[str, Any] = dict(self_edges=self.config.model.self_edges)
        if n_node is not None:
            kwargs["n_node"] = n_node.cpu()
        if periodic:
            lo = torch.tensor([lo for lo, _ in self.scene.bounds or ()], dtype=host.dtype)
            box = [hi - lo for lo, hi in self.scene.bounds or ()]
            edges, shifts = self._searcher(
                host - lo, self.scene.radius, box=box, periodic=list(self.scene.periodic),
                return_shifts=True, **kwargs,
            )  # fmt: skip
        else:
            edges = self._searcher(host, self.scene.radius, **kwargs)
        edges = edges.to(x.device)
        senders, receivers = edges[0], edges[1]
        relative = x.index_select(0, senders) - x.index_select(0, receivers)
        if periodic:
            relative = relative + shifts.to(x.device, x.dtype) * self._box(x.dtype)
        return senders, receivers, relative

    # ------------------------------------------------------------------ preprocess

    def features(
        self,
        position_sequence: Tensor,
        particle_type: Tensor,
        n_node: Tensor | None = None,
        context: Tensor | None = None,
        material_property: Tensor | None = None,
        *,
        mark: Callable[[str], None] | None = None,
        obstacles: GraphObstacles = None,
    ) -> dict[str, Tensor | None]:
        """The model's inputs: node_features, edge_features, senders, receivers,
        global_features (None unless the model has a global latent and the scene a context),
        edge_mask (None unless edge_bucket pads the edge list: then 1 for the real edges, 0 for
        the padding after them). edge_features (E, D + 1) are the displacements
        x[senders] - x[receivers] divided by the radius, then their length; CConv reads its
        kernel coordinates from the first D columns.

        mark: called with "graph" once the radius graph is built (see predict_positions).
        obstacles: each graph's static obstacle shapes (G lists of gns.Obstacle), for a scene
        with obstacle features; None gives every graph the simulator's own (its constructor's).

        Every tensor of the result is on the positions' device. The Rust core (radius graph,
        wall and obstacle distances) reads host memory: the most recent positions are copied
        to the CPU once per call, and the edges and the distance features come back once each.
        """
        n, steps, dim = position_sequence.shape
        c = self.config.model.velocity_history
        if steps != c + 1 or dim != self.scene.dim:
            raise ValueError(
                f"position_sequence must be (N, {c + 1}, {self.scene.dim}) for C = {c}, got "
                f"{tuple(position_sequence.shape)}"
            )
        if particle_type.shape != (n,):
            raise ValueError(f"particle_type must be ({n},), got {tuple(particle_type.shape)}")
        dtype, device = position_sequence.dtype, position_sequence.device
        most_recent = position_sequence[:, -1].detach()
        host = most_recent.cpu()  # the one copy to the host (none on the CPU)
        n_graphs = 1 if n_node is None else int(n_node.shape[0])
        senders, receivers, relative = self._graph(host, most_recent, n_node)
        if mark is not None:
            mark("graph")

        velocities = self.velocity_normalizer.normalize(self.velocity_sequence(position_sequence))
        nodes = [velocities.reshape(n, c * dim)]
        distances = []  # computed on the host, moved to the device together
        if self.scene.wall_axes:
            walls = ops.wall_features(
                host, self.scene.bounds, self.scene.radius, clip=self.scene.wall_clip
            )
            columns = [*self.scene.wall_axes, *(dim + a for a in self.scene.wall_axes)]
            distances.append(walls[:, columns])
        if self.scene.obstacles:
            distances.append(self._obstacle_features(host, n_node, n_graphs, obstacles))
        if distances:
            nodes.append(torch.cat(distances, dim=-1).to(device, dtype))
        if self.overburden_normalizer is not None:
            raw = self._overburden(position_sequence, particle_type, n_node)
            nodes.append(self.overburden_normalizer.normalize(raw))
        if self.scene.wall_basis:
            nodes.append(self._wall_basis(position_sequence))

        global_features = None
        if self.context_normalizer is not None:
            if context is None:
                raise ValueError(f"this scene has a context of width {self.scene.context_size}")
            context = _as_rows(context, n_graphs, self.scene.context_size, "context")
            context = context.to(device, dtype)
            context = self.context_normalizer.normalize(context)
            if self.config.model.global_latent:
                global_features = context
            else:  # appended to every node of its graph
                nodes.append(self._per_node(context, n_node, n))
        if self.scene.material_property_size:
            if material_property is None:
                raise ValueError("this scene has a material property; pass material_property")
            size = self.scene.material_property_size
            material = _as_rows(material_property, n, size, "material_property")
            material = material.to(device, dtype)
            nodes.append(material)
        index = self._type_index(particle_type)
        if self.particle_type_embedding is not None:
            nodes.append(self.particle_type_embedding(index).to(dtype))

        relative = relative / self.scene.radius
        distance = torch.linalg.vector_norm(relative, dim=-1, keepdim=True)
        edge_features = torch.cat([relative, distance], dim=-1)
        edge_mask = None
        if self.edge_bucket:
            if not isinstance(self.model, EncodeProcessDecode):
                raise ValueError("padded edge lists (edge_bucket) are for the GNS, not CConv")
            capacity = edge_capacity(senders.shape[0], self.edge_bucket)
            senders, receivers, edge_features, edge_mask = pad_edges(
                senders, receivers, edge_features, n, capacity
            )
        return {
            "node_features": torch.cat(nodes, dim=-1),
            "edge_features": edge_features,
            "senders": senders,
            "receivers": receivers,
            "global_features": global_features,
            "edge_mask": edge_mask,
        }

    def _obstacle_features(
        self, host: Tensor, n_node: Tensor | None, n_graphs: int, obstacles: GraphObstacles
    ) -> Tensor:
        """(N, D) nearest-obstacle features, graph by graph: each graph has its own shapes."""
        if obstacles is None:
            if not self.obstacles:
                raise ValueError(
                    "this model has obstacle features (scene.obstacles): pass each graph's "
                    "obstacle shapes as `obstacles` (a dataset's come from its metadata.json)"
                )
            obstacles = [self.obstacles] * n_graphs
        if len(obstacles) != n_graphs:
            raise ValueError(
                f"obstacles must give the shapes of each of the {n_graphs} graphs (a list per "
                f"graph), got {len(obstacles)} lists"
            )
        counts = [host.shape[0]] if n_node is None else n_node.tolist()
        parts = [
            ops.nearest_obstacle_features(
                part, shapes, self.scene.radius, clip=self.scene.obstacle_clip
            )
            for part, shapes in zip(torch.split(host, counts), obstacles, strict=True)
        ]
        return torch.cat(parts)

    def _wall_basis(self, position_sequence: Tensor) -> Tensor:
        """(N, 2 A K) wall_basis() of where a free step from the last two input frames takes
        each particle, for the A wall axes, in the positions' dtype. The scene's bounds, as
        the wall features read them (the floor probe moves them). In torch, not through
        gns.ops.wall_features: the free step lives on the model's device, and the Rust core
        would cost one more copy to the host at every step."""
        x = position_sequence[:, -1].double()
        free = 2 * x - position_sequence[:, -2].double()  # at the last velocity
        # Gravity's step added to the positions is the bounds less it (no tensor to copy).
        gravity = self.scene.gravity or (0.0,) * self.scene.dim
        bounds = [(lo - g, hi - g) for (lo, hi), g in zip(self.scene.bounds, gravity, strict=True)]
        basis = wall_basis(
            free, bounds, self.scene.wall_axes, self.scene.radius, self.scene.wall_basis
        )
        return basis.to(position_sequence.dtype)

    def _overburden(
        self, position_sequence: Tensor, particle_type: Tensor, n_node: Tensor | None
    ) -> Tensor:
        """(N, 2) raw overburden features (gns.overburden) of the most recent positions."""
        x = position_sequence.detach()
        return overburden(
            x[:, -1],
            x[:, -1] - x[:, -2],
            self.up,
            self.scene.radius / 2,
            ~self.kinematic_mask(particle_type),
            n_node,
        )

    @staticmethod
    def _per_node(per_graph: Tensor, n_node: Tensor | None, n: int) -> Tensor:
        if n_node is None:
            return per_graph.expand(n, -1)
        repeats = n_node.to(per_graph.device)
        return torch.repeat_interleave(per_graph, repeats, dim=0, output_size=n)

    # ------------------------------------------------------------------ model

    def forward(
        self,
        position_sequence: Tensor,
        particle_type: Tensor,
        n_node: Tensor | None = None,
        context: Tensor | None = None,
        material_property: Tensor | None = None,
        *,
        mark: Callable[[str], None] | None = None,
        obstacles: GraphObstacles = None,
    ) -> Tensor:
        """The predicted normalised acceleration (N, D). mark: see predict_positions;
        obstacles: see features."""
        f = self.features(
            position_sequence,
            particle_type,
            n_node,
            context,
            material_property,
            mark=mark,
            obstacles=obstacles,
        )
        if mark is not None:
            mark("features")
        # Only a padded edge list passes its mask: CConv takes none.
        padding = {} if f["edge_mask"] is None else {"edge_mask": f["edge_mask"]}
        normalized = self.model(
            f["node_features"],
            f["edge_features"],
            f["senders"],
            f["receivers"],
            f["global_features"],
            n_node,
            **padding,
        )
        if mark is not None:
            mark("model")
        return normalized

    def predict_positions(
        self,
        position_sequence: Tensor,
        particle_type: Tensor,
        n_node: Tensor | None = None,
        context: Tensor | None = None,
        material_property: Tensor | None = None,
        *,
        mark: Callable[[str], None] | None = None,
        obstacles: GraphObstacles = None,
    ) -> Tensor:
        """The next positions (N, D), at least float32: one step of the simulator, and the one
        place a step is put together (gns.rollout runs every step through here).

            graph        the most recent positions -> edges within the radius (Rust)
            features     velocities, distances, ... -> node and edge features (`features`)
            model        features -> latents -> message passing -> normalised acceleration
            integration  de-normalise (+ gravity), Euler update -> positions
                         (`decoder_postprocess`)

        mark: called with the name of each of these parts as it ends (gns.rollout.TIMING_PARTS,
        in that order), so that a caller can time them without assembling the step itself.
        obstacles: each graph's static obstacle shapes (see features).
        """
        normalized = self(
            position_sequence,
            particle_type,
            n_node,
            context,
            material_property,
            mark=mark,
            obstacles=obstacles,
        )
        next_position = self.decoder_postprocess(normalized, position_sequence)
        if mark is not None:
            mark("integration")
        return next_position

    # ------------------------------------------------------------------ postprocess and inverse

    @staticmethod
    def _euler_dtype(x: Tensor) -> torch.dtype:
        # Never integrate below float32 (e.g. a bfloat16 network output under autocast).
        return torch.promote_types(x.dtype, torch.float32)

    def decoder_postprocess(
        self, normalized_acceleration: Tensor, position_sequence: Tensor
    ) -> Tensor:
        """Semi-implicit Euler with dt = 1: v' = v + a, x' = x + v' (A). Returns x' (N, D)."""
        dtype = self._euler_dtype(position_sequence)
        positions = position_sequence.to(dtype)
        acceleration = self.acceleration_normalizer.inverse(normalized_acceleration.to(dtype))
        acceleration = acceleration + self.gravity.to(dtype)
        most_recent_velocity = self.displacement(positions[:, -1], positions[:, -2])
        new_velocity = most_recent_velocity + acceleration
        return self.wrap(positions[:, -1] + new_velocity)

    def acceleration(self, next_position: Tensor, position_sequence: Tensor) -> Tensor:
        """The acceleration (minus gravity, when added) that takes the sequence to
        next_position: the raw, un-normalised inverse of the Euler update."""
        dtype = self._euler_dtype(position_sequence)
        positions = position_sequence.to(dtype)
        next_velocity = self.displacement(next_position.to(dtype), positions[:, -1])
        most_recent_velocity = self.displacement(positions[:, -1], positions[:, -2])
        return next_velocity - most_recent_velocity - self.gravity.to(dtype)

    def target_normalized_acceleration(
        self,
        next_position: Tensor,
        noisy_position_sequence: Tensor,
        position_sequence_noise: Tensor | None = None,
    ) -> Tensor:
        """The inverse of decoder_postprocess: the normalised acceleration that takes
        noisy_position_sequence to next_position.

        With position_sequence_noise (N, C + 1, D) the target is corrected for the input noise
        (B.3): the fraction `noise.correct_position_fraction` of the noise in the most recent
        position is removed in the prediction, the rest kept, so at 0 (the default) the
        predicted next velocity is the ground-truth next velocity.
        """
        if position_sequence_noise is not None:
            keep = 1.0 - self.config.noise.correct_position_fraction
            next_position = next_position + keep * position_sequence_noise[:, -1]
        acceleration = self.acceleration(next_position, noisy_position_sequence)
        return self.acceleration_normalizer.normalize(acceleration)

    # ------------------------------------------------------------------ training helpers

    def sample_noise(
        self,
        position_sequence: Tensor,
        particle_type: Tensor,
        generator: torch.Generator | None = None,
        n_node: Tensor | None = None,
    ) -> Tensor:
        """Position noise (N, C + 1, D) of the configured type; zero on kinematic particles;
        n_node (B,): the particles of each window, for noise.std_min's std per window."""
        return sample_noise(
            self.config.noise,
            position_sequence,
            n_node=n_node,
            kinematic=self.kinematic_mask(particle_type),
            generator=generator,
        )

    def sample_wall_push(
        self,
        position_sequence: Tensor,
        particle_type: Tensor,
        generator: torch.Generator | None = None,
    ) -> Tensor | None:
        """The shift (N, D) into the walls of noise.wall_push (gns.noise.wall_push), or None
        when it is off or the scene has no walls."""
        std = self.config.noise.wall_push
        if not std or not self.scene.wall_axes:
            return None
        return wall_push(
            position_sequence[:, -1],
            self.bounds,
            self.scene.wall_axes,
            self.scene.radius,
            std,
            through_only=self.config.noise.wall_push_through_only,
            kinematic=self.kinematic_mask(particle_type),
            generator=generator,
        )

    def update_statistics(
        self,
        noisy_position_sequence: Tensor,
        acceleration: Tensor,
        particle_type: Tensor,
        n_node: Tensor | None = None,
        context: Tensor | None = None,
    ) -> None:
        """Add a batch to the running statistics (no-op for metadata statistics): velocities of
        the noisy inputs and target accelerations of non-kinematic particles, and the context."""
        free = ~self.kinematic_mask(particle_type)
        velocities = self.velocity_sequence(noisy_position_sequence)
        steps = velocities.shape[1]
        self.velocity_normalizer.update(velocities, free[:, None].expand(-1, steps))
        self.acceleration_normalizer.update(acceleration, free)
        if self.overburden_normalizer is not None:
            raw = self._overburden(noisy_position_sequence, particle_type, n_node)
            self.overburden_normalizer.update(raw, free)
        if self.context_normalizer is not None and context is not None:
            n_graphs = 1 if n_node is None else int(n_node.shape[0])
            rows = _as_rows(context, n_graphs, self.scene.context_size, "context")
            self.context_normalizer.update(rows)

    def predict_accelerations(
        self,
        next_position: Tensor,
        position_sequence: Tensor,
        position_sequence_noise: Tensor,
        particle_type: Tensor,
        n_node: Tensor | None = None,
        context: Tensor | None = None,
        material_property: Tensor | None = None,
        *,
        update_statistics: bool | None = None,
        obstacles: GraphObstacles = None,
    ) -> tuple[Tensor, Tensor]:
        """One training example: (predicted, target) normalised accelerations (N, D).

        position_sequence is the clean input (N, C + 1, D); the model sees it plus
        position_sequence_noise. update_statistics (default: in training mode) first adds this
        batch, after noise, to the running statistics (B.2), so the very first batch is already
        normalised by its own statistics.
        """
        noisy = position_sequence + position_sequence_noise
        keep = 1.0 - self.config.noise.correct_position_fraction
        # As target_normalized_acceleration, with the raw acceleration kept for the statistics.
        acceleration = self.acceleration(
            next_position + keep * position_sequence_noise[:, -1], noisy
        )
        if self.training if update_statistics is None else update_statistics:
            self.update_statistics(noisy, acceleration, particle_type, n_node, context)
        target = self.acceleration_normalizer.normalize(acceleration)
        predicted = self(
            noisy, particle_type, n_node, context, material_property, obstacles=obstacles
        )
        return predicted, target
