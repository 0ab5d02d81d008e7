"""Training under faults: non-finite losses and gradients, loss spikes, corrupted checkpoints,
and a run killed at a random moment (issue 7, training)."""

from __future__ import annotations

import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from gns.checkpoints import load_checkpoint, load_simulator
from gns.config import TrainConfig, load_config
from gns.train import TrainingStep, train
from gns.train_log import SPIKES_SHOWN, Progress, SpikeReport
from test_train import config, make_dataset, parameters, read_csv

pytestmark = pytest.mark.usefixtures("torch_one_thread")


class Faults:
    """Wraps TrainingStep.forward and gns.train.batch_tensors: records each step's batch
    windows and the simulator, and at the chosen step breaks the loss or one gradient."""

    def __init__(self, monkeypatch, kind: str | None = None, at: int = -1, first_step: int = 0):
        import gns.train

        self.kind, self.at, self.step = kind, at, first_step - 1
        self.windows: list[list[str]] = []
        self.simulator = None
        self.poisoned: str | None = None
        original_tensors, original_forward = gns.train.batch_tensors, TrainingStep.forward

        def batch_tensors(batch, device):
            self.step += 1
            pairs = zip(batch.trajectory, batch.start, strict=True)
            self.windows.append([f"{t}:{s}" for t, s in pairs])
            tensors = original_tensors(batch, device)
            if self.kind == "loss" and self.step == self.at:
                tensors["next_position"][0, 0] = float("nan")
            return tensors

        def forward(module, *args, **kwargs):
            self.simulator = module.simulator
            squared_sum, count = original_forward(module, *args, **kwargs)
            if self.step == self.at and self.kind == "gradient":
                # Adds 0 to the loss, but 0 * d sqrt(u)/du at u = 0 is NaN: one parameter's
                # gradient becomes NaN while the loss stays finite.
                name, param = list(module.simulator.named_parameters())[-1]
                self.poisoned = name
                squared_sum = squared_sum + 0.0 * torch.sqrt(0.0 * param.abs()).sum()
            if self.step == self.at and self.kind == "spike":
                # The loss's value 1000 times larger, its gradient unchanged.
                squared_sum = squared_sum + 999.0 * squared_sum.detach()
            return squared_sum, count

        monkeypatch.setattr(gns.train, "batch_tensors", batch_tensors)
        monkeypatch.setattr(TrainingStep, "forward", forward)


# ---------------------------------------------------------------------------------- non-finite


@pytest.mark.parametrize("kind", ["loss", "gradient"])
def test_non_finite_loss_or_gradient_stops_before_the_optimizer_step(tmp_path, monkeypatch, kind):
    data = make_dataset(tmp_path / "data")
    reference = parameters(train(data, tmp_path / "ref", config(4), progress=False))
    faults = Faults(monkeypatch, kind, at=4)
    with pytest.raises(FloatingPointError) as raised:
        train(data, tmp_path / "run", config(6), progress=False)
    message = str(raised.value)
    assert "at step 4 " in message
    # The batch that caused it: its windows (trajectory key:start), in the message.
    batch = faults.windows[4]
    assert f"(trajectory:start) {' '.join(batch)};" in message, message
    if kind == "loss":
        assert "the training loss became nan and the gradient of" in message
        assert "rank" not in message  # one process: no ranks to tell apart
    else:
        assert "loss became" not in message  # the loss itself was finite
        assert f"the gradient of {faults.poisoned} became non-finite" in message
    # Not applied: the model holds exactly the weights after steps 0..3 (Adam would have
    # spread the NaN into them). (The running statistics saw the batch in the forward pass,
    # but training stops, so they are never saved.)
    weights = dict(faults.simulator.named_parameters())
    assert len(weights) > 5
    for key, value in weights.items():
        assert torch.equal(value.detach(), reference[key]), key
    # The last good checkpoint is intact and nothing later was written.
    names = sorted(p.name for p in (tmp_path / "run/checkpoints").iterdir())
    assert names == ["step_000000003.pt"]
    assert load_checkpoint(tmp_path / "run/checkpoints/step_000000003.pt", resume=True)["step"] == 3


def test_the_existing_nan_message_still_names_the_step(tmp_path):
    # An infinite learning rate: step 0 is finite, its update makes every parameter non-finite.
    data = make_dataset(tmp_path / "data")
    with pytest.raises(FloatingPointError, match=r"loss became nan .*at step 1 ") as raised:
        train(data, tmp_path / "run", config(3, learning_rate=float("inf")), progress=False)
    assert "the gradient of" in str(raised.value)


# ---------------------------------------------------------------------------------- spikes


