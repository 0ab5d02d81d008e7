"""scripts/gpu-stage.sh, the GPU training stage, run end to end on the CPU with a tiny model:
the folder it leaves, and a second stage that resumes the first from that folder alone."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import gns
import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "gpu-stage.sh"
TINY = """
[model]
latent_size = 8
mlp_hidden_size = 8
message_passing_steps = 1
[train]
steps = 1000000
validate_every = 10
validation_windows = 4
validation_rollouts = 1
validation_rollout_steps = 6
checkpoint_every = 10
"""

pytestmark = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


def stage(tmp: Path, out: str, *extra: str) -> subprocess.CompletedProcess[str]:
    command = ["bash", str(SCRIPT), "--out", str(tmp / out), "--config", str(tmp / "tiny.toml")]
    command += ["--valid-data", str(tmp / "data"), "--device", "cpu", *extra]
    env = {**os.environ, "PYTHON": sys.executable}  # the script's gns: this one
    return subprocess.run(command, capture_output=True, text=True, env=env, timeout=600)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("gpu-stage")
    subprocess.run(
        [sys.executable, "-m", "gns", "generate", "--preset", "sand-taichi", "--out",
         str(tmp / "data"), "--n-train", "2", "--n-valid", "1", "--n-test", "1", "--frames",
         "16", "--seed", "0", "--workers", "1"],
        check=True, capture_output=True,
    )  # fmt: skip
    (tmp / "tiny.toml").write_text(TINY)
    return tmp


def test_a_stage_leaves_a_small_folder_that_a_next_stage_resumes(tiny: Path) -> None:
    first = stage(tiny, "first", "--data", str(tiny / "data"), "--minutes", "0.05")
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]
    out = tiny / "first"
    names = {"model.pt", "last.pt", "train.csv", "valid.csv", "eval_test.json", "stage.json"}
    assert {p.name for p in out.iterdir()} == names | {"stage.log"}
    assert sum(p.stat().st_size for p in out.iterdir()) < 2**20  # no rollouts, no data
    facts = json.loads((out / "stage.json").read_text())
    last = torch.load(out / "last.pt", map_location="cpu", weights_only=False)
    assert facts["device"] == "cpu" and facts["steps"] == last["step"] >= 1
    assert facts["windows_seen"] == last["step"] * last["config"]["train"]["batch_size"]
    assert any(c.startswith("gns train") for c in facts["commands"])
    figures = json.loads((out / "eval_test.json").read_text())["mean"]
    assert figures["model"]["finite"] == 1 and figures["model"]["one_step_mse"] > 0
    simulator = gns.load_simulator(out / "model.pt")
    assert simulator.config.model.latent_size == 8

    # Another machine: only the folder travels; the run goes on from its last checkpoint.
    second = stage(tiny, "second", "--data", str(tiny / "data"), "--minutes", "0.05",
                   "--resume-from", str(out / "last.pt"))  # fmt: skip
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    resumed = json.loads((tiny / "second" / "stage.json").read_text())
    assert resumed["steps"] > facts["steps"]
    assert "--resume" in next(c for c in resumed["commands"] if c.startswith("gns train"))


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--minutes", "1", "--generate", "sand-taichi"], "--generate needs --n-train"),
        (["--minutes", "soon", "--data", "x"], "--minutes must be a number of minutes"),
        (["--minutes", "1"], "give --data DIR or --generate"),
        (["--minutes", "1", "--data", "nowhere"], "nowhere does not exist"),
    ],
)
def test_bad_arguments_are_refused_before_any_work(tiny: Path, extra, message) -> None:
    done = stage(tiny, "refused", *extra)
    assert done.returncode == 2 and message in done.stderr
    assert not (tiny / "refused").exists()
