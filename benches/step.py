"""Time per rollout step and per training step of the GNS, and the model's FLOP/s.

    python benches/step.py [--quick] [--threads N] [--device cpu|cuda] [--sizes N ...]
                           [--variants plain fast bf16 compiled | all]

Model: the paper's GNS-10-128 (the default Config(): 10 message-passing steps, latent and MLP
width 128, 2 hidden layers), running normalisation primed with the case's own window.
Cases, all 2D with R = 0.015 (the paper's 2D radius):
- "WaterDrop size" (--sizes 1100) and "10k particles" (--sizes 10000): a block of particles on a
  jittered square lattice of spacing R * sqrt(pi / 13): 13 neighbours (self included) inside the
  block, fewer along its sides (E/N is printed: ~11.2 at 1.1k, ~12.3k edges), at random small
  velocities in a WaterDrop-like box [0.1, 0.9]^2 with walls and one particle type.
- "sand2d-taichi": trajectory 0 of the real data's train split from frame 100 (656 particles,
  friction angle as context); skipped with a message when the data is absent.

Rollout step: gns.rollout.rollout itself (inference mode, eval mode), split as it times it (the
parts LearnedSimulator.predict_positions marks) into graph (Rust radius graph) / features /
model (EncodeProcessDecode) / integration; `reps`
rollouts of `steps` steps from the same start, so the graph stays that of the case.
Training step: one window (one graph) through gns.train.TrainingStep: noise, forward, backward,
Adam. Times are median (min) after warm-up, perf_counter, CUDA synchronised.
FLOPs: counted from the Linear layers (forward_flops); forward FLOP/s is per rollout "model"
time, training FLOP/s counts 3x forward per whole training step. "% mm" compares them with an
(S x S) @ (S x S) matmul in the row's precision timed on the same device and threads in the
same run (emulated bf16 at S <= 1024); faster variants do fewer FLOPs for the same work, so
their "% mm" can pass 100%.

Variants (rows per case; --variants picks them by key) are the same function and parameters run
differently (gns.config.ModelConfig.implementation / precision / torch_compile):
- plain    "plain fp32": the readable reference (gather, concatenate, MLP, index_add_).
- fast     "fast fp32": split first edge layer, blocked edge MLP without autograd.
- bf16     "fast bf16": the fast path under bf16 autocast; run by default only where bf16 is
           native (CUDA, AVX512-BF16 / AMX CPUs): elsewhere it is emulated and ~20x slower.
- compiled "fast fp32 compiled": torch.compile of the fast path; not by default, as every case
           compiles afresh (tens of seconds; the first calls' time is printed below the table).
"x plain" is the plain row's median time over this row's (> 1: faster).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

SAND = Path(__file__).resolve().parents[2] / "shared" / "data" / "sand2d-taichi"
LABELS = {1100: "WaterDrop size", 10_000: "10k particles"}


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="tiny repeats and sizes (smoke test)")
    p.add_argument("--threads", type=int, help="torch and Rust threads (default: all cores)")
    p.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    p.add_argument(
        "--sizes", type=int, nargs="*", help="lattice cases (default 1100 10000, quick 300 1100)"
    )
    p.add_argument("--sand", default=str(SAND), help="sand2d-taichi folder ('' to skip)")
    p.add_argument("--reps", type=int, help="measured repeats (default 5, quick 2)")
    p.add_argument(
        "--variants",
        nargs="*",
        choices=["plain", "fast", "bf16", "compiled", "all"],
        help="rows per case (default: plain fast, and bf16 where it is native)",
    )
    args = p.parse_args()
    if args.sizes is None:
        args.sizes = [300, 1100] if args.quick else [1100, 10_000]
    args.reps = args.reps or (2 if args.quick else 5)
    args.warmup = 1 if args.quick else 2
    args.steps = 2 if args.quick else 5  # rollout steps per repeat
    args.matmul = 1024 if args.quick else 4096
    return args


ARGS = parse_args()
if ARGS.threads is not None:  # before the Rust pool starts: it reads this once
    os.environ["RAYON_NUM_THREADS"] = str(ARGS.threads)

import torch  # noqa: E402
from gns.config import Config  # noqa: E402
from gns.data import Trajectory, open_dataset  # noqa: E402
from gns.data.windows import collate, trajectory_windows  # noqa: E402
from gns.model import EncodeProcessDecode, native_bf16  # noqa: E402
from gns.rollout import TIMING_PARTS, rollout  # noqa: E402
from gns.simulator import LearnedSimulator, Scene  # noqa: E402
from gns.train import TrainingStep, batch_tensors  # noqa: E402
from lattice import lattice  # noqa: E402
from torch import nn  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402
from torch_bench import bench_device, machine_facts, synchronize  # noqa: E402


@dataclass(frozen=True)
class Variant:
    """One implementation of the GNS: build(scene, config) -> simulator; `context` wraps every
    timed call; `precision` names the matmul rate it is compared with."""

    key: str
    name: str
    build: Callable[[Scene, Config], LearnedSimulator]
    context: Callable[[], AbstractContextManager[object]] = nullcontext
    precision: str = "fp32"


def model_settings(**changes: Any) -> Callable[[Scene, Config], LearnedSimulator]:
    """A builder of the default simulator with these ModelConfig settings."""

    def build(scene: Scene, config: Config) -> LearnedSimulator:
        return LearnedSimulator(scene, replace(config, model=replace(config.model, **changes)))

    return build


VARIANTS = [
    Variant("plain", "plain fp32", model_settings(implementation="plain", precision="fp32")),
    Variant("fast", "fast fp32", model_settings(implementation="fast", precision="fp32")),
    Variant(
        "bf16",
        "fast bf16",
        model_settings(implementation="fast", precision="bf16"),
        precision="bf16",
    ),
    Variant(
        "compiled",
        "fast fp32 compiled",
        model_settings(implementation="fast", precision="fp32", torch_compile=True),
    ),
]


@dataclass(frozen=True)
class Case:
    name: str
    scene: Scene
    trajectory: Trajectory  # rollouts start at frame 0, the training window too


def lattice_case(n: int, history: int) -> Case:
    """n particles on a jittered square lattice with ~13 neighbours within RADIUS."""
    scene, trajectory = lattice(n, history + 1)
    return Case(LABELS.get(n, f"{n} particles"), scene, trajectory)


def sand_case(path: Path, config: Config, start: int = 100) -> Case | None:
    """The real sand2d-taichi data: trajectory 0 of the train split from frame `start`."""
    if not path.is_dir():
        print(f"(sand2d-taichi not found at {path}: skipped)")
        return None
    dataset = open_dataset(path, "train")
    t = dataset[0]
    scene = Scene.from_metadata(dataset.metadata, np.unique(t.particle_type), config.scene)
    context = None if t.step_context is None else t.step_context[start:]
    cut = Trajectory(t.positions[start:], t.particle_type, context, t.material_property)
    return Case("sand2d-taichi", scene, cut)


def forward_flops(model: EncodeProcessDecode, n_nodes: int, n_edges: int, n_graphs: int = 1) -> int:
    """FLOPs of one EncodeProcessDecode forward: 2 * in * out per row for every nn.Linear, with
    E rows for edge MLPs (edge encoder, processor edge MLPs), G for global ones and N for the
    rest (node encoder, processor node MLPs, decoder). LayerNorm, ReLU, the gathers and the
    index_add_ aggregation are O(width) per row and left out."""
    total = 0
    for name, module in model.named_modules():
        if isinstance(module, nn.Linear):
            rows = n_edges if "edge_" in name else n_graphs if "global_" in name else n_nodes
            total += 2 * module.in_features * module.out_features * rows
    return total


def timed(fn: Callable[[], object], warmup: int, reps: int, device: torch.device) -> np.ndarray:
    """Seconds of `reps` calls of fn after `warmup` untimed ones."""
    for _ in range(warmup):
        fn()
    seconds = []
    for _ in range(reps):
        synchronize(device)
        t0 = time.perf_counter()
        fn()
        synchronize(device)
        seconds.append(time.perf_counter() - t0)
    return np.array(seconds)


def matmul_flops_per_second(
    size: int, device: torch.device, warmup: int, reps: int, dtype: torch.dtype = torch.float32
) -> float:
    """(size x size) @ (size x size) throughput in `dtype`, the machine's yardstick."""
    a, b = (torch.randn(size, size, device=device, dtype=dtype) for _ in range(2))
    seconds = timed(lambda: a @ b, warmup, reps, device)
    return 2 * size**3 / float(np.median(seconds))


