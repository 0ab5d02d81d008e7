"""`gns demo`: the whole job on a built-in scene, from nothing to a report, on this machine.

    demo("demo")   # OUT/data, OUT/run, OUT/report/report.md

1. generate  a small dataset with the reference simulator (gns.mpm.generate; resumes by itself)
2. train     a small GNS for a bounded wall-clock time (gns.train's time_limit), validating on
             the valid split so that checkpoints/best.pt exists, with rollouts as long as the
             report's (whole trajectories)
3. report    rollouts of the held-out test trajectories with the best and the latest checkpoint,
             against the simulator at native and cheaper settings and the constant-velocity
             baseline (gns.report), into OUT/report/

Every phase reports progress on stderr. Running the same command again resumes: the dataset is
reused, an interrupted training continues from its last checkpoint (with the full time budget
again), a finished one is kept, and the report is rewritten. OUT/demo.json records the
arguments; other arguments in the same folder are refused rather than mixed. Every argument is
checked before OUT is made.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gns.files import claim_folder, write_json_atomic

__all__ = ["SIZES", "DemoSize", "demo", "demo_config"]


@dataclass(frozen=True)
class DemoSize:
    """How big a demo is: trajectories per split (train, valid, test), frames per trajectory
    (frame 0 included), the GNS (latent and MLP width, message-passing steps), the training
    budget (minutes of wall-clock time, and a cap on gradient steps) and validation cadence."""

    trajectories: tuple[int, int, int]
    frames: int
    latent: int
    message_passing_steps: int
    minutes: float
    steps: int
    validate_every: int


SIZES: dict[str, DemoSize] = {
    # For tests: seconds in all; the model learns nothing, every output file is still made.
    "tiny": DemoSize((2, 1, 1), 16, 8, 1, 1.0, 4, 2),
    # The default: about 5-10 minutes on a 2-core CPU, most of it training.
    "small": DemoSize((12, 2, 2), 161, 32, 3, 4.0, 100_000, 500),
    "medium": DemoSize((40, 4, 4), 321, 64, 5, 30.0, 1_000_000, 2000),
    # The paper's model (latent 128, 10 steps) and preset lengths; hours on a CPU.
    "large": DemoSize((100, 10, 10), 321, 128, 10, 240.0, 10_000_000, 10_000),
}


def demo_config(size: DemoSize, steps: int) -> Any:
    """The GNS settings of a demo: the paper's model at the size's width and depth, noise
    1e-4 (the paper's 3e-4 is about the per-frame acceleration std of the generated sand, and
    less noise learns faster in a short budget), learning rate 4e-4 decaying 10x over 20000
    steps, validation rollouts of whole trajectories (size.frames less the C + 1 input frames)
    on the valid split.

    Whole trajectories, because best.pt is what the report rolls out on the test split, over
    the same length: a model chosen on 50-frame rollouts was seen to beat the others there and
    then diverge on the 155 frames of the test rollouts (issue 22)."""
    from gns.config import Config, ModelConfig, NoiseConfig, TrainConfig

    model = ModelConfig(
        latent_size=size.latent,
        mlp_hidden_size=size.latent,
        message_passing_steps=size.message_passing_steps,
    )
    return Config(
        model=model,
        noise=NoiseConfig(std=1e-4),
        train=TrainConfig(
            steps=steps,
            learning_rate=4e-4,
            learning_rate_final=1e-5,
            learning_rate_decay_steps=20_000,
            log_every=min(100, steps),
            validate_every=size.validate_every,
            validation_windows=64,
            validation_rollouts=2,
            validation_rollout_steps=size.frames - (model.velocity_history + 1),
            checkpoint_every=max(size.validate_every, 500),
            keep_checkpoints=2,
        ),
    )


def _phase(number: int, text: str) -> float:
    sys.stderr.write(f"gns demo [{number}/3] {text}\n")
    sys.stderr.flush()
    return time.perf_counter()


def _arguments(out: Path, arguments: dict[str, Any]) -> None:
    """Record the demo's arguments in OUT/demo.json, or check them against an earlier run."""
    claim_folder(
        out,
        "demo.json",
        arguments,
        holds="a demo made",
        resume="repeat that command to resume it, or choose another --out",
        foreign="exists, is not empty and is not a gns demo folder",
    )