def test_loss_spikes_are_reported_with_their_batch_and_training_goes_on(
    tmp_path, monkeypatch, capsys
):
    data = make_dataset(tmp_path / "data")
    steps, at = 24, 21  # at least 20 earlier steps before the rule applies
    faults = Faults(monkeypatch, "spike", at=at)
    reported = train(data, tmp_path / "run", config(steps, log_every=1), progress=False)
    err = capsys.readouterr().err
    rows = read_csv(tmp_path / "run/spikes.csv")
    assert len(rows) == 1, rows
    row = rows[0]
    losses = {int(r["step"]): float(r["loss"]) for r in read_csv(tmp_path / "run/train.csv")}
    assert sorted(losses) == list(range(1, steps + 1))  # training went on to the end
    # train.csv's step counts steps done: gradient step 21 is row 22.
    assert int(row["step"]) == at + 1
    assert float(row["loss"]) == pytest.approx(losses[at + 1], rel=1e-7)
    earlier = [losses[s] for s in range(1, at + 1)]
    assert float(row["recent_median"]) == pytest.approx(float(np.median(earlier)), rel=1e-6)
    assert float(row["loss"]) > 100 * float(row["recent_median"])
    assert row["windows"] == " ".join(faults.windows[at])
    assert err.count("loss spike at step") == 1
    assert f"loss spike at step {at + 1}:" in err and " ".join(faults.windows[at]) in err

    # spike_factor = 0 turns the check off, and the check never changes the training itself.
    quiet = train(
        data, tmp_path / "off", config(steps, log_every=1, spike_factor=0.0), progress=False
    )
    assert not (tmp_path / "off/spikes.csv").exists()
    assert "loss spike" not in capsys.readouterr().err
    a, b = parameters(reported), parameters(quiet)
    for key in a:
        assert torch.equal(a[key], b[key]), key

    # A resumed run has the recent losses from the checkpoint: the same report.
    monkeypatch.undo()
    train(data, tmp_path / "resumed", config(at - 2, log_every=1), progress=False)
    Faults(monkeypatch, "spike", at=at, first_step=at - 2)
    train(data, tmp_path / "resumed", config(steps, log_every=1), resume=True, progress=False)
    assert read_csv(tmp_path / "resumed/spikes.csv") == rows


def test_many_spikes_print_a_few_lines_then_one_summary_with_the_worst(capsys):
    meter = Progress(100, 0, enabled=False)
    report = SpikeReport(enabled=True, meter=meter)
    factors = [12.0, 30.0, 11.0, 50.0, 15.0, 13.0]  # the worst (50x) comes after the shown ones
    for k, factor in enumerate(factors):
        report.add(10 + k, factor * 2.0, 2.0, 100, f"{k}:0")
    report.summarise(Path("run/spikes.csv"))
    lines = capsys.readouterr().err.strip().splitlines()
    assert [line.split(":")[0] for line in lines[:SPIKES_SHOWN]] == [
        f"loss spike at step {10 + k}" for k in range(SPIKES_SHOWN)
    ]
    assert "further spikes are counted" in lines[SPIKES_SHOWN - 1]
    assert len(lines) == SPIKES_SHOWN + 1  # no line for spikes 4-6, then the summary
    assert lines[-1].startswith(f"{len(factors)} loss spikes this session")
    assert "the worst at step 13: 100, 50.0 times the median" in lines[-1]
    assert "run/spikes.csv" in lines[-1]
    # Ranks other than 0 say nothing.
    quiet = SpikeReport(enabled=False, meter=meter)
    quiet.add(1, 100.0, 1.0, 100, "0:0")
    quiet.summarise(Path("x"))
    assert capsys.readouterr().err == ""


def test_spike_factor_is_zero_or_above_one():
    assert TrainConfig().spike_factor == 10.0
    TrainConfig(spike_factor=0.0)
    TrainConfig(spike_factor=3.0)
    for bad in (0.5, 1.0, -2.0, float("nan")):
        with pytest.raises(ValueError, match="spike_factor"):
            TrainConfig(spike_factor=bad)


# ---------------------------------------------------------------------------------- checkpoints