def measure(case: Case, variant: Variant, config: Config, device: torch.device) -> dict:
    """One row: rollout and training step times, edges and FLOPs of `variant` on `case`."""
    history = config.model.velocity_history + 1
    torch.manual_seed(0)
    simulator = variant.build(case.scene, config).to(device)
    batch = collate(list(trajectory_windows(case.trajectory, history, [0])))
    t = batch_tensors(batch, device)
    sequence, types = t["position_sequence"], t["particle_type"]
    assert sequence is not None and types is not None and t["next_position"] is not None
    generator = torch.Generator(device=device).manual_seed(0)
    # Prime the running statistics with this window, so the untrained model predicts
    # accelerations of the data's scale and the rollout keeps the case's graph.
    noise = simulator.sample_noise(sequence, types, generator)
    acceleration = simulator.acceleration(t["next_position"], sequence + noise)
    simulator.update_statistics(sequence + noise, acceleration, types, t["n_node"], t["context"])

    # Rollout: the per-step split of gns.rollout, pooled over all measured steps.
    with variant.context():
        t0 = time.perf_counter()
        rollout(simulator, case.trajectory, num_steps=1)  # compiles, for a compiled variant
        first_rollout = time.perf_counter() - t0
        if ARGS.warmup > 1:
            rollout(simulator, case.trajectory, num_steps=ARGS.warmup - 1)
        runs = [rollout(simulator, case.trajectory, num_steps=ARGS.steps) for _ in range(ARGS.reps)]
    parts = {p: np.concatenate([r.timings[p] for r in runs]) for p in TIMING_PARTS}
    per_step = sum(parts.values())

    # Training: noise, TrainingStep forward, backward, Adam (as gns.train's loop does).
    step = TrainingStep(simulator).train()
    optimizer = torch.optim.Adam(simulator.parameters(), lr=config.train.learning_rate)

    def train_step() -> float:
        with variant.context():
            noise = simulator.sample_noise(sequence, types, generator)
            args = (t["next_position"], noise, types, t["n_node"], t["context"])
            squared, count = step(sequence, *args, t["material_property"])
            loss = squared / count.to(squared.dtype).clamp(min=1.0)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        return float(loss.detach())

    t0 = time.perf_counter()
    train_step()
    synchronize(device)
    first_train = time.perf_counter() - t0
    train = timed(train_step, ARGS.warmup - 1, ARGS.reps, device)

    # FLOPs of the plain model on this case's graph (the useful work, whatever the variant);
    # counted by torch as a cross-check.
    simulator.eval()
    with torch.inference_mode():
        f = simulator.features(sequence, types, t["n_node"], t["context"], t["material_property"])
        n, e = sequence.shape[0], f["senders"].shape[0]  # type: ignore[union-attr]
        plain = replace(config.model, implementation="plain", precision="fp32", torch_compile=False)
        reference = EncodeProcessDecode(
            simulator.node_input_size, simulator.edge_input_size, 2, plain
        ).to(device)
        flops = forward_flops(reference, n, e)
        with FlopCounterMode(display=False) as counter:
            reference(f["node_features"], f["edge_features"], f["senders"], f["receivers"])
    return {
        "n": n,
        "e": e,
        "rollout": per_step,
        **{p: float(np.median(s)) for p, s in parts.items()},
        "train": train,
        "flops": flops,
        "torch_flops": counter.get_total_flops(),
        "first_rollout": first_rollout,
        "first_train": first_train,
    }


