"""Is a RadiusSearcher kept between rollout steps worth it? The graph part of a step (radius
graph, then the edges' displacements, as LearnedSimulator.graph builds them on the CPU) with a
fresh search per call (gns.ops.radius_graph) against one reused gns.RadiusSearcher (its
buffers kept between calls, as LearnedSimulator does since this measurement).

    python benches/graph_reuse.py [--sizes N ...] [--rounds R] [--calls K] [--step]

Cases: benches/lattice.py's jittered lattice (2D, R = 0.015, ~13 neighbours), each call on the
next frame of its slowly moving trajectory, as a rollout's steps are. The two run in turn,
`rounds` rounds of `calls` calls each (the order swapped every round), so drift and other
processes hit both alike; printed: the median ms per call of each, and the per-round ratio
reused / fresh (median, min, max). --step also times one rollout step of the default model
(GNS-10-128, fast fp32) on the case, to put the difference in proportion.

Run it with OMP_NUM_THREADS=1 when a core is busy: two torch threads then stall the
displacements (index_select) for 10-40 ms a call, which hides the search (a rollout's thread
tuner would have moved torch to one thread by then).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch
from gns import ops
from lattice import RADIUS, lattice


def graph_stage(search: Callable[..., torch.Tensor], x: torch.Tensor) -> torch.Tensor:
    """LearnedSimulator._graph on the CPU without periodic axes, with `search` for the edges."""
    edges = search(x, RADIUS, self_edges=True)
    senders, receivers = edges[0], edges[1]
    return x.index_select(0, senders) - x.index_select(0, receivers)


def step_ms(n: int) -> float:
    """Median ms of a rollout step of the default model on the case (3 steps after 1)."""
    from gns.config import Config
    from gns.rollout import TIMING_PARTS, rollout
    from gns.simulator import LearnedSimulator

    scene, trajectory = lattice(n, 10)
    torch.manual_seed(0)
    simulator = LearnedSimulator(scene, Config())
    # Running statistics primed with the case (as benches/step.py does), so the untrained
    # model's steps are of the data's size and the graph stays the case's.
    window = torch.from_numpy(trajectory.positions[:7].transpose(1, 0, 2).copy())
    types = torch.from_numpy(trajectory.particle_type.copy())
    noisy = window[:, :6] + simulator.sample_noise(window[:, :6], types)
    simulator.update_statistics(noisy, simulator.acceleration(window[:, 6], noisy), types)
    rollout(simulator, trajectory, num_steps=1)
    r = rollout(simulator, trajectory, num_steps=3)
    return 1e3 * float(np.median(sum(r.timings[p] for p in TIMING_PARTS)))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--sizes", type=int, nargs="*", default=[1100, 2000, 4000, 8000])
    p.add_argument("--rounds", type=int, default=20)
    p.add_argument("--calls", type=int, default=50)
    p.add_argument("--step", action="store_true", help="also time a rollout step")
    args = p.parse_args()
    print(f"torch threads {torch.get_num_threads()}; ms per graph stage, median of calls")
    print("N      E        fresh ms  reused ms  reused/fresh per round: median (min-max)")
    for n in args.sizes:
        _, trajectory = lattice(n, args.calls)
        frames = [torch.from_numpy(x) for x in trajectory.positions]
        searcher = ops.RadiusSearcher()
        variants = {"fresh": ops.radius_graph, "reused": searcher}
        times: dict[str, list[float]] = {k: [] for k in variants}
        ratios = []
        for search in variants.values():
            graph_stage(search, frames[0])  # warm-up (the searcher's buffers, the pool)
        for r in range(args.rounds):
            medians = {}
            for name in sorted(variants, reverse=r % 2 == 1):
                seconds = []
                for x in frames:
                    t0 = time.perf_counter()
                    graph_stage(variants[name], x)
                    seconds.append(time.perf_counter() - t0)
                times[name] += seconds
                medians[name] = float(np.median(seconds))
            ratios.append(medians["reused"] / medians["fresh"])
        edges = graph_stage(searcher, frames[0]).shape[0]
        fresh, reused = (1e3 * float(np.median(times[k])) for k in variants)
        line = f"{n:<6} {edges:<8} {fresh:8.3f}  {reused:9.3f}  "
        line += f"{np.median(ratios):.3f} ({min(ratios):.3f}-{max(ratios):.3f})"
        if args.step:
            step = step_ms(n)
            line += f"; step {step:.0f} ms, difference {100 * (fresh - reused) / step:.2f}% of it"
        print(line, flush=True)


if __name__ == "__main__":
    main()
