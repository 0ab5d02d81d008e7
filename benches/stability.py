"""Numerical stability and robustness under bad input, layer by layer: one row per case.

    python benches/stability.py            # every case (a few minutes; includes 1M particles)
    python benches/stability.py --quick    # the fast, deterministic part (what CI runs)
    python benches/stability.py --only mpm # cases whose layer or name contains the text

Each case runs in a child process of its own with a time limit and a memory limit, so that a crash
(a signal), a hang or a runaway allocation is a failed row, not the end of the run. A case
passes when what happened is what should happen: a finite, correct answer, or a ValueError that
names the problem. The table says what was tried, what happened, and pass or fail.
"""

from __future__ import annotations

import argparse
import faulthandler
import json
import math
import os
import resource
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gns
import numpy as np

MEMORY_LIMIT = 6 << 30  # bytes of address space per case


@dataclass(frozen=True)
class Case:
    layer: str
    name: str
    tried: str
    run: Callable[[], str]  # returns what happened; raises (AssertionError, ...) on failure
    quick: bool = True
    timeout: float = 60.0


def refused(fn: Callable[[], object], match: str, error: type[Exception] = ValueError) -> str:
    """Runs fn, which must raise `error` whose message contains `match`; returns the message."""
    try:
        fn()
    except error as e:
        message = str(e)
        assert match in message, f"{error.__name__} without {match!r}: {message}"
        return f"{error.__name__}: {message[:110]}"
    raise AssertionError(f"no {error.__name__} (expected one mentioning {match!r})")


