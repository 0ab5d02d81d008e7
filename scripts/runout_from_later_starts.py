"""When does a model lose the runout? Roll it out from the truth's frames at later starts.

    python scripts/runout_from_later_starts.py MODEL DATA SPLIT [--starts 0 10 20 30 50 80]

MODEL: a model name, folder or checkpoint (as `gns rollout --run`); DATA: a dataset folder in
which the deposits are measured along x. For each trajectory and each start s (in the model's
steps), the model is rolled out from the ground truth's frames s ... s + C to the trajectory's
end, and the runout of its last frame (the 99th minus the 1st percentile of x over the free,
not kinematic, particles, as `gns eval` measures it) is printed over the truth's: a ratio near
1 from start s on means the model keeps what the truth has reached by then, and the runout is
lost before s.
"""

from __future__ import annotations

import argparse
import dataclasses

import gns
import numpy as np
import torch
from gns.deposit import runout_extent
from gns.rollout import rollout


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("data")
    parser.add_argument("split")
    parser.add_argument("--starts", type=int, nargs="+", default=[0, 10, 20, 30, 50, 80])
    args = parser.parse_args()
    torch.set_num_threads(1)
    simulator = gns.load_simulator(args.model).eval()
    dataset = gns.data.open_dataset(args.data, args.split)
    stride = simulator.frame_stride_for(dataset.metadata)
    print("| trajectory | " + " | ".join(f"from step {s}" for s in args.starts) + " |")
    print("|---" * (len(args.starts) + 1) + "|")
    ratios = []
    for index in range(len(dataset)):
        trajectory = gns.data.at_frame_stride(dataset[index], stride)
        free = ~simulator.scene.kinematic_mask(trajectory.particle_type)  # as gns eval measures
        truth = runout_extent(trajectory.positions[-1], free)
        row = []
        for start in args.starts:
            context = trajectory.step_context
            later = dataclasses.replace(
                trajectory,
                positions=trajectory.positions[start:],
                step_context=None if context is None else context[start:],
            )
            last = rollout(simulator, later).predicted_trajectory[-1]
            row.append(runout_extent(last, free) / truth)
        ratios.append(row)
        print(f"| {index} | " + " | ".join(f"{r:.2f}" for r in row) + " |", flush=True)
    mean = np.mean(ratios, axis=0)
    print("| mean | " + " | ".join(f"{r:.2f}" for r in mean) + " |")


if __name__ == "__main__":
    main()
