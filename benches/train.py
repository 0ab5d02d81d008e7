"""Training windows per second of the shipped sand model's settings, at several batch sizes.

    python benches/train.py [--quick] [--threads N] [--device cpu|cuda]
                            [--batch-sizes B ...] [--steps S] [--sand PATH]

Model and training settings: models/sand2d-taichi/config.toml, the shipped sand model's
(GNS-10-64, noise 1e-3 with a tenth of it corrected, mirroring in x; [train]'s batch size is
replaced by each --batch-sizes entry). Data: the real sand2d-taichi train split (656 particles a
trajectory, friction angle as context) at the model's frame stride (every 3rd frame, 7.5 ms,
as gns convert --frame-stride 3 makes it); where that is absent, the benchmarks' jittered
lattice (benches/lattice.py) of 656 particles in frames that move, made here.

A step is what gns.train's loop does with one batch, every part of it timed:
  data   the next batch of windows (gns.data.WindowSampler, shuffled across trajectories),
         mirroring, the tensors on the device, the input noise (and wall push)
  step   gns.train.TrainingStep (radius graph, features, forward, loss), backward, the
         finiteness check and gradient norm, clipping where configured, Adam
Adam is torch's fused kernel on CUDA (one launch for all parameters), torch's default on the
CPU (as gns.train, whose CPU results it keeps). Times are median (min) per step after warm-up,
perf_counter, CUDA synchronised at each part's end; windows/s is batch size over the median
step.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SAND = ROOT.parent / "shared" / "data" / "sand2d-taichi"
CONFIG = ROOT / "models" / "sand2d-taichi" / "config.toml"
PARTICLES = 656  # a sand2d-taichi trajectory's, for the generated stand-in


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="tiny model, steps and sizes (smoke test)")
    p.add_argument("--threads", type=int, help="torch and Rust threads (default: all cores)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument(
        "--batch-sizes", type=int, nargs="*", help="windows per batch (default 1 2 4 8 16)"
    )
    p.add_argument("--steps", type=int, help="measured steps per batch size (default 10)")
    p.add_argument("--sand", default=str(SAND), help="sand2d-taichi folder ('' to generate)")
    args = p.parse_args()
    if args.batch_sizes is None:
        args.batch_sizes = [1, 2] if args.quick else [1, 2, 4, 8, 16]
    args.steps = args.steps or (2 if args.quick else 10)
    args.warmup = 1 if args.quick else 3
    return args


ARGS = parse_args()
if ARGS.threads is not None:  # before the Rust pool starts: it reads this once
    os.environ["RAYON_NUM_THREADS"] = str(ARGS.threads)

import torch  # noqa: E402
from gns.augment import mirror_batch  # noqa: E402
from gns.batches import batch_tensors  # noqa: E402
from gns.config import Config, load_config  # noqa: E402
from gns.data import Trajectory, open_dataset  # noqa: E402
from gns.data.stride import at_frame_stride  # noqa: E402
from gns.data.windows import WindowSampler  # noqa: E402
from gns.simulator import LearnedSimulator, Scene  # noqa: E402
from gns.train import TrainingStep  # noqa: E402
from lattice import lattice  # noqa: E402
from torch_bench import bench_device, machine_facts, synchronize  # noqa: E402

# The stride of the shipped model's frames to the data's (its steps are 7.5 ms, the data's
# frames 2.5 ms: models/sand2d-taichi/config.toml's header).
FRAME_STRIDE = 3
MODEL_STEP = 0.0025 * FRAME_STRIDE  # seconds


def at_model_step(scene: Scene, config: Config, step: float) -> Scene:
    """`scene` stepping `step` seconds at a time: its dt, and the config's gravity per step
    (m/s^2 times the step squared, as Scene.from_dataset makes it per frame)."""
    g = config.scene.gravity
    gravity = None if g is None else tuple(a * step**2 for a in g)
    return dataclasses.replace(scene, dt=step, gravity=gravity)


def sand_data(path: Path, config: Config) -> tuple[str, Scene, list[Trajectory], object] | None:
    """(name, scene, trajectories at the model's stride, statistics) of the real train split."""
    if not path.is_dir():
        print(f"(sand2d-taichi not found at {path}: training on a generated lattice)")
        return None
    dataset = open_dataset(path, "train")
    scene = Scene.from_dataset(dataset, config.scene)
    scene = at_model_step(scene, config, dataset.metadata.dt * FRAME_STRIDE)
    trajectories = [at_frame_stride(t, FRAME_STRIDE) for t in dataset]
    return "sand2d-taichi train", scene, trajectories, dataset.metadata


def generated_data(config: Config, n: int) -> tuple[str, Scene, list[Trajectory], None]:
    """Four lattice trajectories of n particles, 40 frames each, in the config's scene
    settings (wall clip, gravity at the shipped model's step); running normalisation from the
    first batch, as without metadata."""
    trajectories = []
    for k in range(4):
        scene, t = lattice(n + k, 40)  # n + k: four different jitters and velocities
        trajectories.append(dataclasses.replace(t, key=k))
    scene = dataclasses.replace(scene, wall_clip=config.scene.wall_clip)
    scene = at_model_step(scene, config, MODEL_STEP)
    return f"generated lattice, {n} particles", scene, trajectories, None


def bench_config() -> Config:
    """The shipped sand model's settings; with --quick a tiny network (GNS-2-8): the smoke
    test checks the plumbing, not the speed."""
    config = load_config(CONFIG)
    if not ARGS.quick:
        return config
    model = dataclasses.replace(
        config.model, latent_size=8, mlp_hidden_size=8, message_passing_steps=2
    )
    return dataclasses.replace(config, model=model)


def measure(
    scene: Scene,
    trajectories: list[Trajectory],
    statistics: object,
    config: Config,
    batch_size: int,
    device: torch.device,
) -> dict[str, np.ndarray | float]:
    """Seconds per step (data, step) of `ARGS.steps` training steps of `batch_size` windows,
    after ARGS.warmup untimed ones, and the mean particles per batch."""
    tc = config.train
    history = config.model.velocity_history + 1
    torch.manual_seed(tc.seed)
    simulator = LearnedSimulator(scene, config, statistics=statistics).to(device).train()
    training_step = TrainingStep(simulator, tc.huber_delta, tc.target_weight)
    parameters = list(simulator.parameters())
    # Fused Adam on CUDA only: there it is one kernel for all parameters instead of a few per
    # parameter; on the CPU torch's default is gns.train's, whose exact results it keeps.
    optimizer = torch.optim.Adam(parameters, lr=tc.learning_rate, fused=device.type == "cuda")
    sampler = WindowSampler(trajectories, history + tc.extra_frames, seed=tc.seed)
    generator = torch.Generator(device=device).manual_seed(tc.seed)
    rng = np.random.default_rng(tc.seed)
    data, step, particles = [], [], []
    for k in range(ARGS.warmup + ARGS.steps):
        synchronize(device)
        t0 = time.perf_counter()
        batch = sampler.next_batch(batch_size, tc.batch_particles)
        if tc.mirror_axes:
            batch = mirror_batch(batch, tc.mirror_axes, scene.bounds, rng)
        t = batch_tensors(batch, device)
        sequence, next_position = t["position_sequence"], t["next_position"]
        types = t["particle_type"]
        assert sequence is not None and next_position is not None and types is not None
        # The window's extra frames (multi-step loss, pushforward) are not used here.
        targets = torch.cat([sequence[:, history:], next_position[:, None]], dim=1)
        sequence = sequence[:, :history]
        noise = simulator.sample_noise(sequence, types, generator)
        shift = simulator.sample_wall_push(sequence, types, generator)
        synchronize(device)
        t1 = time.perf_counter()
        loss_sum, count = training_step(
            sequence, targets[:, 0], noise, types, t["n_node"], t["context"],
            t["material_property"], wall_shift=shift,
        )  # fmt: skip
        loss = loss_sum / count.to(loss_sum.dtype).clamp(min=1.0)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        # gns.train's check before Adam: the largest |gradient| and the norm, one sync.
        grads = [p.grad for p in parameters if p.grad is not None]
        largest = torch.nn.utils.get_total_norm(grads, norm_type=math.inf)
        norm = torch.nn.utils.get_total_norm(grads)
        health = torch.stack([loss.detach().float(), largest.float(), norm.float()]).tolist()
        if not all(math.isfinite(v) for v in health):
            raise FloatingPointError(f"non-finite loss or gradient at step {k}: {health}")
        if tc.max_grad_norm is not None:
            torch.nn.utils.clip_grads_with_norm_(parameters, tc.max_grad_norm, norm)
        optimizer.step()
        synchronize(device)
        t2 = time.perf_counter()
        if k >= ARGS.warmup:
            data.append(t1 - t0)
            step.append(t2 - t1)
            particles.append(int(batch.n_node.sum()))
    return {"data": np.array(data), "step": np.array(step), "particles": float(np.mean(particles))}


COLUMNS = [("batch", 5), ("N", 6), ("data ms", 15), ("step ms", 17), ("total ms", 17)]
COLUMNS += [("data%", 6), ("windows/s", 9), ("particles/s", 11)]


def line(texts: list[str]) -> str:
    return " ".join(t.rjust(w) for t, (_, w) in zip(texts, COLUMNS, strict=True))


def cells(batch_size: int, r: dict) -> list[str]:
    data, step = 1e3 * r["data"], 1e3 * r["step"]
    total = data + step
    median = float(np.median(total))

    def ms(x: np.ndarray) -> str:
        return f"{np.median(x):.1f} ({x.min():.1f})"

    return [
        str(batch_size),
        f"{r['particles']:.0f}",
        ms(data),
        ms(step),
        ms(total),
        f"{100 * float(np.median(data)) / median:.0f}%",
        f"{1e3 * batch_size / median:.1f}",
        f"{1e3 * r['particles'] / median:.0f}",
    ]


def main() -> None:
    device = bench_device("train.py", ARGS.threads, ARGS.device)
    config = bench_config()
    found = sand_data(Path(ARGS.sand), config) if ARGS.sand else None
    name, scene, trajectories, statistics = found or generated_data(
        config, 120 if ARGS.quick else PARTICLES
    )
    facts = machine_facts(device)
    m = config.model
    facts.append(
        f"model: GNS-{m.message_passing_steps}-{m.latent_size} ({CONFIG.relative_to(ROOT)}"
        f"{', shrunk by --quick' if ARGS.quick else ''}); data: {name}, "
        f"{len(trajectories)} trajectories"
    )
    facts.append(
        f"Adam: {'fused' if device.type == 'cuda' else 'torch default'}; {ARGS.steps} steps after "
        f"{ARGS.warmup}; times median (min) in ms per step\n"
    )
    print("\n".join(facts))
    print(line([title for title, _ in COLUMNS]))
    print("-" * len(line([""] * len(COLUMNS))))
    for batch_size in ARGS.batch_sizes:
        r = measure(scene, trajectories, statistics, config, batch_size, device)
        print(line(cells(batch_size, r)), flush=True)


if __name__ == "__main__":
    main()
