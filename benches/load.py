"""A rollout step of the GNS idle and with one core busy, under each way of choosing threads.

    python benches/load.py [--quick] [--models 3-32 10-128] [--particles 1100] [--steps 40]

A user's machine is often busy: with another process on one core, torch's OpenMP workers can
wait for a thread that is not running (issue 22: a GNS-3-32 step went from 3.6 ms to 1,166 ms
on a 2-core Zen 4). Rows, each measured in a fresh process (OpenMP reads its settings once):
- "before": what gns did until issue 22: torch's default thread count and wait policy, fixed,
  and precision "auto" as it was then (bf16 wherever it is native, fp32 elsewhere);
- "1 thread" and "2 thr. passive" (OMP_WAIT_POLICY=passive): the fixed alternatives;
- "gns default": what gns does now (gns.threads: the thread count chosen by timing the steps,
  timed again when they slow down; precision "auto": bf16 only when measured faster and close).
Conditions: "idle", and "busy" with one process spinning on the CPU for the whole
measurement (not pinned: the scheduler places it, as a user's other program would be).
The model: the demo's GNS-3-32 (latent 32, 3 message-passing steps) and the paper's GNS-10-128,
untrained but with a zero output layer, so the particles keep their lattice and every step
has the same graph: 1100 particles on the WaterDrop-sized lattice of benches/step.py.
Per measurement: the median and the mean ms per rollout step (gns.rollout's own timing, graph
to integration) over `reps` rollouts of `steps` steps after one unmeasured rollout (the mean
includes whatever re-probing the tuner did). This VM's speed drifts by 20-40% within minutes,
so the policies are measured in turn, `rounds` times in a rotating order, and each cell is the
median over the rounds with their range; "x before" is the "before" row's median over this
row's in the same condition; "ran with" is the threads and precision of the last rollout of
each round (several when the rounds differed).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

# name -> (environment, gns settings); threads None: gns's default (tuned).
POLICIES: dict[str, tuple[dict[str, str], dict[str, object]]] = {
    "before": ({}, {"threads": "torch", "precision": "old-auto"}),
    "1 thread": ({}, {"threads": 1, "precision": "fp32"}),
    "2 thr. passive": ({"OMP_WAIT_POLICY": "passive"}, {"threads": 2, "precision": "fp32"}),
    "gns default": ({}, {"threads": None, "precision": "auto"}),
}


def parse_args() -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--quick", action="store_true", help="small sizes and repeats (smoke test)")
    p.add_argument("--models", nargs="+", default=["3-32", "10-128"], help="GNS-M-L by M-L")
    p.add_argument("--particles", type=int, help="lattice size (default 1100, quick 200)")
    p.add_argument("--steps", type=int, help="steps per rollout (default 40, quick 6)")
    p.add_argument("--reps", type=int, help="measured rollouts (default 3, quick 1)")
    p.add_argument("--rounds", type=int, help="turns through the policies (default 3, quick 1)")
    p.add_argument("--policies", nargs="+", choices=list(POLICIES), default=list(POLICIES))
    p.add_argument("--conditions", nargs="+", choices=["idle", "busy"], default=["idle", "busy"])
    p.add_argument("--child", help=argparse.SUPPRESS)  # one measurement, as JSON
    args = p.parse_args()
    args.particles = args.particles or (200 if args.quick else 1100)
    args.steps = args.steps or (6 if args.quick else 40)
    args.reps = args.reps or (1 if args.quick else 3)
    args.rounds = args.rounds or (1 if args.quick else 3)
    return args


def child(spec: dict) -> dict:
    """One measurement in this process: returns the step times and what they ran with."""
    import numpy as np
    import torch
    from gns.config import Config, ModelConfig
    from gns.model import native_bf16
    from gns.rollout import rollout
    from gns.simulator import LearnedSimulator
    from gns.threads import fix_threads

    sys.path.insert(0, str(HERE))
    from lattice import lattice

    threads, precision = spec["threads"], spec["precision"]
    if threads == "torch":  # torch's default count, fixed (the tuner leaves it alone)
        fix_threads(torch.get_num_threads())
    elif threads is not None:
        fix_threads(int(threads))
    if precision == "old-auto":
        precision = "bf16" if native_bf16("cpu") else "fp32"
    depth, width = (int(v) for v in spec["model"].split("-"))
    scene, trajectory = lattice(spec["particles"], 6 + spec["steps"])
    model = ModelConfig(
        latent_size=width, mlp_hidden_size=width, message_passing_steps=depth, precision=precision
    )
    torch.manual_seed(0)
    simulator = LearnedSimulator(scene, Config(model=model))
    output = simulator.model.decoder[-1]
    torch.nn.init.zeros_(output.weight)
    torch.nn.init.zeros_(output.bias)
    times, result = [], None
    for rep in range(spec["reps"] + 1):
        result = rollout(simulator, trajectory, escape_distance=None)
        if rep:  # the first rollout warms up (and lets the tuner choose)
            times.append(sum(result.timings.values()))
    per_step = 1e3 * np.concatenate(times)
    assert result is not None
    return {
        "median": float(np.median(per_step)),
        "mean": float(np.mean(per_step)),
        "threads": result.metadata["torch_threads"],
        "precision": result.metadata["precision"],
    }


def measure(args: argparse.Namespace, model: str, policy: str) -> dict:
    env, settings = POLICIES[policy]
    spec = {**settings, "model": model, "particles": args.particles, "steps": args.steps,
            "reps": args.reps}  # fmt: skip
    command = [sys.executable, __file__, "--child", json.dumps(spec)]
    run = subprocess.run(
        command, env={**os.environ, **env}, capture_output=True, text=True, timeout=3600
    )
    if run.returncode:
        raise RuntimeError(f"{policy} {model}: {run.stderr.strip().splitlines()[-1]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def summary(runs: list[dict]) -> dict:
    """One cell from the rounds: the median of their medians, its range, the mean of their
    means, and what they ran with."""
    import statistics

    medians = [r["median"] for r in runs]
    ran = dict.fromkeys(f"{r['threads']} thr. {r['precision']}" for r in runs)
    return {
        "median": statistics.median(medians),
        "low": min(medians),
        "high": max(medians),
        "mean": statistics.mean(r["mean"] for r in runs),
        "ran": " / ".join(ran),
    }


def busy_core() -> subprocess.Popen:
    """Another program holding one core for as long as it runs."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