def scipy_pairs(x: np.ndarray, r: float) -> set[tuple[int, int]]:
    """Every directed pair within r, self included: the independent oracle."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(x).query_pairs(r, output_type="ndarray")
    both = np.concatenate([pairs, pairs[:, ::-1], np.repeat(np.arange(len(x)), 2).reshape(-1, 2)])
    return set(map(tuple, both.tolist()))


def edge_set(edges: np.ndarray) -> set[tuple[int, int]]:
    return set(zip(edges[0].tolist(), edges[1].tolist(), strict=True))


# ------------------------------------------------------------------------------ core geometry


def million_particles() -> str:
    rng = np.random.default_rng(0)
    n = 1_000_000
    x = rng.random((n, 3))
    r = (14 * 3 / (4 * math.pi * n)) ** (1 / 3)
    t = time.perf_counter()
    edges = gns.radius_graph(x, r)
    seconds = time.perf_counter() - t
    from scipy.spatial import cKDTree

    expected = 2 * len(cKDTree(x).query_pairs(r, output_type="ndarray")) + n
    assert edges.shape == (2, expected), (edges.shape, expected)
    return f"{expected:,} edges in {seconds:.2f} s, the same count as scipy"


def one_point() -> str:
    x = np.zeros((100_000, 2))
    t = time.perf_counter()
    message = refused(lambda: gns.radius_graph(x, 0.1), "max_edges")
    seconds = time.perf_counter() - t
    assert seconds < 10, f"took {seconds:.1f} s to refuse"
    return f"{message} (after {seconds:.2f} s)"


def far_outliers() -> str:
    rng = np.random.default_rng(1)
    x = rng.random((5000, 2))
    x[::100] *= 1e6  # 1% of the particles at up to 10^6 box lengths
    got = gns.radius_graph(x, 0.02)
    assert edge_set(got) == scipy_pairs(x, 0.02)
    return f"{got.shape[1]:,} edges, equal to scipy's; grid not blown up"


def exactly_at_the_radius() -> str:
    found = []
    for dtype in (np.float32, np.float64):
        # Distances of exactly 0.5 and 0.5 + 1 ulp: the first pair is in, the second out.
        x = np.array([[0.0, 0.0], [0.5, 0.0], [2.0, 0.0], [2.0, 0.0]], dtype)
        x[3, 1] = np.nextafter(dtype(0.5), dtype(1.0))
        edges = edge_set(gns.radius_graph(x, 0.5, self_edges=False))
        assert edges == {(0, 1), (1, 0)}, (dtype.__name__, edges)
        found.append(dtype.__name__)
    return f"pair at exactly R kept, pair 1 ulp beyond dropped ({', '.join(found)})"


def duplicates() -> str:
    rng = np.random.default_rng(2)
    x = np.repeat(rng.random((200, 3)), 3, axis=0)  # every position three times
    got = gns.radius_graph(x, 0.05)
    assert edge_set(got) == scipy_pairs(x, 0.05)
    twins = sum(1 for s, r in edge_set(got) if s != r and (x[s] == x[r]).all())
    assert twins == 200 * 6
    return f"{got.shape[1]:,} edges equal to scipy's; every coincident pair linked both ways"


def tiny_inputs() -> str:
    for n in (0, 1):
        x = np.zeros((n, 2))
        edges = gns.radius_graph(x, 0.1)
        assert edges.shape == (2, n) and (edges == 0).all()
        walls = gns.wall_features(x, ((0.0, 1.0), (0.0, 1.0)), 0.1)
        assert walls.shape == (n, 4)
        position, velocity = gns.euler_step(x, x, x)
        assert position.shape == velocity.shape == (n, 2)
        segment = gns.Obstacle.polyline([[0.0, 0.0], [1.0, 0.0]])
        assert gns.obstacle_features(x, [segment], 0.1).shape[0] == n
    return "N = 0 and N = 1 through radius_graph, wall_features, obstacle_features, euler_step"


def periodic_minimum_width() -> str:
    rng = np.random.default_rng(3)
    r = 0.25
    x = rng.random((300, 2))
    edges = gns.radius_graph(x, r, box=[2 * r, 1.0], periodic=[True, False], self_edges=False)
    # Oracle: minimum-image distances, brute force.
    d = x[None] - x[:, None]
    d[..., 0] -= np.round(d[..., 0] / (2 * r)) * 2 * r
    expected = {
        (int(s), int(t)) for t, s in zip(*np.nonzero((d**2).sum(-1) <= r * r), strict=True)
    } - {(i, i) for i in range(300)}
    assert edge_set(edges) == expected
    message = refused(
        lambda: gns.radius_graph(x, r, box=[2 * r * 0.999, 1.0], periodic=[True, False]),
        "narrower than 2 * radius",
    )
    return f"box = 2R: {edges.shape[1]:,} edges equal to brute force; narrower: {message[:60]}"


TESTS = Path(__file__).resolve().parents[1] / "tests"


def pytest_passes(shown: str, *tests: str, **env: str) -> str:
    """Runs tests of tests/ (file or file::name) in a child pytest; they must all pass, and
    then `shown` (what they assert) is what happened. The training and fuzz cases live there,
    where CI runs them, so they are written once."""
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:warnings", "-p", "no:cacheprovider"]
    t = time.perf_counter()
    done = subprocess.run(
        [*command, *(str(TESTS / test) for test in tests)],
        cwd=TESTS.parent,
        env={**os.environ, "OMP_NUM_THREADS": "1", **env},
        capture_output=True,
        text=True,
    )
    summary = (done.stdout.strip().splitlines() or ["no output"])[-1]
    assert done.returncode == 0, f"{summary}\n{done.stdout[-3000:]}{done.stderr[-2000:]}"
    return f"{shown} ({summary.strip('= ')}, {time.perf_counter() - t:.0f} s)"


def fuzz_core() -> str:
    """tests/test_fuzz.py with 2000 random (not the CI's derandomized 150) examples per
    function: every answer checked against numpy, ValueError exactly for invalid input."""
    return pytest_passes(
        "2000 examples per function: every result equal to the numpy oracle, ValueError "
        "exactly for the invalid inputs, no panic or hang",
        "test_fuzz.py",
        GNS_FUZZ_EXAMPLES="2000",
    )


# ------------------------------------------------------------------- integrator and rollouts


def huge_accelerations() -> str:
    x = np.zeros((4, 2))
    message = refused(lambda: gns.euler_step(x, x, np.full((4, 2), 1e308), dt=10.0), "overflows")
    big = gns.euler_step(x, x, np.full((4, 2), 1e30))
    assert np.isfinite(big[0]).all()
    return f"1e30 integrates to finite values; overflow: {message[:70]}"


def _tiny_simulator(bounds=((0.1, 0.9), (0.1, 0.9))):
    import torch
    from gns.config import Config, ModelConfig, NormalizationConfig
    from gns.data.metadata import Metadata
    from gns.simulator import LearnedSimulator, Scene

    torch.manual_seed(0)
    torch.set_num_threads(1)
    scene = Scene(dim=2, radius=0.1, particle_types=(5,), bounds=bounds, walls=True)
    config = Config(
        model=ModelConfig(latent_size=8, mlp_hidden_size=8, message_passing_steps=2),
        normalization=NormalizationConfig(source="metadata"),
    )
    # Statistics of a plausible flow, so that the untrained model moves particles by about
    # acc_std per step, as a model early in training does.
    statistics = Metadata(
        bounds=bounds,
        sequence_length=20,
        default_connectivity_radius=0.1,
        dim=2,
        dt=0.0025,
        vel_mean=(1e-4, -2e-4),
        vel_std=(1e-3, 1e-3),
        acc_mean=(0.0, -1e-5),
        acc_std=(1e-4, 1e-4),
    )
    return LearnedSimulator(scene, config, statistics=statistics)


def _drifting(frames: int, n: int = 40):
    from gns.data.trajectory import Trajectory

    rng = np.random.default_rng(5)
    start = rng.uniform(0.3, 0.7, size=(1, n, 2))
    positions = start + np.arange(frames)[:, None, None] * 1e-3
    return Trajectory(
        positions.astype(np.float32), np.full(n, 5), None, None, key=0, source="<drift>"
    )


def model_outputs_nan_or_inf() -> str:
    import torch
    from gns.rollout import RolloutDiverged, rollout

    lines = []
    for value in (float("nan"), float("inf"), 1e30):
        sim = _tiny_simulator()
        torch.nn.init.constant_(sim.model.decoder[-1].bias, value)
        try:
            rollout(sim, _drifting(20))
        except RolloutDiverged as e:
            assert e.step == 0 and len(e.particles) == 40 and e.rollout.num_steps == 0
            lines.append(f"{value:g}: stopped at step {e.step}, {len(e.particles)} particles")
            continue
        raise AssertionError(f"a model output of {value} was not caught")
    return "; ".join(lines)


def long_rollout() -> str:
    """A rollout 10x longer than its trajectory (an untrained model drifts): it either stays
    finite and near the domain for every step or stops at the first step that is not."""
    from gns.rollout import RolloutDiverged, rollout

    traj = _drifting(30)
    steps = 10 * traj.num_frames
    try:
        r = rollout(_tiny_simulator(), traj, num_steps=steps)
    except RolloutDiverged as e:
        assert np.isfinite(e.rollout.predicted_rollout).all()
        return f"stopped at step {e.step} of {steps}: {str(e)[:80]}"
    assert np.isfinite(r.predicted_rollout).all() and r.num_steps == steps
    return f"{steps} steps (10x the trajectory), all finite and within a box length"


def float64_drift() -> str:
    from gns.rollout import rollout

    traj = _drifting(60)
    single = rollout(_tiny_simulator(), traj).predicted_rollout
    double = rollout(_tiny_simulator().double(), traj).predicted_rollout
    drift = np.abs(double - single.astype(np.float64)).max(axis=(1, 2))
    assert double.dtype == np.float64 and np.isfinite(drift).all()
    return f"float32 vs float64 over {len(drift)} steps: max |dx| {drift[0]:.1e} -> {drift[-1]:.1e}"


# ---------------------------------------------------------------------- reference simulator


def _mpm(blocks, frames: int = 20, **settings):
    from gns import mpm

    scene = mpm.MpmScene(blocks=blocks, grid=32, particles_per_cell=2.0, **settings)
    result = mpm.simulate(scene, frames, seed=0)
    x = result.positions
    assert np.isfinite(x).all()
    (x0, x1), (y0, y1) = scene.bounds
    slack = 2 / scene.grid  # particles may sit up to a cell or two past the walls
    assert (x[..., 0] > x0 - slack).all() and (x[..., 0] < x1 + slack).all()
    assert (x[..., 1] > y0 - slack).all() and (x[..., 1] < y1 + slack).all()
    return result


def stiff_materials() -> str:
    from gns.mpm import Block, Goop, Sand, Water

    rows = []
    for stiffness in (1e4, 1e6, 1e8):
        for material in (
            Sand(youngs_modulus=stiffness),
            Goop(youngs_modulus=stiffness),
            Water(bulk_modulus=stiffness),
        ):
            result = _mpm([Block(material, (0.3, 0.3), (0.2, 0.2))])
            rows.append(int(np.max(result.substeps)))
    return f"E (or K) 1e4..1e8 for sand, goop, water: all finite, in the box; substeps {rows}"


def fast_and_cornered() -> str:
    from gns.mpm import Block, Sand, Water

    fast = _mpm([Block(Water(), (0.4, 0.4), (0.1, 0.1), velocity=(40.0, -30.0))])
    corner = _mpm([Block(Sand(), (0.1, 0.1), (0.1, 0.1))], frames=40)
    return (
        f"40 m/s water: up to {int(np.max(fast.substeps))} substeps a frame, stable; sand in "
        f"a corner: {int(np.max(corner.substeps))} substeps, stable"
    )


def time_steps() -> str:
    from gns.mpm import Block, Water

    block = [Block(Water(), (0.4, 0.4), (0.1, 0.1))]
    tiny = _mpm(block, frames=5, frame_dt=1e-7)
    message = refused(lambda: _mpm(block, frames=2, frame_dt=10.0), "substeps")
    bad = refused(lambda: _mpm(block, frames=2, frame_dt=-1.0), "frame_dt")
    return (
        f"frame_dt 1e-7: {int(np.max(tiny.substeps))} substep(s), fine; 10 s: {message[:60]}; "
        f"-1: {bad[:40]}"
    )


# ---------------------------------------------------------------------------------- data


def damaged_files() -> str:
    """Every reader on truncated and byte-flipped copies of a valid file: each read ends in
    a DatasetError (a ValueError naming the file) or reads back; nothing else escapes."""
    from gns.data import open_dataset
    from gns.data.deepmind import write_tfrecord
    from gns.data.h5 import write_h5
    from gns.data.npz import write_npz

    traj = _drifting(8, n=12)
    writers = {
        "train.tfrecord": write_tfrecord,
        "train.npz": write_npz,
        "train.h5": write_h5,
    }
    meta = (
        '{"bounds": [[0.1, 0.9], [0.1, 0.9]], "sequence_length": 7, "dim": 2, '
        '"default_connectivity_radius": 0.015, "dt": 0.0025, "vel_mean": [0, 0], '
        '"vel_std": [1, 1], "acc_mean": [0, 0], "acc_std": [1, 1]}'
    )
    rng = np.random.default_rng(6)
    counts = {"read": 0, "refused": 0}
    with tempfile.TemporaryDirectory() as tmp:
        for name, write in writers.items():
            folder = Path(tmp) / name.replace(".", "_")
            folder.mkdir()
            (folder / "metadata.json").write_text(meta)
            write(folder / name, [traj, traj])
            good = (folder / name).read_bytes()
            for trial in range(60):
                damaged = bytearray(good)
                if trial % 2:
                    damaged = damaged[: int(rng.integers(0, len(good)))]
                else:
                    for _ in range(int(rng.integers(1, 8))):
                        damaged[int(rng.integers(len(damaged)))] ^= 1 << int(rng.integers(8))
                (folder / name).write_bytes(bytes(damaged))
                try:
                    for t in open_dataset(folder, "train"):
                        assert np.isfinite(t.positions).all()
                    counts["read"] += 1
                except ValueError:
                    counts["refused"] += 1
    return (
        f"tfrecord, npz, h5: 180 damaged files, {counts['refused']} refused with a "
        f"ValueError, {counts['read']} read back finite"
    )


# ------------------------------------------------------------------------------------ training

ROBUST = "test_train_robust.py::"


def non_finite_training() -> str:
    return pytest_passes(
        "stopped before the optimizer step, naming the step, the parameters and the batch's "
        "windows; under DDP every rank stops",
        ROBUST + "test_non_finite_loss_or_gradient_stops_before_the_optimizer_step",
        ROBUST + "test_under_ddp_every_rank_stops_at_a_bad_batch_on_one_rank",
    )


def loss_spikes() -> str:
    return pytest_passes(
        "reported with its step, its size against the median and the batch's windows; "
        "training goes on",
        ROBUST + "test_loss_spikes_are_reported_with_their_batch_and_training_goes_on",
    )


def damaged_checkpoints() -> str:
    return pytest_passes(
        "each refused on load, naming the file and the problem (torch.load alone reads the "
        "bit flip); resume falls back to the newest intact one",
        ROBUST + "test_load_checkpoint_detects_truncated_corrupted_and_incomplete_files",
        ROBUST + "test_resume_falls_back_past_a_corrupted_newest_checkpoint",
    )


def killed_and_resumed() -> str:
    return pytest_passes(
        "every checkpoint intact; resumed from the newest, ends bit for bit equal to an "
        "uninterrupted run",
        ROBUST + "test_a_run_killed_at_a_random_moment_resumes_exactly",
    )


CASES = [
    Case("core", "1M particles", "3D, 1M uniform points, ~14 neighbours", million_particles, False),
    Case("core", "one point", "1e5 particles all at one point", one_point),
    Case("core", "far outliers", "1% of particles at 1e6 box lengths", far_outliers),
    Case("core", "exact radius", "pairs exactly at R in f32 and f64", exactly_at_the_radius),
    Case("core", "duplicates", "every position three times", duplicates),
    Case("core", "N = 0, 1", "empty and single-particle inputs everywhere", tiny_inputs),
    Case(
        "core", "periodic 2R", "periodic box exactly 2R wide, and narrower", periodic_minimum_width
    ),
    Case(
        "core",
        "fuzz",
        "hypothesis: random arrays and scalars through every public function",
        fuzz_core,
        quick=False,  # CI runs tests/test_fuzz.py itself
        timeout=900,
    ),
    Case(
        "integrator", "huge accelerations", "euler_step with 1e30 and overflow", huge_accelerations
    ),
    Case(
        "rollout", "NaN / Inf / 1e30 out", "model outputs NaN, Inf, 1e30", model_outputs_nan_or_inf
    ),
    Case("rollout", "10x longer", "untrained model, 10x the trajectory length", long_rollout),
    Case("rollout", "float64", "the same rollout in float32 and float64", float64_drift),
    Case("mpm", "stiff", "E from 1e4 to 1e8, three materials", stiff_materials, timeout=180),
    Case("mpm", "fast, corner", "40 m/s block; block in a corner", fast_and_cornered, timeout=120),
    Case("mpm", "time steps", "frame_dt 1e-7, 10 s and -1", time_steps),
    Case("data", "damaged files", "truncated and bit-flipped files, every reader", damaged_files),
    # The training rows run tests/test_train_robust.py, which CI runs itself: not quick.
    Case(
        "training",
        "non-finite",
        "a NaN loss, a NaN gradient; a bad batch on one of 2 DDP ranks",
        non_finite_training,
        quick=False,
        timeout=300,
    ),
    Case("training", "loss spike", "a loss 1000x its median", loss_spikes, False, 120),
    Case(
        "training",
        "damaged checkpoints",
        "truncated, bit-flipped, empty, incomplete checkpoints; resume past them",
        damaged_checkpoints,
        quick=False,
        timeout=300,
    ),
    Case(
        "training",
        "kill -9",
        "training killed at a random step, then --resume",
        killed_and_resumed,
        quick=False,
        timeout=300,
    ),
]


# ------------------------------------------------------------------------------------ driver


def _self_test_cases() -> list[Case]:
    """Cases that must fail, for the driver's own test: a crash, a hang, a missing error."""

    def crash() -> str:
        os.kill(os.getpid(), signal.SIGSEGV)
        return ""

    return [
        Case("self-test", "crash", "", crash),
        Case("self-test", "hang", "", lambda: str(time.sleep(60)), timeout=2.0),
        Case("self-test", "wrong", "", lambda: refused(lambda: None, "x")),
    ]


def _cases(self_test: bool) -> list[Case]:
    return _self_test_cases() if self_test else CASES


def _child(index: int, self_test: bool) -> None:
    """Runs one case in this (fresh) process and prints its outcome as one JSON line."""
    # A crash is reported by the parent from the exit signal; no traceback dump from here.
    faulthandler.disable()
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))
    try:
        outcome = (True, _cases(self_test)[index].run())
    except BaseException as e:  # noqa: BLE001 - every failure becomes the row's text
        last = traceback.extract_tb(e.__traceback__)[-1]
        outcome = (False, f"{type(e).__name__}: {e} ({Path(last.filename).name}:{last.lineno})")
    print(RESULT + json.dumps(outcome), flush=True)