def test_load_checkpoint_detects_truncated_corrupted_and_incomplete_files(tmp_path):
    data = make_dataset(tmp_path / "data")
    train(data, tmp_path / "run", config(3), progress=False)
    good = tmp_path / "run/checkpoints/step_000000003.pt"
    payload = good.read_bytes()
    state = load_checkpoint(good, resume=True)

    def variant(name: str, content: bytes) -> Path:
        path = tmp_path / name
        path.write_bytes(content)
        return path

    # One weight's bytes inside the file, one of them flipped: torch.load alone reads the wrong
    # number without complaint; the CRC-32 check refuses the file.
    weight = max(state["model"].values(), key=lambda v: v.numel()).numpy()
    where = payload.find(weight.tobytes())
    assert where > 0
    flipped = bytearray(payload)
    flipped[where + 5] ^= 0x40
    flipped_path = variant("flipped.pt", bytes(flipped))
    silently = torch.load(flipped_path, map_location="cpu", weights_only=True)["model"]
    assert any(not torch.equal(silently[k], state["model"][k]) for k in state["model"])
    cases = {
        "flipped.pt": "truncated or corrupted",
        "half.pt": "truncated or corrupted",
        "short.pt": "truncated or corrupted",
        "empty.pt": "empty",
        "text.pt": "truncated or corrupted",
    }
    variant("half.pt", payload[: len(payload) // 2])
    variant("short.pt", payload[:-1])
    variant("empty.pt", b"")
    variant("text.pt", b"step = 3\n")
    for name, problem in cases.items():
        with pytest.raises(ValueError) as raised:
            load_checkpoint(tmp_path / name)
        assert str(raised.value).startswith(f"{tmp_path / name}: ") and problem in str(raised.value)
    # Complete files without the entries that are needed: named.
    weights_only = {k: v for k, v in state.items() if k not in ("optimizer", "sampler")}
    torch.save(weights_only, tmp_path / "weights.pt")
    assert load_checkpoint(tmp_path / "weights.pt")["step"] == 3  # enough for a rollout
    with pytest.raises(ValueError, match="weights.pt: the checkpoint lacks optimizer, sampler"):
        load_checkpoint(tmp_path / "weights.pt", resume=True)
    torch.save({k: v for k, v in state.items() if k != "model"}, tmp_path / "nomodel.pt")
    with pytest.raises(ValueError, match="nomodel.pt: the checkpoint lacks model"):
        load_checkpoint(tmp_path / "nomodel.pt")
    torch.save({**state, "step": -1}, tmp_path / "step.pt")
    with pytest.raises(ValueError, match="step.pt: the checkpoint's step is -1"):
        load_checkpoint(tmp_path / "step.pt")


def test_resume_falls_back_past_a_corrupted_newest_checkpoint(tmp_path, capsys):
    data = make_dataset(tmp_path / "data")
    train(data, tmp_path / "run", config(12), progress=False)
    folder = tmp_path / "run/checkpoints"
    final = parameters(load_simulator(tmp_path / "run"))
    newest = folder / "step_000000012.pt"
    newest.write_bytes(newest.read_bytes()[:-100])  # cut short
    (folder / ".step_000000012.pt.x1y2.tmp").write_bytes(b"half a checkpoint")
    capsys.readouterr()
    resumed = train(data, tmp_path / "run", None, resume=True, progress=False)
    err = capsys.readouterr().err
    assert f"WARNING: {newest}: the checkpoint is truncated or corrupted" in err
    assert f"resuming from {folder / 'step_000000009.pt'} (step 9)" in err
    for key, value in parameters(resumed).items():
        assert torch.equal(value, final[key]), key
    # The corrupted file was written again, the stale temporary removed, the log complete.
    assert load_checkpoint(newest, resume=True)["step"] == 12
    assert sorted(p.name for p in folder.iterdir()) == [
        "step_000000006.pt",
        "step_000000009.pt",
        "step_000000012.pt",
    ]
    steps = [int(r["step"]) for r in read_csv(tmp_path / "run/train.csv")]
    assert steps == [2, 4, 6, 8, 10, 12]

    # Nothing intact left: a clear error naming every file and what to do.
    for path in folder.glob("step_*.pt"):
        path.write_bytes(b"")
    with pytest.raises(ValueError, match="no intact checkpoint") as raised:
        train(data, tmp_path / "run", None, resume=True, progress=False)
    message = str(raised.value)
    for step in (6, 9, 12):
        assert f"{folder / f'step_{step:09d}.pt'}: the checkpoint is empty" in message
    assert "Delete the corrupted files" in message


# ---------------------------------------------------------------------------------- kill -9

KILL_CONFIG = """
[model]
latent_size = 8
mlp_hidden_size = 8
message_passing_steps = 2
precision = "fp32"

[train]
steps = {steps}
log_every = 1
checkpoint_every = 5
keep_checkpoints = 3
validate_every = 0
trajectories_in_memory = 2
learning_rate = 1e-3
"""


def test_a_run_killed_at_a_random_moment_resumes_exactly(tmp_path):
    steps = 50
    data = make_dataset(tmp_path / "data")
    settings = tmp_path / "config.toml"
    settings.write_text(KILL_CONFIG.format(steps=steps))
    seed = int.from_bytes(os.urandom(4), "little")
    kill_after = random.Random(seed).randint(6, 35)  # a train.csv row (one per step)
    why = f"seed {seed}: killed once train.csv reached step {kill_after}"
    run = tmp_path / "run"
    command = [sys.executable, "-m", "gns", "train", "--data", str(data), "--out", str(run)]
    command += ["--threads", "1"]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    process = subprocess.Popen(
        [*command, "--config", str(settings), "--quiet"], env=env, stderr=subprocess.PIPE
    )
    try:
        deadline = time.monotonic() + 120
        log = run / "train.csv"
        while not (log.exists() and log.read_text().count("\n") > kill_after):
            assert process.poll() is None, process.stderr.read().decode()
            assert time.monotonic() < deadline, why
            time.sleep(0.005)
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == -signal.SIGKILL, why
    killed = sorted((run / "checkpoints").glob("step_*.pt"))
    assert killed and killed[-1].name != f"step_{steps:09d}.pt", why
    for path in killed:  # whatever moment the kill came at, no checkpoint is damaged
        load_checkpoint(path, resume=True)
    last = load_checkpoint(killed[-1])["step"]

    reference = train(data, tmp_path / "straight", load_config(settings), progress=False)
    resumed = subprocess.run(
        [*command, "--resume"], env=env, stderr=subprocess.PIPE, text=True, timeout=120
    )
    assert resumed.returncode == 0, resumed.stderr
    # It went on from the newest checkpoint: only the steps after it were lost.
    progress = [line for line in resumed.stderr.splitlines() if line.startswith("step ")]
    assert progress[0].startswith(f"step {last + 1}/{steps} "), (why, progress[:2])
    # Every checkpoint loads, no temporary is left, and the result is bit for bit the same.
    names = sorted(p.name for p in (run / "checkpoints").iterdir())
    assert names == [f"step_{s:09d}.pt" for s in (40, 45, 50)], (why, names)
    for name in names:
        load_checkpoint(run / "checkpoints" / name, resume=True)
    final = parameters(load_simulator(run, checkpoint="latest"))
    for key, value in parameters(reference).items():
        assert torch.equal(final[key], value), (why, key)
    rows, straight = read_csv(run / "train.csv"), read_csv(tmp_path / "straight/train.csv")
    assert [int(r["step"]) for r in rows] == list(range(1, steps + 1)), why
    assert [r["loss"] for r in rows] == [r["loss"] for r in straight], why


# ---------------------------------------------------------------------------------- DDP

DDP_FAULT_SCRIPT = """
import os, sys, torch
torch.set_num_threads(1)
import gns.train
from gns.config import Config, ModelConfig, TrainConfig
rank = int(os.environ["RANK"])
original, calls = gns.train.batch_tensors, [0]
def batch_tensors(batch, device):  # only rank 1's batch of step 2 is bad
    tensors = original(batch, device)
    if calls[0] == 2 and rank == 1:
        tensors["next_position"][0, 0] = float("nan")
    calls[0] += 1
    return tensors
gns.train.batch_tensors = batch_tensors
config = Config(
    model=ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=2),
    train=TrainConfig(steps=6, batch_size=1, log_every=1, checkpoint_every=2,
                      validate_every=0, trajectories_in_memory=2),
)
try:
    gns.train.train(sys.argv[1], sys.argv[2], config, progress=False)
except FloatingPointError as err:
    print(f"rank {rank} stopped: {err}", flush=True)
    sys.exit(3)
"""


def test_under_ddp_every_rank_stops_at_a_bad_batch_on_one_rank(tmp_path):
    data = make_dataset(tmp_path / "data")
    script = tmp_path / "fault.py"
    script.write_text(DDP_FAULT_SCRIPT)
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone"]
    done = subprocess.run(
        [*torchrun, "--nproc_per_node", "2", str(script), str(data), str(tmp_path / "run")],
        env=dict(os.environ, OMP_NUM_THREADS="1"),
        capture_output=True,
        text=True,
        timeout=300,  # a rank left waiting in a collective would hang here
    )
    assert done.returncode != 0
    # The ranks share the pipe and their lines can arrive run together: split on the reports.
    reports = re.split(r"(?=rank \d stopped: )", done.stdout)
    lines = [r.strip() for r in reports if " stopped: " in r]
    assert len(lines) == 2, done.stdout + done.stderr
    for rank, line in enumerate(sorted(lines)):
        assert line.startswith(f"rank {rank} stopped: the training loss became nan"), line
        # Every rank names both ranks' windows.
        assert "rank 0: " in line and "; rank 1: " in line and "at step 2 " in line, line
    # The checkpoint of step 2 is intact, and nothing later was written.
    names = sorted(p.name for p in (tmp_path / "run/checkpoints").iterdir())
    assert names == ["step_000000002.pt"]
    load_checkpoint(tmp_path / "run/checkpoints/step_000000002.pt", resume=True)
