"""Checkpoints: plain dicts written atomically with torch.save, verified before they are used.

A step_*.pt holds everything an exact resume needs (RESUME_KEYS); best.pt only what a rollout
needs (WEIGHTS_KEYS). This module writes, verifies, finds and loads them; the training loop
(gns.train) decides what goes into them.

A model folder holds one model.pt (WEIGHTS_KEYS, written by `export_model`) beside its card.
The package ships trained ones in gns/models/NAME (SHIPPED_MODELS), loadable by name:

    gns.load_simulator("sand2d-taichi")
"""

from __future__ import annotations

import copy
import os
import sys
import zipfile
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from gns.config import MODEL_SECTIONS, Config, from_dict
from gns.device import resolve_device
from gns.files import atomic_file
from gns.simulator import LearnedSimulator, Scene

__all__ = [
    "CHECKPOINT_FORMAT",
    "READABLE_FORMATS",
    "RESUME_KEYS",
    "WEIGHTS_KEYS",
    "MODEL_FILE",
    "SHIPPED_MODELS",
    "choose_checkpoint",
    "export_model",
    "is_of_run",
    "latest_checkpoint",
    "load_checkpoint",
    "load_simulator",
    "model_location",
    "recorded_checkpoint",
    "remove_stale_temporaries",
    "resume_checkpoint",
    "run_folder",
    "save_checkpoint",
    "shipped_models",
    "simulator_from_checkpoint",
    "statistics_dict",
]

CHECKPOINT_FORMAT = "gns-checkpoint-3"
# Formats load_checkpoint reads. 1: before the scene recorded the training data's frame spacing
# (Scene.dt); such a model loads with frame_dt None and reads every frame, as it did. 2: before
# the scene had obstacle features (Scene.obstacles, obstacle_clip); it loads without them. New
# checkpoints say 3, so that an older gns refuses them with a message rather than failing on
# the scene's unknown entry.
READABLE_FORMATS = ("gns-checkpoint-1", "gns-checkpoint-2", CHECKPOINT_FORMAT)
# What load_simulator needs (best.pt holds only these), and what an exact resume needs too.
WEIGHTS_KEYS = ("format", "step", "config", "scene", "statistics", "model")
RESUME_KEYS = (*WEIGHTS_KEYS, "optimizer", "sampler", "noise_generator")
# The trained models that come with the package, one folder each, and a model folder's weights.
SHIPPED_MODELS = Path(__file__).parent / "models"
MODEL_FILE = "model.pt"


def statistics_dict(metadata: Any) -> dict[str, list[float] | None]:
    """The metadata statistics the simulator was built with, as plain lists for a checkpoint."""
    names = ("vel_mean", "vel_std", "acc_mean", "acc_std", "context_mean", "context_std")
    out: dict[str, list[float] | None] = {}
    for name in names:
        value = getattr(metadata, name, None)
        out[name] = None if value is None else [float(v) for v in np.asarray(value).reshape(-1)]
    return out


def _scene_from_dict(data: dict[str, Any]) -> Scene:
    def tuples(value: Any) -> Any:
        return tuple(tuples(v) for v in value) if isinstance(value, list) else value

    return Scene(**{key: tuples(value) for key, value in data.items()})


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> None:
    """torch.save `state` to `path` atomically (a crash never leaves a half-written file),
    every tensor copied to the CPU: a run trained on a GPU loads on any machine."""
    from torch.utils._pytree import tree_map

    def on_cpu(value: Any) -> Any:
        return value.detach().cpu() if isinstance(value, torch.Tensor) else value

    with atomic_file(path) as tmp:
        torch.save(tree_map(on_cpu, state), tmp)