def main() -> None:
    args = parse_args()
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return
    from gns.machine import cpu_name

    print(f"{cpu_name()}, {os.cpu_count()} CPUs; {args.particles} particles on the lattice, "
          f"{args.reps} rollouts of {args.steps} steps per measurement, {args.rounds} rounds; "
          "ms per rollout step")  # fmt: skip
    rounds: dict[tuple[str, str, str], list[dict]] = {}
    for condition in args.conditions:
        spinner = busy_core() if condition == "busy" else None
        try:
            time.sleep(0.5 if spinner else 0.0)
            for model in args.models:
                for turn in range(args.rounds):
                    shift = turn % len(args.policies)
                    for policy in args.policies[shift:] + args.policies[:shift]:
                        key = (condition, model, policy)
                        rounds.setdefault(key, []).append(measure(args, model, policy))
        finally:
            if spinner is not None:
                spinner.kill()
                spinner.wait()
    results = {key: summary(runs) for key, runs in rounds.items()}
    header = ["model", "policy"]
    for condition in args.conditions:
        header += [f"{condition} median", "mean", "x before", "ran with"]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for model in args.models:
        for policy in args.policies:
            cells = [f"GNS-{model}", policy]
            for condition in args.conditions:
                r = results[condition, model, policy]
                before = results.get((condition, model, "before"))
                ratio = f"{before['median'] / r['median']:.2f}" if before else "-"
                spread = f"{r['median']:.2f} ({r['low']:.2f}-{r['high']:.2f})"
                cells += [spread, f"{r['mean']:.2f}", ratio, r["ran"]]
            print("| " + " | ".join(cells) + " |", flush=True)


if __name__ == "__main__":
    main()
