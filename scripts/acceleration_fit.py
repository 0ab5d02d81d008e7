"""How much of the true acceleration a model predicts, one step ahead from true frames, by size.

    python scripts/acceleration_fit.py MODEL DATA SPLIT [--trajectories 8] [--every 2]

MODEL: a model name, folder or checkpoint (as `gns rollout --run`); DATA: a dataset folder.
Every `every`-th window of `trajectories` trajectories (spread evenly over the split) is
predicted from the ground truth's frames (no noise, no rollout), at the model's frame stride;
kinematic particles, which follow the truth, do not count.
The particle-steps are binned by the size of their true acceleration, in units of its std over
them (per axis: the same units for every model on the same data). Each bin prints its share
of the particle-steps, the slope of predicted on true acceleration (1: all of it; 0.5: half),
the rms error and its share of the squared error. The first line gives R^2 over all of them
and how much of the target's squared size the largest 1% of the true accelerations hold.
A rollout can only be as good as these steps: where the slope is
well below 1 the model damps that motion (for sand: gravity and the spreading after landing).
"""

from __future__ import annotations

import argparse

import gns
import numpy as np
import torch
from gns.data.windows import window_keys
from gns.evaluate import one_step_predictions

BINS = (0.0, 0.1, 0.3, 1.0, 3.0, 10.0, np.inf)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("data")
    parser.add_argument("split")
    parser.add_argument("--trajectories", type=int, default=8)
    parser.add_argument("--every", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(1)
    simulator = gns.load_simulator(args.model).eval()
    dataset = gns.data.open_dataset(args.data, args.split)
    stride = simulator.frame_stride_for(dataset.metadata)
    history = simulator.config.model.velocity_history + 1
    chosen = np.unique(np.linspace(0, len(dataset) - 1, min(args.trajectories, len(dataset))))
    trajectories = [gns.data.at_frame_stride(dataset[int(i)], stride) for i in chosen]
    pairs = [(k, s) for k, s in window_keys(trajectories, history) if s % args.every == 0]
    true, predicted = [], []
    for sequence, truth, following, free in one_step_predictions(simulator, trajectories, pairs):
        # Second differences as the model takes them (minimum images on periodic axes).
        sequence, last = sequence.double(), sequence[:, -1].double()
        velocity = simulator.displacement(last, sequence[:, -2])
        true.append((simulator.displacement(truth.double(), last) - velocity)[free].numpy())
        moved = simulator.displacement(following.double(), last)
        predicted.append((moved - velocity)[free].numpy())
    true_all = np.concatenate(true)
    std = true_all.std(axis=0)
    a, p = true_all / std, np.concatenate(predicted) / std
    size = np.linalg.norm(a, axis=1)
    error = ((p - a) ** 2).sum(axis=1)
    explained = 1.0 - error.sum() / ((a - a.mean(axis=0)) ** 2).sum()
    top = np.sort(size**2)[-max(1, len(size) // 100) :].sum() / (size**2).sum()
    print(
        f"{args.model} on {args.split}: {len(size)} particle-steps from {len(chosen)} "
        f"trajectories, true acceleration std {std} a step; R^2 {explained:.2f} (squared error "
        f"{error.mean():.3f} in units of the std); the largest 1% of the true accelerations "
        f"hold {top:.0%} of their squares"
    )
    print("| true acceleration (std) | share | slope | rms error | share of squared error |")
    print("|---|---|---|---|---|")
    for low, high in zip(BINS[:-1], BINS[1:], strict=True):
        keep = (size >= low) & (size < high)
        if not keep.any():
            continue
        slope = (a[keep] * p[keep]).sum() / (a[keep] ** 2).sum()
        print(
            f"| {low:g}-{high:g} | {keep.mean():.3f} | {slope:.2f} | "
            f"{np.sqrt(error[keep].mean()):.3f} | {error[keep].sum() / error.sum():.2f} |"
        )


if __name__ == "__main__":
    main()