def _check_archive(path: str | os.PathLike[str]) -> None:
    """ValueError unless `path` is a complete zip archive (torch.save's format) whose members all
    match their CRC-32: torch.load itself notices truncation but reads flipped bytes silently."""
    name = os.fspath(path)
    try:
        size = os.path.getsize(path)
    except OSError as err:
        raise ValueError(f"{name}: cannot read the checkpoint ({err})") from err
    if size == 0:
        raise ValueError(f"{name}: the checkpoint is empty (0 bytes)")
    try:
        with zipfile.ZipFile(path) as archive:
            for info in archive.infolist():
                if info.CRC == 0 and info.file_size:
                    continue  # saved with torch's CRC-32 turned off: nothing to compare
                with archive.open(info) as member:
                    while member.read(1 << 20):
                        pass
    except Exception as err:  # BadZipFile, EOFError, OSError, struct.error, ...
        raise ValueError(
            f"{name}: the checkpoint is truncated or corrupted ({type(err).__name__}: {err})"
        ) from err


def load_checkpoint(path: str | os.PathLike[str], resume: bool = False) -> dict[str, Any]:
    """A checkpoint dict; tensors are loaded on the CPU (weights_only: nothing is executed).

    Verified first: a truncated or corrupted file (every member's CRC-32 is checked), one that
    is not a gns checkpoint, or one without the entries the model needs (`resume`: and those an
    exact resume needs) raises ValueError naming the file and what is wrong."""
    name = os.fspath(path)
    _check_archive(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:
        raise ValueError(f"{name}: not a readable gns checkpoint ({err})") from err
    if not isinstance(state, dict) or state.get("format") not in READABLE_FORMATS:
        found = state.get("format") if isinstance(state, dict) else None
        raise ValueError(
            f"{name}: not a gns checkpoint this version reads (format {found!r}; expected "
            f"{' or '.join(READABLE_FORMATS)})"
        )
    missing = [key for key in (RESUME_KEYS if resume else WEIGHTS_KEYS) if key not in state]
    if missing:
        hint = " (weights only: resume from a step_*.pt)" if resume else ""
        raise ValueError(f"{name}: the checkpoint lacks {', '.join(missing)}{hint}")
    step = state["step"]
    if isinstance(step, bool) or not isinstance(step, int) or step < 0:
        raise ValueError(f"{name}: the checkpoint's step is {step!r}, not a count of steps")
    model = state["model"]
    if not isinstance(model, dict) or not all(isinstance(v, Tensor) for v in model.values()):
        raise ValueError(f"{name}: the checkpoint's model entry is not a dict of tensors")
    return state


def latest_checkpoint(run_dir: str | os.PathLike[str]) -> Path | None:
    """The checkpoint with the highest step in run_dir/checkpoints, or None."""
    folder = Path(run_dir) / "checkpoints"
    found = sorted(folder.glob("step_*.pt")) if folder.is_dir() else []
    return found[-1] if found else None


def resume_checkpoint(run_dir: Path, announce: bool) -> tuple[Path, dict[str, Any]]:
    """The newest intact step_*.pt of run_dir and its contents. A newer one that fails
    verification is skipped with a loud message on stderr (`announce`: this process reports);
    it stays in place and is overwritten when training reaches its step again."""
    folder = run_dir / "checkpoints"
    found = sorted(folder.glob("step_*.pt"), reverse=True) if folder.is_dir() else []
    if not found:
        raise ValueError(f"--resume: no checkpoint in {folder}")
    problems: list[str] = []
    for path in found:
        try:
            state = load_checkpoint(path, resume=True)
        except ValueError as err:
            problems.append(str(err))
            if announce:
                sys.stderr.write(f"WARNING: {err}; skipping it\n")
            continue
        if problems and announce:
            sys.stderr.write(
                f"WARNING: resuming from {path} (step {state['step']}), the newest intact "
                f"checkpoint; {len(problems)} newer one(s) could not be used (above), and the "
                "steps after it are trained again\n"
            )
        return path, state
    raise ValueError(
        f"--resume: no intact checkpoint in {folder}: "
        + "; ".join(problems)
        + ". Delete the corrupted files; with none left, start a new run folder"
    )


def remove_stale_temporaries(run_dir: Path) -> None:
    """Temporary files of atomic writes that a killed run left behind (never read)."""
    for folder in (run_dir, run_dir / "checkpoints"):
        if folder.is_dir():
            for tmp in folder.glob(".*.tmp"):
                tmp.unlink(missing_ok=True)


def shipped_models() -> list[str]:
    """The names of the models that come with the package (SHIPPED_MODELS)."""
    if not SHIPPED_MODELS.is_dir():
        return []
    return sorted(p.name for p in SHIPPED_MODELS.iterdir() if (p / MODEL_FILE).is_file())


def is_model_folder(path: Path) -> bool:
    """A folder with one exported model (model.pt), not a run folder (checkpoints/)."""
    return (path / MODEL_FILE).is_file() and not (path / "checkpoints").is_dir()


def is_of_run(checkpoint: Path, run: Path) -> bool:
    """Whether `checkpoint` is the one `run` names (a checkpoint file, or a model folder's
    model) or, for a run folder, one of its checkpoints."""
    if run.is_file() or is_model_folder(run):
        return checkpoint.resolve() == choose_checkpoint(run).resolve()
    return run.resolve() in checkpoint.resolve().parents


def model_location(text: str | os.PathLike[str]) -> Path:
    """The checkpoint file, run folder or model folder `text` names, or else the shipped model
    of that name."""
    path = Path(text)
    shipped = str(text) in shipped_models()
    # A shipped model's outputs go to ./NAME (see run_folder): that folder, which holds
    # no model, must not hide the model of the same name.
    holds_model = path.is_file() or is_model_folder(path) or (path / "checkpoints").is_dir()
    if path.exists() and (holds_model or not shipped):
        return path
    if shipped:
        return SHIPPED_MODELS / str(text)
    names = ", ".join(shipped_models()) or "none"
    raise ValueError(
        f"no such file or folder: {text}, nor a shipped model of that name (shipped: {names})"
    )


def choose_checkpoint(path: str | os.PathLike[str], which: str = "auto") -> Path:
    """The checkpoint file meant by `path`: the file itself, a model folder's model.pt, or in a
    run folder "latest" (the highest step), "best" (the best validation, see
    gns.validation.better_validation) or "auto" (best when the run has one, otherwise latest)."""
    path = Path(path)
    if not path.is_dir() or is_model_folder(path):
        if which != "auto":
            kind = "model folder" if path.is_dir() else "file"
            raise ValueError(
                f"checkpoint {which!r} picks from a run folder, but {path} is a {kind}"
            )
        return path / MODEL_FILE if path.is_dir() else path
    if which not in ("auto", "best", "latest"):
        raise ValueError(f"checkpoint must be 'auto', 'best' or 'latest', got {which!r}")
    best = path / "checkpoints" / "best.pt"
    if which == "best" or (which == "auto" and best.is_file()):
        if not best.is_file():
            raise ValueError(f"{path}: no {best.name} (the run has not been validated)")
        return best
    found = latest_checkpoint(path)
    if found is None:
        raise ValueError(f"{path}: no checkpoints in {path / 'checkpoints'}")
    return found


def load_simulator(
    path: str | os.PathLike[str], device: str | torch.device = "cpu", checkpoint: str = "auto"
) -> LearnedSimulator:
    """The trained simulator of a checkpoint file, a run folder (see choose_checkpoint), a model
    folder or a shipped model's name (see model_location)."""
    chosen = choose_checkpoint(model_location(path), checkpoint)
    return simulator_from_checkpoint(load_checkpoint(chosen), device)


def export_model(
    run: str | os.PathLike[str],
    out: str | os.PathLike[str],
    checkpoint: str = "auto",
    average: int = 1,
    enforce_walls: bool | None = None,
) -> dict[str, Any]:
    """Write the weights a rollout needs to out/model.pt (out is created; an existing model.pt
    is replaced atomically) and return the state written.

    average: 1 exports the checkpoint `checkpoint` of `run` (see choose_checkpoint); N > 1
    averages the parameters of the run's last N step_*.pt (equal weights), which evens out the
    swings between neighbouring checkpoints; buffers (the normalisation statistics, the scene's
    constants) are the newest checkpoint's. The state records the steps averaged.
    enforce_walls: sets the exported config's scene.enforce_walls (see gns.rollout); None keeps
    the run's."""
    if isinstance(average, bool) or not isinstance(average, int) or average < 1:
        raise ValueError(f"average must be an integer >= 1, got {average!r}")
    run = Path(run)
    if average == 1:
        state = load_checkpoint(choose_checkpoint(run, checkpoint))
        sources = [state]
    else:
        if checkpoint != "auto":
            raise ValueError(f"average={average} takes the last checkpoints; drop {checkpoint!r}")
        found = sorted((run / "checkpoints").glob("step_*.pt")) if run.is_dir() else []
        if len(found) < average:
            raise ValueError(
                f"{run}: average={average} needs {average} step_*.pt checkpoints, "
                f"found {len(found)}"
            )
        sources = [load_checkpoint(path) for path in found[-average:]]
        state = sources[-1]
    exported = {key: state[key] for key in WEIGHTS_KEYS}
    if average > 1:
        for source in sources:
            differs = _model_differences(source, state)
            if differs:
                raise ValueError(
                    f"{run}: the last {average} checkpoints are of different models (step "
                    f"{source['step']} and step {state['step']} differ in {', '.join(differs)})"
                )
        # Which entries are parameters: those of the model the checkpoint builds.
        parameters = {name for name, _ in simulator_from_checkpoint(state).named_parameters()}
        model = dict(state["model"])
        for name in parameters:
            model[name] = torch.stack([s["model"][name] for s in sources]).mean(dim=0)
        exported["model"] = model
        exported["averaged_steps"] = [int(s["step"]) for s in sources]
    if enforce_walls is not None:
        config = copy.deepcopy(exported["config"])
        config["scene"]["enforce_walls"] = bool(enforce_walls)
        exported["config"] = config
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    save_checkpoint(folder / MODEL_FILE, exported)
    return exported


def _model_differences(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """The config's MODEL_SECTIONS (and the checkpoint's "scene") in which two checkpoints'
    models differ: a run resumed with another --steps, say, is still one model."""
    differs = [k for k in MODEL_SECTIONS if a["config"].get(k) != b["config"].get(k)]
    return differs + (["scene"] if a["scene"] != b["scene"] else [])


def simulator_from_checkpoint(
    state: dict[str, Any], device: str | torch.device = "cpu"
) -> LearnedSimulator:
    """The trained simulator of a checkpoint already read by load_checkpoint."""
    statistics = state["statistics"]
    simulator = LearnedSimulator(
        _scene_from_dict(state["scene"]),
        from_dict(Config, state["config"]),
        statistics=None if statistics is None else SimpleNamespace(**statistics),
    )
    simulator.load_state_dict(state["model"])
    return simulator.to(resolve_device(device))


def run_folder(run: Path) -> Path:
    """Where outputs of `--run RUN` go: RUN itself, the folder of a checkpoint file, or for a
    model folder (a shipped model's among them) a folder of its name in the working directory:
    a model's card and weights stay as they were shipped."""
    if run.is_dir() and is_model_folder(run):
        return Path.cwd() / run.name
    return run if run.is_dir() else run.parent


def recorded_checkpoint(recorded: str, run: Path) -> Path:
    """The checkpoint file a rollout's metadata names. `gns rollout` records it absolute; older
    versions recorded it as given, relative to the directory they ran in, which is tried here
    as the working directory and then as the run folder."""
    path = Path(recorded)
    tried = [path] if path.is_absolute() else [path, run_folder(run) / path]
    for candidate in tried:
        if candidate.is_file():
            return candidate
    raise ValueError(
        f"the rollouts were made with checkpoint {recorded}, which is not at "
        f"{' nor at '.join(str(p.absolute()) for p in tried)}; pass --checkpoint latest or best "
        "to use one of --run's"
    )
