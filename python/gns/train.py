"""Training: the loop of section B.4, checkpoints that resume exactly, logs, and DDP.

One gradient step (`TrainingStep.forward`): sample the input noise (C.2), add the batch to the
running statistics (B.2), predict the normalised acceleration, and take the squared error summed
over dimensions (or train.huber_delta's Huber loss, train.target_weight's weighting) and
averaged over the non-kinematic particles of the whole (global) batch; with
train.loss_steps = K > 1, plus the errors of K - 1 further steps predicted from the model's own
predictions (the multi-step loss CConv was trained with); with train.pushforward, from inputs
the model first pushed forward itself. The network is the GNS or, with
model.kind = "cconv", section D.1's CConv baseline; checkpoints hold the config, which names it.
Adam with lr(j) = final + (start - final) * 0.1^(j / decay_steps).

Runs as one process or under torchrun (torch.distributed DDP: gloo on the CPU, nccl on CUDA).
All training goes through the DDP wrapper's forward, so gradients are averaged across ranks;
the running statistics are summed across ranks by the normalisers themselves (DDP's buffer
broadcast is off: it would overwrite them with rank 0's).

A run folder holds:
    config.json           the settings (gns train --config accepts it back)
    checkpoints/          step_000001000.pt ...: plain dicts written atomically (torch.save);
                          best.pt: the best validated weights so far (see `better_validation`)
    train.csv, valid.csv  loss and validation figures per logged step
    spikes.csv            loss spikes (see TrainConfig.spike_factor), with their batches
    tensorboard/          the same figures for TensorBoard
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from collections import deque
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor, nn

from gns.augment import check_mirror_axes, mirror_batch

# Re-exported: gns.train.batch_tensors is where callers have always found it.
from gns.batches import batch_obstacles, batch_tensors
from gns.checkpoints import (
    CHECKPOINT_FORMAT,
    choose_checkpoint,
    latest_checkpoint,
    load_checkpoint,
    model_location,
    remove_stale_temporaries,
    resume_checkpoint,
    save_checkpoint,
    simulator_from_checkpoint,
    statistics_dict,
)
from gns.config import MODEL_SECTIONS, Config, TrainConfig, from_dict, to_dict
from gns.data import open_dataset
from gns.data.windows import Batch, WindowSampler
from gns.device import resolve_device
from gns.files import atomic_file
from gns.normalization import RunningNormalizer
from gns.simulator import GraphObstacles, LearnedSimulator, Scene
from gns.threads import thread_tuner
from gns.train_log import Progress, RunLog, SpikeReport
from gns.validation import (
    better_validation,
    trajectories_digest,
    validate,
    validation_trajectories,
)

__all__ = ["TrainingStep", "batch_tensors", "better_validation", "train", "validate"]

# Loss spikes are measured against the median loss of this many previous steps, once there
# are at least SPIKE_MIN_HISTORY of them (see TrainConfig.spike_factor).
SPIKE_WINDOW = 100
SPIKE_MIN_HISTORY = 20


# ---------------------------------------------------------------------------------- one step


def _split_targets(tensors: dict[str, Tensor | None], history: int) -> tuple[Tensor, Tensor]:
    """The C + 1 input positions (N, C + 1, D) of a batch_tensors dict and the K target frames
    after them (N, K, D); K > 1 when the windows are longer for a multi-step loss."""
    sequence, last = tensors["position_sequence"], tensors["next_position"]
    assert sequence is not None and last is not None
    targets = torch.cat([sequence[:, history:], last[:, None]], dim=1)
    return sequence[:, :history], targets


class TrainingStep(nn.Module):
    """The loss of one batch, as a module so DDP's forward (and its gradient hooks) see it.

    forward returns (sum over non-kinematic particles of their loss, the number of those
    particles); the trainer divides by the global count. A particle's loss is its squared
    acceleration error summed over dimensions (normalised units), as in the paper. With
    huber_delta (TrainConfig.huber_delta), each dimension's error beyond it counts linearly
    (the Huber loss, scaled to equal the squared error below delta); with target_weight w
    (TrainConfig.target_weight), a particle's loss is multiplied by 1 + w |a|,
    |a| the 2-norm of its normalised target acceleration.

    With later_positions (N, K - 1, D), the ground truth of K - 1 further frames, the loss adds
    K steps (TrainConfig.loss_steps, the multi-step loss of Ummenhofer et al. 2020): each
    later step is predicted from the sequence with the previous prediction appended (kinematic
    particles: the ground truth), its target is the acceleration that reaches the ground truth
    shifted by the same kept input noise as the first step's target, and the gradient runs back
    through the predictions. The acceleration error of a later step is then its position error
    (in normalised units), as in the original's position loss.

    With pushforward = k > 0 (TrainConfig.pushforward), the noisy input is first pushed k
    steps forward by the model without gradient, and the loss is the one step from there to
    the ground truth k frames later (later_positions holds it).

    wall_shift (N, D) (noise.wall_push) moves the noisy input into the walls; the first step's
    target corrects it fully, whatever correct_position_fraction keeps of the noise.
    """

    def __init__(
        self,
        simulator: LearnedSimulator,
        huber_delta: float | None = None,
        target_weight: float = 0.0,
    ) -> None:
        super().__init__()
        self.simulator = simulator
        self.huber_delta = huber_delta
        self.target_weight = target_weight

    def _error(self, predicted: Tensor, target: Tensor) -> Tensor:
        """The loss of each particle (N,): its acceleration error summed over dimensions."""
        residual = predicted.float() - target.float()
        if self.huber_delta is None:
            error = residual.square()
        else:
            delta, size = self.huber_delta, residual.abs()
            error = torch.where(size <= delta, residual.square(), 2.0 * delta * size - delta**2)
        error = error.sum(dim=-1)
        if self.target_weight:
            error = error * (1.0 + self.target_weight * target.float().norm(dim=-1))
        return error

    def forward(
        self,
        position_sequence: Tensor,
        next_position: Tensor,
        position_sequence_noise: Tensor,
        particle_type: Tensor,
        n_node: Tensor | None = None,
        context: Tensor | None = None,
        material_property: Tensor | None = None,
        later_positions: Tensor | None = None,
        pushforward: int = 0,
        obstacles: GraphObstacles = None,
        wall_shift: Tensor | None = None,
    ) -> tuple[Tensor, Tensor]:
        simulator = self.simulator
        if wall_shift is not None:
            position_sequence_noise = position_sequence_noise + wall_shift[:, None]
        if pushforward:
            assert later_positions is not None and later_positions.shape[1] >= pushforward
            position_sequence, next_position = self._push_forward(
                pushforward,
                position_sequence,
                next_position,
                position_sequence_noise,
                later_positions,
                particle_type,
                n_node,
                context,
                material_property,
                obstacles,
            )
            later_positions = None
        if wall_shift is not None:
            # The target keeps this much of the input noise's last position; not of the shift.
            keep = 1.0 - simulator.config.noise.correct_position_fraction
            next_position = next_position - keep * wall_shift
        predicted, target = simulator.predict_accelerations(
            next_position,
            position_sequence,
            position_sequence_noise,
            particle_type,
            n_node,
            context,
            material_property,
            obstacles=obstacles,
        )
        free = ~simulator.kinematic_mask(particle_type)
        loss = self._error(predicted, target)
        if later_positions is not None:
            kinematic = ~free[:, None]
            sequence = position_sequence + position_sequence_noise
            truth = next_position
            for k in range(later_positions.shape[1]):
                sequence = _moved_on(simulator, sequence, predicted, truth, kinematic)
                truth = later_positions[:, k]
                predicted = simulator(
                    sequence, particle_type, n_node, context, material_property, obstacles=obstacles
                )
                target = simulator.target_normalized_acceleration(
                    truth, sequence, position_sequence_noise
                )
                loss = loss + self._error(predicted, target)
        return loss[free].sum(), free.sum()

    @torch.no_grad()
    def _push_forward(
        self,
        steps: int,
        position_sequence: Tensor,
        next_position: Tensor,
        position_sequence_noise: Tensor,
        later_positions: Tensor,
        particle_type: Tensor,
        n_node: Tensor | None,
        context: Tensor | None,
        material_property: Tensor | None,
        obstacles: GraphObstacles,
    ) -> tuple[Tensor, Tensor]:
        """(input sequence, its next ground-truth frame) after the model's own `steps` steps
        from the noisy input. The sequence is returned less the noise, which the caller adds
        back, so that the target keeps the input noise as an unpushed step's does."""
        simulator = self.simulator
        kinematic = simulator.kinematic_mask(particle_type)[:, None]
        sequence = position_sequence + position_sequence_noise
        truth = next_position
        for k in range(steps):
            predicted = simulator(
                sequence, particle_type, n_node, context, material_property, obstacles=obstacles
            )
            sequence = _moved_on(simulator, sequence, predicted, truth, kinematic)
            truth = later_positions[:, k]
        return sequence - position_sequence_noise, truth