COLUMNS = [  # (title, width); the first two are left-aligned
    *[("case", 15), ("variant", 18), ("N", 6), ("E", 7), ("E/N", 5)],
    *[("rollout ms", 17), ("x plain", 7), ("graph", 6), ("feat", 6), ("model", 8)],
    *[("integ", 6), ("graph%", 6), ("train ms", 17), ("x plain", 7)],
    *[("GFLOP", 6), ("fwd GF/s", 8), ("% mm", 5), ("trn GF/s", 8), ("% mm", 5)],
]


def line(texts: list[str]) -> str:
    """One table line: the texts padded to the COLUMNS' widths."""
    widths = [w for _, w in COLUMNS]
    pairs = enumerate(zip(texts, widths, strict=True))
    return " ".join(t.ljust(w) if i < 2 else t.rjust(w) for i, (t, w) in pairs)


def cells(case: Case, variant: Variant, r: dict, peak: float, plain: dict | None) -> list[str]:
    """The table row of one measurement; peak: the matmul FLOP/s in the variant's precision;
    plain: the plain row's measurement of the same case, for the "x plain" ratios."""
    ms = {p: 1e3 * r[p] for p in TIMING_PARTS}
    roll, train = 1e3 * r["rollout"], 1e3 * r["train"]

    def ratio(part: str) -> str:
        if plain is None:
            return "-"
        return f"{float(np.median(plain[part]) / np.median(r[part])):.2f}"

    forward = r["flops"] / r["model"]  # the model part of a rollout step
    training = 3 * r["flops"] / float(np.median(r["train"]))  # the whole training step
    return [
        *[case.name, variant.name, str(r["n"]), str(r["e"]), f"{r['e'] / r['n']:.1f}"],
        f"{np.median(roll):.1f} ({roll.min():.1f})",
        ratio("rollout"),
        *[f"{ms['graph']:.2f}", f"{ms['features']:.2f}", f"{ms['model']:.1f}"],
        f"{ms['integration']:.2f}",
        f"{100 * ms['graph'] / np.median(roll):.1f}%",
        f"{np.median(train):.1f} ({train.min():.1f})",
        ratio("train"),
        f"{r['flops'] / 1e9:.2f}",
        *[f"{forward / 1e9:.1f}", f"{100 * forward / peak:.0f}%"],
        *[f"{training / 1e9:.1f}", f"{100 * training / peak:.0f}%"],
    ]


