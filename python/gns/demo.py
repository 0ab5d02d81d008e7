"""`gns demo`: the whole job on a built-in scene, from nothing to a report, on this machine.

    demo("demo")   # OUT/data, OUT/finetune, OUT/scratch, OUT/report/report.md

1. generate  a small dataset with the reference simulator (gns.mpm.generate; resumes by itself),
             by default of the `sand-taichi` preset: the scenes of the shipped sand2d-taichi
             model (SHIPPED_FOR_PRESET)
2. train     (a) the shipped model, fine-tuned on the generated train split for a bounded
             wall-clock time (`gns train --init-from`, which validates the shipped weights first,
             as step 0), and (b) a small GNS from scratch for as long, both validated on every
             valid trajectory over whole rollouts as long as the test rollouts. A preset
             without a shipped model gets (b) alone, with both budgets.
3. report    rollouts of the held-out test trajectories by the shipped model, its fine-tuning
             and the model from scratch, against the simulator at native and cheaper settings
             and the two baselines (gns.report), into OUT/report/. The headline, the row the
             report's conclusion speaks of, is chosen on validation, never on the test split
             (`headline`).

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

__all__ = ["SHIPPED_FOR_PRESET", "SIZES", "DemoSize", "demo", "demo_config", "finetune_config"]

# The preset whose scenes a shipped model was trained on (models/NAME/README.md, its card).
SHIPPED_FOR_PRESET = {"sand-taichi": "sand2d-taichi"}


@dataclass(frozen=True)
class DemoSize:
    """How big a demo is: trajectories per split (train, valid, test), frames per trajectory
    (frame 0 included; None: the preset's own), the GNS trained from scratch (latent and MLP
    width, message-passing steps), the training budgets (minutes of wall-clock time for the
    fine-tuning and for the model from scratch, and a cap on gradient steps for each) and the
    validation cadence in steps."""

    trajectories: tuple[int, int, int]
    frames: int | None
    latent: int
    message_passing_steps: int
    minutes: float
    scratch_minutes: float
    steps: int
    validate_every: int


SIZES: dict[str, DemoSize] = {
    # For tests: seconds in all; nothing is learnt, every output file is still made.
    "tiny": DemoSize((2, 1, 1), 30, 8, 1, 1.0, 1.0, 4, 2),
    # The default: 8-9 minutes on an idle 2-core CPU, 12 with a core busy (docs/demo-runs.md).
    "small": DemoSize((8, 4, 4), None, 32, 3, 3.0, 2.0, 100_000, 250),
    "medium": DemoSize((40, 4, 4), None, 64, 5, 15.0, 15.0, 1_000_000, 1000),
    # The paper's model (latent 128, 10 steps) from scratch; hours on a CPU.
    "large": DemoSize((100, 10, 10), None, 128, 10, 60.0, 180.0, 10_000_000, 5000),
}


def _validation(size: DemoSize, rollout_steps: int, n_valid: int) -> dict[str, Any]:
    """The demo's validation settings: whole rollouts (as long as the test rollouts) of every
    valid trajectory, so that best.pt, which the report rolls out on the test split over the
    same length, is chosen on something that means as much. A model chosen on 50-frame
    rollouts was seen to beat the others there and then diverge on the 155 frames of the test
    rollouts (issue 22); one chosen on 2 trajectories was an early checkpoint that merely
    stayed in the box (issue 41)."""
    return {
        "log_every": min(100, size.steps),
        "validate_every": size.validate_every,
        "validation_windows": 64,
        "validation_rollouts": n_valid,
        "validation_rollout_steps": rollout_steps,
        "checkpoint_every": size.validate_every,
        "keep_checkpoints": 2,
    }


def demo_config(size: DemoSize, steps: int, rollout_steps: int, n_valid: int) -> Any:
    """The GNS trained from scratch: the paper's model at the size's width and depth, noise
    1e-4 (the paper's 3e-4 is about the per-frame acceleration std of the generated sand, and
    less noise learns faster in a short budget), learning rate 4e-4 decaying 10x over 20000
    steps, validated as _validation says."""
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
            **_validation(size, rollout_steps, n_valid),
        ),
    )


# The demo's fine-tuning rate, capped by the shipped model's own last stage (finetune_config).
FINETUNE_LEARNING_RATE = 5e-5


def finetune_rate(shipped: Any) -> float:
    """FINETUNE_LEARNING_RATE, or the shipped model's (gns.config.Config) last-stage rate where
    that is lower."""
    return min(FINETUNE_LEARNING_RATE, shipped.train.learning_rate)


def finetune_config(
    shipped: Any, size: DemoSize, steps: int, rollout_steps: int, n_valid: int
) -> Any:
    """The fine-tuning of a shipped model (its gns.config.Config `shipped`): its own model,
    scene and noise, and its last stage's training (models/NAME/finetune.toml for
    sand2d-taichi: pushforward, mirroring), at FINETUNE_LEARNING_RATE or its last stage's own
    rate where that is lower, decaying tenfold over 2000 steps, validated as _validation says.
    Never faster than the last stage: a higher rate undoes what the model learnt there
    (docs/sand-ablation.md, session 37)."""
    rate = finetune_rate(shipped)
    train = dataclasses.replace(
        shipped.train,
        steps=steps,
        learning_rate=rate,
        learning_rate_final=rate / 10,
        learning_rate_decay_steps=2000,
        **_validation(size, rollout_steps, n_valid),
    )
    return dataclasses.replace(shipped, train=train)


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


def _train_once(
    name: str,
    out: Path,
    run: Path,
    data: Path,
    config: Any,
    minutes: float,
    *,
    valid_data: Path,
    init_from: str | None,
    device: str,
) -> dict[str, Any]:
    """Train `run` once for at most `minutes` (resuming an interrupted training, keeping a
    finished one: OUT/NAME.json records it). Returns {"step", "seconds"} of the last step."""
    from gns.checkpoints import latest_checkpoint, load_checkpoint
    from gns.train import train

    state_path = out / f"{name}.json"
    if state_path.is_file():
        trained = json.loads(state_path.read_text(encoding="utf-8"))
        sys.stderr.write(f"gns demo: {name} finished earlier (step {trained['step']})\n")
        return dict(trained)
    t0 = time.perf_counter()
    found = latest_checkpoint(run)
    if found is not None:
        sys.stderr.write(f"gns demo: resuming the interrupted {name} from {found.name}\n")
    train(
        data,
        run,
        None if found is not None else config,
        resume=found is not None,
        device=device,
        time_limit=60.0 * minutes,
        valid_data=valid_data,
        init_from=None if found is not None else init_from,
    )
    last = latest_checkpoint(run)
    assert last is not None  # train always writes a checkpoint before it returns
    trained = {"step": int(load_checkpoint(last)["step"]), "seconds": time.perf_counter() - t0}
    write_json_atomic(state_path, trained)
    return trained


def _validated(run: Path) -> list[dict[str, float]]:
    """valid.csv of a run: one dict per validation (step, rollout_mse, ...)."""
    import csv

    with open(run / "valid.csv", newline="", encoding="utf-8") as f:
        return [{k: float(v) for k, v in row.items()} for row in csv.DictReader(f)]


def headline(candidates: list[dict[str, Any]]) -> int:
    """The index of the candidate ({"label", "record"}: best.pt's {"step", "value", "in_box"})
    that validated best: inside the box first, then the lowest validation rollout MSE
    (gns.validation.validation_rank); the first of equals."""
    from gns.validation import validation_rank

    return min(range(len(candidates)), key=lambda k: validation_rank(candidates[k]["record"]))


def demo(
    out: str | os.PathLike[str] = "demo",
    *,
    preset: str = "sand-taichi",
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

    size: one of SIZES; train_minutes (each training's), steps, trajectories (train, valid,
    test) and frames override its values. The test split is what the report rolls out.
    """
    from gns.checkpoints import choose_checkpoint, load_checkpoint, model_location
    from gns.config import Config, ModelConfig, from_dict
    from gns.data.convert import convert
    from gns.data.stride import frame_stride, frames_at_stride
    from gns.device import resolve_device
    from gns.mpm.generate import PRESETS, generate
    from gns.mpm.presets import preset_scene
    from gns.report import report
    from gns.validation import better_validation

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
        chosen = dataclasses.replace(
            chosen, minutes=float(train_minutes), scratch_minutes=float(train_minutes)
        )
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
    scene, preset_frames = preset_scene(preset, seed)[:2]
    n_frames = chosen.frames or preset_frames
    # A shipped model steps over `stride` of the preset's frames; every row must (gns.report).
    shipped_name = SHIPPED_FOR_PRESET.get(preset)
    shipped_path = shipped = shipped_scene = None
    stride = 1
    if shipped_name is not None:
        shipped_path = choose_checkpoint(model_location(shipped_name))
        state = load_checkpoint(shipped_path)
        shipped, shipped_scene = from_dict(Config, state["config"]), state["scene"]
        stride = frame_stride(shipped_scene["dt"], scene.frame_dt)
    # The input frames (C + 1) of every row: the shipped model's, and the scratch model's
    # (demo_config keeps ModelConfig's default C).
    history = (shipped.model if shipped is not None else ModelConfig()).velocity_history + 1
    # Every row (gns.report) and every training window (gns convert) reads each phase of the
    # stride as a trajectory of frames_at_stride frames; the fine-tuning's windows hold the
    # frames its pushforward rolls over too.
    rollout_steps = frames_at_stride(n_frames, stride) - history
    needed = 2 if shipped is None else shipped.train.extra_frames + 1
    if rollout_steps < needed:
        raise ValueError(
            f"frames must leave at least {needed} steps after the {history} input frames at "
            f"{stride} frames a step, got {n_frames}"
        )
    out = Path(out)
    arguments = {"preset": preset, "seed": seed, **dataclasses.asdict(chosen)}
    arguments["trajectories"] = list(chosen.trajectories)
    _arguments(out, arguments)
    data, strided = out / "data", out / f"data-stride{stride}"
    started = time.perf_counter()

    n_train, n_valid, n_test = chosen.trajectories
    t0 = _phase(
        1,
        f"generating {preset}: {n_train}/{n_valid}/{n_test} trajectories of "
        f"{n_frames} frames into {data}",
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
            frames=n_frames,
        )
    train_data = data
    if stride > 1:
        # Training windows at the shipped model's step (`gns convert --frame-stride`);
        # validation takes every stride-th frame of OUT/data itself.
        if not (strided / "metadata.json").is_file():
            convert(data, strided, "deepmind", splits=["train"], frame_stride=stride)
        train_data = strided
    generate_seconds = time.perf_counter() - t0

    scratch_minutes = chosen.scratch_minutes + (chosen.minutes if shipped is None else 0.0)
    t0 = _phase(
        2,
        "training: "
        + ("" if shipped is None else f"{shipped_name} fine-tuned for {chosen.minutes:g} min, ")
        + f"a GNS (latent {chosen.latent}, {chosen.message_passing_steps} message-passing "
        f"steps) from scratch for {scratch_minutes:g} min (at most {chosen.steps} steps each) "
        f"into {out}",
    )
    # Rows of the report: {"label", "path" (checkpoint file), "record" (its validation, as
    # best.pt's "best", or None when it was not chosen by one)}.
    rows: list[dict[str, Any]] = []
    trained: dict[str, dict[str, Any]] = {}
    if shipped is not None:
        config = finetune_config(shipped, chosen, chosen.steps, rollout_steps, n_valid)
        trained["finetune"] = _train_once(
            "finetune",
            out,
            out / "finetune",
            train_data,
            config,
            chosen.minutes,
            valid_data=data,
            init_from=shipped_name,
            device=device,
        )
        # Step 0 of the fine-tuning is the shipped model's own validation (gns.train).
        first = _validated(out / "finetune")[0]
        record = {"step": 0, **(better_validation(first, None, shipped_scene["radius"]) or {})}
        rows.append({"label": f"shipped {shipped_name}", "path": shipped_path, "record": record})
        best = load_checkpoint(out / "finetune" / "checkpoints" / "best.pt")["best"]
        if best["step"] == 0:  # no fine-tuned checkpoint beat it: show the last one, unchosen
            tuned = choose_checkpoint(out / "finetune", "latest")
            rows.append({"label": "fine-tuned, no better on valid", "path": tuned, "record": None})
        else:
            tuned = out / "finetune" / "checkpoints" / "best.pt"
            rows.append({"label": "fine-tuned", "path": tuned, "record": best})
    config = demo_config(chosen, chosen.steps, rollout_steps, n_valid)
    trained["scratch"] = _train_once(
        "scratch",
        out,
        out / "scratch",
        train_data,
        config,
        scratch_minutes,
        valid_data=data,
        init_from=None,
        device=device,
    )
    scratch = choose_checkpoint(out / "scratch")
    record = load_checkpoint(scratch).get("best") if scratch.name == "best.pt" else None
    rows.append({"label": "from scratch", "path": scratch, "record": record})
    train_seconds = time.perf_counter() - t0

    _phase(3, f"rolling out the {n_test} test trajectories and writing the report")
    validated = [r for r in rows if r["record"] is not None]
    lead = rows.index(validated[headline(validated)]) if validated else len(rows) - 1
    rows.insert(0, rows.pop(lead))  # the headline leads the table
    notes = [
        f"`gns demo` size {size!r}: {n_train} train / {n_valid} valid / {n_test} test "
        f"trajectories of preset {preset!r} (seed {seed}), {n_frames} frames each, dataset "
        + ("reused from an earlier run" if reused else f"generated in {generate_seconds:.0f} s"),
        *_training_notes(
            trained,
            chosen,
            shipped_name,
            None if shipped is None else finetune_rate(shipped),
            scratch_minutes,
        ),
        _headline_note(rows, n_valid, rollout_steps, stride),
    ]
    result = report(
        out,
        data,
        split="test",
        checkpoints=[str(r["path"]) for r in rows],
        labels=[r["label"] for r in rows],
        headline=0,
        out=out / "report",
        device=device,
        command=command,
        notes=notes,
    )
    sys.stderr.write(
        f"gns demo: done in {(time.perf_counter() - started) / 60:.1f} min "
        f"(training {train_seconds / 60:.1f}); open {result.out / 'report.md'}\n"
    )
    return result.out


def _training_notes(
    trained: dict[str, dict[str, Any]],
    size: DemoSize,
    shipped: str | None,
    rate: float | None,
    scratch_minutes: float,
) -> list[str]:
    notes = []
    if "finetune" in trained:
        t = trained["finetune"]
        notes.append(
            f"Fine-tuning: the shipped {shipped} (`gns train --init-from {shipped}`, its last "
            f"stage's recipe at learning rate {rate:g}) for {t['step']} steps in "
            f"{t['seconds'] / 60:.1f} min (budget {size.minutes:g} min or {size.steps} steps)"
        )
    t = trained["scratch"]
    notes.append(
        f"From scratch: GNS latent {size.latent}, {size.message_passing_steps} message-passing "
        f"steps, noise 1e-4, {t['step']} steps in {t['seconds'] / 60:.1f} min (budget "
        f"{scratch_minutes:g} min or {size.steps} steps)"
    )
    return notes


def _headline_note(rows: list[dict[str, Any]], n_valid: int, steps: int, stride: int) -> str:
    """How the headline (rows[0]) was chosen, with every candidate's validation."""
    scored = [
        f"{r['label']} {r['record']['value']:.3g}"
        + ("" if r["record"]["in_box"] else " (left the box)")
        + (f" at step {r['record']['step']}" if r["record"]["step"] else "")
        for r in rows
        if r["record"] is not None
    ]
    if not scored:
        return (
            f"Headline: {rows[0]['label']}, the only learned row; it was never validated "
            "(its training ended before the first validation)"
        )
    return (
        f"Headline (the row the conclusion speaks of): {rows[0]['label']}, the best on the "
        f"valid split, never on test: rollouts of all {n_valid} valid trajectories over "
        f"{steps} steps{f' of {stride} frames' if stride > 1 else ''}, inside the box first, "
        "then the lowest MSE. Validation rollout MSE: " + "; ".join(scored)
    )