def _moved_on(
    simulator: LearnedSimulator,
    sequence: Tensor,
    predicted: Tensor,
    truth: Tensor,
    kinematic: Tensor,
) -> Tensor:
    """The input sequence (N, C + 1, D) one frame on: its oldest frame dropped, the positions
    the predicted normalised acceleration reaches appended; kinematic particles (N, 1) follow
    the ground truth `truth`, as in a rollout."""
    reached = simulator.decoder_postprocess(predicted, sequence)
    reached = torch.where(kinematic, truth.to(reached.dtype), reached)
    return torch.cat([sequence[:, 1:], reached[:, None].to(sequence.dtype)], 1)


def _pushforward_steps(config: TrainConfig, step: int) -> int:
    """How many steps the model pushes this step's batch forward (TrainConfig.pushforward):
    drawn from (seed, step) alone, so every rank and a resumed run push alike."""
    if not config.pushforward:
        return 0
    weights = np.asarray(config.pushforward, dtype=np.float64)
    # The extra entry keeps this stream apart from mirroring's (seed, step, rank).
    rng = np.random.default_rng([config.seed, step, 0, 1])
    return int(rng.choice(len(weights), p=weights / weights.sum()))


# ---------------------------------------------------------------------------------- the loop


def _distributed() -> tuple[int, int, int]:
    """(rank, world_size, local_rank), starting the process group under torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world == 1:
        return 0, 1, 0
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if not dist.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        dist.init_process_group(backend)
    return dist.get_rank(), dist.get_world_size(), local


def _all_reduce_sum(tensor: Tensor) -> None:
    dist.all_reduce(tensor, op=dist.ReduceOp.SUM)


def _batch_windows(batch: Batch, world: int) -> str:
    """The windows of every rank's batch as "trajectory:start" (each trajectory by its key),
    "rank R: ..." per rank under DDP (a collective call there)."""
    own = " ".join(f"{t}:{s}" for t, s in zip(batch.trajectory, batch.start, strict=True))
    if world == 1:
        return own
    parts: list[Any] = [None] * world
    dist.all_gather_object(parts, own)
    return "; ".join(f"rank {r}: {part}" for r, part in enumerate(parts))


def _non_finite_message(
    step: int, loss: float, local_loss: float, simulator: nn.Module, windows: str, world: int
) -> str:
    """What was not finite at gradient step `step` (the loss, which parameters' gradients)."""
    what = []
    if not math.isfinite(loss):
        local = "" if world == 1 else f" (this rank's part: {local_loss})"
        what.append(f"the training loss became {loss}{local}")
    bad = [
        name
        for name, p in simulator.named_parameters()
        if p.grad is not None and not bool(torch.isfinite(p.grad).all())
    ]
    if bad:
        shown = ", ".join(bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
        what.append(f"the gradient of {shown} became non-finite")
    if not what:  # the largest gradient is finite in every parameter, yet not overall
        what.append("the gradients became non-finite")
    return (
        f"{' and '.join(what)} at step {step} (counting from 0), on the batch of windows "
        f"(trajectory:start) {windows}; the optimizer did not apply it, and the last checkpoint "
        "holds the parameters before it"
    )


def _fine_tuning_config(config: Config | None, model: Config, source: object) -> Config:
    """config for fine-tuning the model whose config is `model` (None: the model's own): the
    sections that shape the network and its inputs must be the model's (scene.enforce_walls
    shapes neither: only the rollouts)."""
    if config is None:
        return model
    walls = dataclasses.replace(model.scene, enforce_walls=config.scene.enforce_walls)
    model = dataclasses.replace(model, scene=walls)
    differ = [name for name in MODEL_SECTIONS if getattr(config, name) != getattr(model, name)]
    if differ:
        sections = ", ".join(f"[{name}]" for name in differ)
        raise ValueError(
            f"--init-from {source}: the config's {sections} differ from the model's; fine-tuning "
            "may change only [noise], [train] and scene.enforce_walls (omit --config to use the "
            "model's own)"
        )
    return config


def _check_fine_tuning_scene(model: Scene, data: Scene, announce: bool) -> None:
    """The data a model is fine-tuned on must be the scene it was trained for. The box may
    differ (a dataset's metadata may give a nominal box, another the walls' true place): the
    model keeps its own walls, as it does when it rolls out on that data, and says so."""
    unknown = sorted(set(data.particle_types) - set(model.particle_types))
    if unknown:
        raise ValueError(
            f"--init-from: the data has particle types {unknown} the model does not know "
            f"(it knows {list(model.particle_types)})"
        )
    differ = [
        f"{f.name} {getattr(data, f.name)!r} (the model's: {getattr(model, f.name)!r})"
        for f in dataclasses.fields(Scene)
        if f.name not in ("particle_types", "bounds")
        and getattr(data, f.name) != getattr(model, f.name)
    ]
    if differ:
        raise ValueError("--init-from: the data is not the model's scene: " + "; ".join(differ))
    if announce and data.bounds != model.bounds:
        print(
            f"--init-from: the data's box is {data.bounds}; the model keeps its walls at "
            f"{model.bounds}",
            file=sys.stderr,
        )


def train(
    data: str | os.PathLike[str],
    run_dir: str | os.PathLike[str],
    config: Config | None = None,
    *,
    steps: int | None = None,
    resume: bool = False,
    device: str | torch.device = "auto",
    progress: bool = True,
    time_limit: float | None = None,
    valid_data: str | os.PathLike[str] | None = None,
    init_from: str | os.PathLike[str] | None = None,
) -> LearnedSimulator:
    """Train a GNS (or CConv, by config.model.kind) on the dataset at `data` (train split;
    validation on valid) into run_dir.

    valid_data: validate on this dataset's valid split instead (e.g. train on `gns generate`
    data, validate on the real data it imitates); its frames may be a whole factor finer than
    the model's step (every k-th is taken). The checkpoints record its path and a digest of
    its trajectories: a resume uses the path again, takes another path (the run moved
    machines) only where it holds the same trajectories, and refuses other data.

    init_from: fine-tune. Start from a trained model's weights and running statistics (a
    checkpoint, run folder, model folder or shipped model's name, as gns.load_simulator takes)
    instead of fresh ones; the optimizer, the learning-rate schedule and the step count start
    anew. Its [model], [scene] and [normalization] settings must be config's (config None:
    the model's own config), and the data must be the model's scene: the same dimension,
    frame spacing and global input, with particle types it knows (another box is announced;
    the model keeps its own walls). Metadata normalisation keeps the model's noise-inflated
    std. The checkpoints record where the weights came from. With validation, the starting
    weights are validated first (valid.csv's step 0; best.pt when nothing later beats them).

    resume=True continues from the newest checkpoint in run_dir with its saved settings (the
    `config` argument must then be None or differ only in train.steps, to train for longer):
    the parameters after N + M steps equal those of an uninterrupted run on the CPU.
    steps overrides config.train.steps (e.g. to resume a finished run for longer). A run
    folder that already has checkpoints is never overwritten without resume.
    time_limit: wall-clock seconds for this call (loading included); training stops after the
    first step that ends past it, validates (with validation) and writes a checkpoint of that
    step and returns. resume=True then continues from that checkpoint exactly as an
    uninterrupted run would have.
    A non-finite loss or gradient stops training with FloatingPointError naming the step, what
    was non-finite and the batch's windows, before the optimizer applies it; a loss spike (see
    TrainConfig.spike_factor) is reported on stderr and in spikes.csv. On resume, a newest
    checkpoint that fails verification is skipped, loudly, for the previous intact one.
    """
    if time_limit is not None and not (
        isinstance(time_limit, (int, float)) and math.isfinite(time_limit) and time_limit > 0
    ):
        raise ValueError(f"time_limit must be a positive number of seconds, got {time_limit!r}")
    if init_from is not None and resume:
        raise ValueError("--init-from starts a new run; --resume continues one: pass one")
    started = time.perf_counter()
    run_dir = Path(run_dir)
    rank, world, local_rank = _distributed()
    device = resolve_device(device)
    if device.type == "cuda" and world > 1:
        device = torch.device("cuda", local_rank)
        torch.cuda.set_device(device)
    leader = rank == 0

    checkpoint: dict[str, Any] | None = None
    # What a resumed run validated on, where not at valid_data, and the digest of it.
    validated_on: str | None = None
    recorded_digest: str | None = None
    found = latest_checkpoint(run_dir)
    if resume:
        found, checkpoint = resume_checkpoint(run_dir, announce=leader)
        saved = from_dict(Config, checkpoint["config"])
        # Only the number of steps may change on resume (to train a run for longer).
        if config is not None:
            same_steps = dataclasses.replace(config.train, steps=saved.train.steps)
            if dataclasses.replace(config, train=same_steps) != saved:
                raise ValueError(
                    f"--resume: the settings differ from the run's ({found}) in more than "
                    "train.steps; resume with the run's own settings or start a new run folder"
                )
            saved = dataclasses.replace(
                saved, train=dataclasses.replace(saved.train, steps=config.train.steps)
            )
        config = saved
        recorded = checkpoint.get("valid_data")
        if valid_data is None:
            valid_data = recorded
        elif recorded is None or Path(valid_data).absolute() != Path(recorded):
            # Another path (the run moved machines) is checked by content once loaded.
            validated_on = recorded or "its own data"
        recorded_digest = checkpoint.get("valid_digest")
    elif found is not None:
        raise ValueError(f"{run_dir} already holds checkpoints; pass --resume or another --out")
    initial: dict[str, Any] | None = None
    if init_from is not None:
        initial = load_checkpoint(choose_checkpoint(model_location(init_from)))
        config = _fine_tuning_config(config, from_dict(Config, initial["config"]), init_from)
    elif checkpoint is not None:
        initial = checkpoint
        init_from = checkpoint.get("init_from")
    config = config or Config()
    if steps is not None:
        config = dataclasses.replace(config, train=dataclasses.replace(config.train, steps=steps))
    tc = config.train

    dataset = open_dataset(data, "train")
    history = config.model.velocity_history + 1
    if initial is None:
        scene = Scene.from_dataset(dataset, config.scene)
        torch.manual_seed(tc.seed)  # the initial weights (the same on every rank)
        simulator = LearnedSimulator(scene, config, statistics=dataset.metadata)
        statistics = statistics_dict(dataset.metadata)
    else:  # resumed or fine-tuned: the weights and statistics (metadata or running) carry on
        simulator = simulator_from_checkpoint(initial)
        # The run's settings, not the checkpoint's: a fine-tuning run may change [noise] (which
        # the simulator draws its input noise by), [train] and scene.enforce_walls; [model],
        # the rest of [scene] and [normalization] are the checkpoint's (checked above).
        simulator.config = config
        statistics = initial["statistics"]
        if checkpoint is None:
            _check_fine_tuning_scene(
                simulator.scene, Scene.from_dataset(dataset, config.scene), announce=leader
            )
        elif simulator.scene.dt is None:
            # A run begun before checkpoints recorded the frame spacing: the data it resumes
            # on is the data it trains on, so its checkpoints from now on know their spacing.
            simulator.scene = dataclasses.replace(simulator.scene, dt=dataset.metadata.dt)
    simulator.to(device).train()
    check_mirror_axes(
        tc.mirror_axes, simulator.scene.dim, dataset.metadata.acc_mean, dataset.metadata.acc_std
    )

    step_module: nn.Module = TrainingStep(simulator, tc.huber_delta, tc.target_weight)
    if world > 1:
        for module in simulator.modules():
            if isinstance(module, RunningNormalizer):
                module.all_reduce = _all_reduce_sum
        ids = [device.index] if device.type == "cuda" else None
        step_module = nn.parallel.DistributedDataParallel(
            step_module, device_ids=ids, broadcast_buffers=False
        )
    optimizer = torch.optim.Adam(simulator.parameters(), lr=tc.learning_rate)
    # More frames per window: the ground truth of the later steps (loss_steps, pushforward).
    sampler = WindowSampler(
        dataset,
        history + tc.extra_frames,
        seed=tc.seed,
        trajectories_in_memory=tc.trajectories_in_memory,
        rank=rank,
        world_size=world,
        early_steps=tc.early_steps,
        early_repeat=tc.early_repeat,
    )
    generator = torch.Generator(device=device)
    noise_seed = tc.seed * 1_000_003 + rank
    generator.manual_seed(noise_seed)
    start = 0
    # {"step", "value", "in_box"} of best.pt, as chosen by better_validation.
    best: dict[str, Any] | None = None
    if checkpoint is not None:
        saved_world = len(checkpoint["noise_generator"])
        if saved_world != world:
            raise ValueError(
                f"--resume: the run was trained by {saved_world} process(es), this is {world}; "
                "an exact continuation needs the same number"
            )
        optimizer.load_state_dict(checkpoint["optimizer"])
        sampler.load_state_dict(checkpoint["sampler"])
        start = int(checkpoint["step"])
        best = checkpoint.get("best")
        saved_noise = checkpoint["noise_generator"][rank].to(torch.uint8)
        if saved_noise.numel() == generator.get_state().numel():
            generator.set_state(saved_noise)
        else:
            # Another kind of device drew this stream (a CUDA generator's state is 16 bytes, the
            # CPU's 5056) and it cannot go on here. A new one from the run's seed, rank and step,
            # so that every resume from this checkpoint on this kind of device is the same run.
            generator.manual_seed(noise_seed * 1_000_033 + start)
            if leader:
                sys.stderr.write(
                    f"--resume: the checkpoint's noise stream was drawn on another kind of "
                    f"device than {device.type}; a new one starts at step {start} (weights, "
                    "optimizer, sampler and schedule go on; the noise differs from an "
                    "uninterrupted run's)\n"
                )

    valid_trajectories = (
        validation_trajectories(valid_data or data, tc, simulator, required=bool(valid_data))
        if leader
        else []
    )
    # A resume validates on the trajectories the run validated on, wherever they lie now
    # (checkpoints from before the digest was recorded: at the same path).
    valid_digest = trajectories_digest(valid_trajectories)
    if leader and (validated_on or recorded_digest) and recorded_digest != valid_digest:
        here = valid_data or data
        if recorded_digest is None:  # a checkpoint from before the digest: only the path is known
            problem = f"validated on {validated_on}, not on {here}"
        else:
            problem = f"validated on other trajectories than those now at {here}"
            problem += f" (it validated on {validated_on})" if validated_on else ""
        raise ValueError(
            f"--resume: the run {problem}; resume on the same validation data or start a new "
            "run folder"
        )
    if leader:
        remove_stale_temporaries(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "checkpoints").mkdir(exist_ok=True)
        with atomic_file(run_dir / "config.json") as tmp:
            tmp.write_text(json.dumps(to_dict(config), indent=1) + "\n")
    log = RunLog(run_dir, start if checkpoint is not None else None) if leader else None
    meter = Progress(tc.steps, start, enabled=progress and leader, time_limit=time_limit)

    def out_of_time() -> bool:
        """Whether to stop at this step; under DDP every rank must stop at the same step, so
        the ranks agree on it (stop as soon as any rank is out of time)."""
        if time_limit is None:
            return False
        late = time.perf_counter() - started >= time_limit
        if world == 1:
            return late
        flag = torch.tensor(float(late), device=device)
        dist.all_reduce(flag, op=dist.ReduceOp.MAX)
        return bool(flag.item())

    def weights_state(step: int) -> dict[str, Any]:
        """What load_simulator needs (best.pt holds only this)."""
        return {
            "format": CHECKPOINT_FORMAT,
            "step": step,
            "config": to_dict(config),
            "scene": dataclasses.asdict(simulator.scene),
            "statistics": statistics,
            "model": simulator.state_dict(),
            "best": best,
            "valid_data": None if valid_data is None else str(Path(valid_data).absolute()),
            "valid_digest": valid_digest,
            "init_from": None if init_from is None else str(init_from),
        }

    def checkpoint_state(step: int) -> dict[str, Any]:
        """Everything an exact resume needs (a collective call under DDP)."""
        states = [generator.get_state()]
        if world > 1:  # every rank's noise stream, so each resumes its own
            local = states[0].to(device)
            states = [torch.empty_like(local) for _ in range(world)]
            dist.all_gather(states, local)
        return {
            **weights_state(step),
            "optimizer": optimizer.state_dict(),
            "sampler": sampler.state_dict(),
            "noise_generator": [s.cpu() for s in states],
            "recent_losses": list(recent),
        }

    def write_checkpoint(step: int) -> None:
        state = checkpoint_state(step)
        if not leader:
            return
        save_checkpoint(run_dir / "checkpoints" / f"step_{step:09d}.pt", state)
        for old in sorted((run_dir / "checkpoints").glob("step_*.pt"))[: -tc.keep_checkpoints]:
            old.unlink()

    losses: list[float] = []
    grad_norms: list[float] = []  # before clipping, since the last log line
    # The losses of the last SPIKE_WINDOW steps (the global loss under DDP), for spikes.
    recent: deque[float] = deque(maxlen=SPIKE_WINDOW)
    if checkpoint is not None:
        recent.extend(float(v) for v in checkpoint.get("recent_losses", []))
    parameters = [p for p in simulator.parameters() if p.requires_grad]
    spikes = SpikeReport(enabled=leader, meter=meter)
    # Threads chosen by timing the steps (gns.threads): a fixed count stalls when another
    # process holds a core. Fixed by --threads / OMP_NUM_THREADS (e.g. for exact resumes).
    tuner = thread_tuner()

    def validate_and_keep(done: int) -> None:
        """Validate the weights after `done` steps; they become best.pt when they beat it."""
        nonlocal best
        if log is None:  # only the leader validates
            return
        figures = validate(simulator, valid_trajectories, tc, device)
        if figures:
            log.write("valid", done, figures)
        record = better_validation(figures, best, simulator.scene.radius)
        if record is not None:
            best = {"step": done, **record}
            # Weights only: best.pt is for rollouts, resuming uses step_*.pt.
            save_checkpoint(run_dir / "checkpoints" / "best.pt", weights_state(done))

    if initial is not None and checkpoint is None and tc.validate_every:
        # Fine-tuning: the starting weights are validated first (step 0), so best.pt is never
        # worse on validation than the model the run started from.
        validate_and_keep(0)
    step = start
    stopped_at: int | None = None
    try:
        tuner.__enter__()
        for step in range(start, tc.steps):
            tuner.begin()
            step_started = time.perf_counter()
            for group in optimizer.param_groups:
                group["lr"] = tc.learning_rate_at(step)
            batch = sampler.next_batch(tc.batch_size, tc.batch_particles)
            if tc.mirror_axes:
                # Drawn from (seed, step, rank) alone, so a resumed run mirrors the same windows.
                rng = np.random.default_rng([tc.seed, step, rank])
                batch = mirror_batch(batch, tc.mirror_axes, simulator.scene.bounds, rng)
            t = batch_tensors(batch, device)
            sequence, targets = _split_targets(t, history)
            noise = simulator.sample_noise(
                sequence,
                t["particle_type"],  # type: ignore[arg-type]
                generator,
                t["n_node"],
            )
            shift = simulator.sample_wall_push(sequence, t["particle_type"], generator)  # type: ignore[arg-type]
            unroll = _pushforward_steps(tc, step)
            loss_sum, count = step_module(
                sequence,
                targets[:, 0],
                noise,
                t["particle_type"],
                t["n_node"],
                t["context"],
                t["material_property"],
                later_positions=targets[:, 1:] if tc.loss_steps > 1 or unroll else None,
                pushforward=unroll,
                obstacles=batch_obstacles(batch),
                wall_shift=shift,
            )
            count = count.to(loss_sum.dtype)
            if world > 1:
                _all_reduce_sum(count)
            # DDP averages gradients over ranks: world * (local sum) / (global count) makes that
            # average the gradient of the mean over every particle of the global batch.
            loss = loss_sum * world / count.clamp(min=1.0)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            # Before the optimizer applies anything: are the loss and every gradient finite?
            # One synchronisation (and under DDP one all-reduce, so all ranks agree): the
            # loss, the largest |gradient|, which cannot overflow and is NaN if any is, and
            # the gradient's 2-norm (for clipping and the log).
            grads = [p.grad for p in parameters if p.grad is not None]
            zero = torch.zeros((), device=device)
            largest = torch.nn.utils.get_total_norm(grads, norm_type=math.inf) if grads else zero
            grad_norm = torch.nn.utils.get_total_norm(grads) if grads else zero
            health = torch.stack([loss.detach().float(), largest.float(), grad_norm.float()])
            if world > 1:
                # The sum over ranks: the global loss; the gradient (averaged by DDP) as is.
                health /= world
                _all_reduce_sum(health)
            global_loss, largest_grad, norm = health.tolist()
            value = global_loss if world == 1 else float(loss.detach())
            if not (math.isfinite(global_loss) and math.isfinite(largest_grad)):
                windows = _batch_windows(batch, world)
                raise FloatingPointError(
                    _non_finite_message(step, global_loss, value, simulator, windows, world)
                )
            if tc.max_grad_norm is not None:
                torch.nn.utils.clip_grads_with_norm_(parameters, tc.max_grad_norm, grad_norm)
            grad_norms.append(norm)
            optimizer.step()
            tuner.end(time.perf_counter() - step_started)
            done = step + 1
            if tc.spike_factor and len(recent) >= SPIKE_MIN_HISTORY:
                median = float(np.median(recent))
                if global_loss > tc.spike_factor * median:  # the same on every rank
                    windows = _batch_windows(batch, world)
                    spikes.add(done, global_loss, median, len(recent), windows)
                    if log is not None:
                        log.spike(done, global_loss, median, windows)
            recent.append(global_loss)
            losses.append(value)
            meter.show(done, value, threads=tuner.chosen if len(tuner.candidates) > 1 else None)
            stopping = out_of_time() and done < tc.steps
            if done % tc.log_every == 0 or done == tc.steps or stopping:
                mean = torch.tensor(np.mean(losses), dtype=torch.float64, device=device)
                if world > 1:
                    _all_reduce_sum(mean)
                    mean /= world
                if log is not None:
                    log.write(
                        "train",
                        done,
                        {
                            "loss": float(mean),
                            "learning_rate": tc.learning_rate_at(step),
                            "steps_per_second": meter.rate(done),
                            "grad_norm": float(np.median(grad_norms)),
                            "clipped": float(
                                np.mean(np.array(grad_norms) > (tc.max_grad_norm or np.inf))
                            ),
                        },
                    )
                meter.show(done, float(mean), force=True)
                losses, grad_norms = [], []
            # A run stopped by its time limit validates its last weights too: without it they
            # could never become best.pt.
            if tc.validate_every and (done % tc.validate_every == 0 or stopping):
                validate_and_keep(done)
            if done % tc.checkpoint_every == 0 or done == tc.steps or stopping:
                write_checkpoint(done)
            if stopping:
                stopped_at = done
                break
    finally:
        tuner.__exit__()
        meter.close()
        spikes.summarise(run_dir / "spikes.csv")
        if log is not None:
            log.close()
    if stopped_at is not None and leader:
        sys.stderr.write(
            f"time limit of {time_limit:.0f} s reached after step {stopped_at} of {tc.steps}; "
            f"checkpoint written, `gns train --resume` continues the run\n"
        )
    return simulator