def main() -> None:
    device = bench_device("step.py", ARGS.threads, ARGS.device)
    config = Config()
    print("\n".join(machine_facts(device)))
    keys = ARGS.variants or ["plain", "fast"] + (["bf16"] if native_bf16(device) else [])
    keys = [v.key for v in VARIANTS] if "all" in keys else keys
    variants = [v for v in VARIANTS if v.key in keys]
    if "bf16" not in keys:
        # Why it was left out: the machine's, or the --variants given (issue 40: the message
        # said "not native" on an H100 whenever --variants named other variants only).
        why = (
            f"--variants {' '.join(ARGS.variants)} leaves it out"
            if ARGS.variants
            else f"bf16 is not native on {device}; --variants bf16 forces it"
        )
        print(f"fast bf16: not run ({why})")
    s = ARGS.matmul
    peaks = {"fp32": matmul_flops_per_second(s, device, ARGS.warmup, ARGS.reps)}
    print(f"fp32 matmul ({s} x {s}) @ ({s} x {s}): {peaks['fp32'] / 1e9:.1f} GFLOP/s")
    if "bf16" in keys:
        # Emulated bf16 is ~20x slower than fp32: a smaller yardstick keeps this short.
        s = s if native_bf16(device) else min(s, 1024)
        peaks["bf16"] = matmul_flops_per_second(s, device, 1, ARGS.reps, torch.bfloat16)
        print(f"bf16 matmul ({s} x {s}) @ ({s} x {s}): {peaks['bf16'] / 1e9:.1f} GFLOP/s")
    m = config.model
    print(
        f"model: GNS-{m.message_passing_steps}-{m.latent_size}; rollout: {ARGS.reps} x "
        f"{ARGS.steps} steps after {ARGS.warmup}; training: {ARGS.reps} steps after "
        f"{ARGS.warmup}; times median (min) in ms\n"
    )
    history = config.model.velocity_history + 1
    cases = [lattice_case(n, history) for n in ARGS.sizes]
    sand = sand_case(Path(ARGS.sand), config) if ARGS.sand else None
    cases += [sand] if sand else []

    print(line([title for title, _ in COLUMNS]))
    print("-" * len(line([""] * len(COLUMNS))))
    notes = []
    for case in cases:
        plain = None
        for variant in variants:
            r = measure(case, variant, config, device)
            plain = r if variant.key == "plain" else plain
            print(line(cells(case, variant, r, peaks[variant.precision], plain)), flush=True)
            if variant.key == "compiled":
                notes.append(
                    f"{case.name}, {variant.name}: first 1-step rollout "
                    f"{r['first_rollout']:.1f} s, first training step {r['first_train']:.1f} s "
                    "(compilation)"
                )
            if abs(r["torch_flops"] - r["flops"]) > 0.1 * r["flops"]:
                notes.append(
                    f"{case.name}: FlopCounterMode counts {r['torch_flops'] / 1e9:.2f} GFLOP, "
                    f"forward_flops {r['flops'] / 1e9:.2f}"
                )
    print("\n".join(notes) or "(FlopCounterMode agrees with forward_flops within 10%)")


if __name__ == "__main__":
    main()