RESULT = "stability-result: "


def run_case(index: int, self_test: bool = False) -> tuple[bool, str, float]:
    """(passed, what happened, seconds) of case `index`, run in a fresh Python process. Not a
    fork: a forked child of a process that has used the Rust core inherits a thread pool whose
    threads do not exist in the child, and its first parallel call would wait forever."""
    case = _cases(self_test)[index]
    command = [sys.executable, __file__, "--case", str(index)]
    if self_test:
        command.append("--self-test")
    started = time.perf_counter()
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=case.timeout)
    except subprocess.TimeoutExpired:
        return False, f"hung: no answer within {case.timeout:g} s", case.timeout
    seconds = time.perf_counter() - started
    if done.returncode < 0:
        return False, f"crashed: signal {-done.returncode}", seconds
    lines = [x for x in done.stdout.splitlines() if x.startswith(RESULT)]
    if not lines:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        return False, f"crashed: exit status {done.returncode}: {tail}", seconds
    passed, happened = json.loads(lines[-1][len(RESULT) :])
    return bool(passed), str(happened), seconds


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="only the fast, deterministic part")
    parser.add_argument("--only", help="cases whose layer or name contains this text")
    parser.add_argument("--case", type=int, help=argparse.SUPPRESS)  # the child's side
    parser.add_argument("--self-test", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.case is not None:
        _child(args.case, args.self_test)
        return 0
    chosen = [
        i
        for i, c in enumerate(CASES)
        if (c.quick or not args.quick)
        and (not args.only or args.only in c.layer or args.only in c.name)
    ]
    print("| layer | case | tried | what happened | result | s |")
    print("|---|---|---|---|---|---|")
    failed = 0
    for i in chosen:
        passed, happened, seconds = run_case(i)
        failed += not passed
        c = CASES[i]
        text = happened.replace("|", "/").replace("\n", " ")
        verdict = "pass" if passed else "FAIL"
        print(f"| {c.layer} | {c.name} | {c.tried} | {text} | {verdict} | {seconds:.1f} |")
        sys.stdout.flush()
    print(f"\n{len(chosen) - failed} of {len(chosen)} cases pass ({os.cpu_count()} cores).")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