def demo(
    out: str | os.PathLike[str] = "demo",
    *,
    preset: str = "sand",
    size: str = "small",
    train_minutes: float | None = None,
    steps: int | None = None,
    trajectories: tuple[int, int, int] | None = None,
    frames: int | None = None,
    seed: int = 0,
    device: str = "auto",
    workers: int | None = None,
    command: str | None = None,
) -> Path:
    """Run the demo into `out` (see the module docstring); returns the report folder.

    size: one of SIZES; train_minutes, steps, trajectories (train, valid, test) and frames
    override its values. The test split is what the report rolls out.
    """
    from gns.checkpoints import latest_checkpoint, load_checkpoint
    from gns.device import resolve_device
    from gns.mpm.generate import PRESETS, generate
    from gns.report import report
    from gns.train import train

    # Every argument is checked here, before OUT (and demo.json in it) is made: a typo must not
    # leave a folder that a corrected command would then refuse as "other arguments".
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
    if size not in SIZES:
        raise ValueError(f"unknown demo size {size!r}; expected one of {list(SIZES)}")
    chosen = SIZES[size]
    if trajectories is not None:
        if len(trajectories) != 3 or min(trajectories) < 1:
            raise ValueError(
                f"trajectories must be three counts >= 1 (train, valid, test), got {trajectories}"
            )
        train_n, valid_n, test_n = (int(n) for n in trajectories)
        chosen = dataclasses.replace(chosen, trajectories=(train_n, valid_n, test_n))
    if train_minutes is not None:
        if not (train_minutes > 0 and math.isfinite(train_minutes)):
            raise ValueError(f"train_minutes must be a positive number, got {train_minutes}")
        chosen = dataclasses.replace(chosen, minutes=float(train_minutes))
    if steps is not None:
        if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
            raise ValueError(f"steps must be a whole number >= 1, got {steps!r}")
        chosen = dataclasses.replace(chosen, steps=steps)
    if frames is not None:
        # The model reads 6 frames (velocity_history 5); a rollout needs a few more after them.
        if isinstance(frames, bool) or not isinstance(frames, int) or frames < 8:
            raise ValueError(f"frames must be a whole number >= 8, got {frames!r}")
        chosen = dataclasses.replace(chosen, frames=frames)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ValueError(f"seed must be a whole number >= 0, got {seed!r}")
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 1
    ):
        raise ValueError(f"workers must be a whole number >= 1, got {workers!r}")
    resolve_device(device)
    out = Path(out)
    arguments = {"preset": preset, "seed": seed, **dataclasses.asdict(chosen)}
    arguments["trajectories"] = list(chosen.trajectories)
    _arguments(out, arguments)
    data, run = out / "data", out / "run"
    started = time.perf_counter()

    n_train, n_valid, n_test = chosen.trajectories
    t0 = _phase(
        1,
        f"generating {preset}: {n_train}/{n_valid}/{n_test} trajectories of "
        f"{chosen.frames} frames into {data}",
    )
    reused = (data / "metadata.json").is_file()
    if reused:
        sys.stderr.write(f"gns demo: reusing the dataset in {data}\n")
    else:
        generate(
            preset,
            data,
            n_train,
            n_valid,
            n_test,
            seed=seed,
            workers=workers or os.cpu_count() or 1,
            frames=chosen.frames,
        )
    generate_seconds = time.perf_counter() - t0

    config = demo_config(chosen, chosen.steps)
    state_path = out / "training.json"
    t0 = _phase(
        2,
        f"training a GNS (latent {chosen.latent}, {chosen.message_passing_steps} message-passing "
        f"steps) for at most {chosen.minutes:g} min / {chosen.steps} steps into {run}",
    )
    if state_path.is_file():
        trained = json.loads(state_path.read_text(encoding="utf-8"))
        sys.stderr.write(f"gns demo: training finished earlier (step {trained['step']})\n")
    else:
        found = latest_checkpoint(run)
        if found is not None:
            sys.stderr.write(f"gns demo: resuming the interrupted training from {found.name}\n")
        train(
            data,
            run,
            None if found is not None else config,
            resume=found is not None,
            device=device,
            time_limit=60.0 * chosen.minutes,
        )
        last = latest_checkpoint(run)
        assert last is not None  # train always writes a checkpoint before it returns
        trained = {
            "step": int(load_checkpoint(last)["step"]),
            "seconds": time.perf_counter() - t0,
        }
        write_json_atomic(state_path, trained)

    _phase(3, f"rolling out the {n_test} test trajectories and writing the report")
    checkpoints = ["latest"]
    best = run / "checkpoints" / "best.pt"
    if best.is_file() and int(load_checkpoint(best)["step"]) != trained["step"]:
        checkpoints.insert(0, "best")
    notes = [
        f"`gns demo` size {size!r}: {n_train} train / {n_valid} valid / {n_test} test "
        f"trajectories of preset {preset!r} (seed {seed}), {chosen.frames} frames each, "
        "dataset "
        + ("reused from an earlier run" if reused else f"generated in {generate_seconds:.0f} s"),
        f"GNS latent {chosen.latent}, {chosen.message_passing_steps} message-passing steps, "
        f"noise 1e-4: trained {trained['step']} steps in {trained['seconds'] / 60:.1f} min "
        f"(budget {chosen.minutes:g} min or {chosen.steps} steps); best.pt is the checkpoint "
        "`gns train` keeps as best by validation: rollouts of "
        f"{config.train.validation_rollout_steps} frames, as long as the test rollouts, on "
        f"{min(n_valid, config.train.validation_rollouts)} valid trajectories",
    ]
    result = report(
        run,
        data,
        split="test",
        checkpoints=checkpoints,
        out=out / "report",
        device=device,
        command=command,
        notes=notes,
    )
    sys.stderr.write(
        f"gns demo: done in {(time.perf_counter() - started) / 60:.1f} min; "
        f"open {result.out / 'report.md'}\n"
    )
    return result.out
