"""The wheel works where there is no Rust: install it into a fresh environment and use it.

    python scripts/check_wheel.py [WHEEL]      # default: the one dist/gns-*.whl

scripts/build-wheel makes the wheel; scripts/test runs both. Checked here:
- the wheel's tag: the stable ABI for every CPython >= 3.10 (cp310-abi3), a manylinux platform
  on Linux, one extension module (gns/_core.abi3.so) without symbols or debug info, and the
  shipped model inside;
- installed alone (pip --no-deps --no-index) into a new virtual environment that sees this
  Python's packages (--system-site-packages: torch, numpy and scipy come from here, nothing is
  downloaded), and run from an empty folder with PYTHONPATH unset and no cargo or rustc on
  PATH: `import gns` is the wheel's, not an editable checkout's; a radius graph against brute
  force; a few rollout steps of the shipped model sand2d-taichi (a block of sand at rest on
  the floor stays there); and the `gns` command's --help.
"""

from __future__ import annotations

import argparse
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOOLS = ("cargo", "rustc")

# Run by the environment's Python, from an empty folder: argv[1] is the environment.
INSIDE = r"""
import importlib.metadata
import shutil
import sys
import time
from pathlib import Path

import numpy as np

venv = Path(sys.argv[1]).resolve()
start = time.perf_counter()
for tool in ("cargo", "rustc"):
    assert shutil.which(tool) is None, f"{tool} is on PATH: {shutil.which(tool)}"

import gns
import gns._core

for module in (gns, gns._core):
    where = Path(module.__file__).resolve()
    assert where.is_relative_to(venv), f"{module.__name__} is {where}, not the wheel's in {venv}"
dist = importlib.metadata.distribution("gns")
assert Path(dist.locate_file("gns/__init__.py")).resolve() == Path(gns.__file__).resolve()
(tag,) = [line[5:] for line in dist.read_text("WHEEL").splitlines() if line.startswith("Tag: ")]
assert tag.startswith("cp310-abi3-"), tag
assert gns.__version__ == dist.version, (gns.__version__, dist.version)
print(f"  gns {gns.__version__} from {Path(gns.__file__).parent} ({tag})")

# A radius graph against brute force: every pair within the radius, sorted by receiver.
x = np.random.default_rng(0).random((500, 2))
edges = gns.radius_graph(x, 0.08)
receivers, senders = np.nonzero(np.linalg.norm(x[:, None] - x[None], axis=-1) <= 0.08)
assert edges.dtype == np.int64 and np.array_equal(edges, np.stack([senders, receivers]))
print(f"  radius_graph: {edges.shape[1]} edges, as brute force finds them")

# The shipped model: a block of sand at rest on the floor, 6 frames given, 5 predicted.
import torch
from gns.data import Trajectory
from gns.mpm import lattice
from gns.rollout import rollout

torch.set_num_threads(1)
simulator = gns.load_simulator("sand2d-taichi")
spacing, side, steps = 1 / 128, 12, 5
floor = simulator.scene.bounds[1][0]
block = lattice((0.5, floor), (side * spacing, side * spacing), spacing)  # lowest row at s/2
frames = simulator.config.model.velocity_history + 1 + steps
positions = np.repeat(block[None], frames, axis=0)
context = np.full((frames, 1), np.tan(np.radians(30.0)))  # sand2d-taichi's friction context
result = rollout(simulator, Trajectory(positions, np.full(len(block), 6), step_context=context))
predicted = result.predicted_rollout
assert predicted.shape == (steps, len(block), 2), predicted.shape
assert np.isfinite(predicted).all()
moved = float(np.abs(predicted - block).max())
assert moved < spacing, f"a block at rest moved {moved:.3g} in {steps} steps"
print(f"  sand2d-taichi: {steps} steps of {len(block)} particles at rest, moved <= {moved:.2g}")
print(f"  inside the environment: {time.perf_counter() - start:.1f} s")
"""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("wheel", nargs="?", type=Path, help="default: the one dist/gns-*.whl")
    return parser.parse_args(argv)


def find_wheel(given: Path | None) -> Path:
    if given is not None:
        return given.resolve()
    found = sorted((REPO / "dist").glob("gns-*.whl"))
    if len(found) != 1:
        sys.exit(f"expected one dist/gns-*.whl (scripts/build-wheel makes it), found {found}")
    return found[0]


def elf_sections(data: bytes) -> list[str] | None:
    """The section names of a 64-bit little-endian ELF file; None for anything else."""
    if data[:6] != b"\x7fELF\x02\x01":
        return None
    (shoff,) = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    (strings,) = struct.unpack_from("<Q", data, shoff + shstrndx * shentsize + 0x18)
    names = []
    for i in range(shnum):
        (offset,) = struct.unpack_from("<I", data, shoff + i * shentsize)
        names.append(data[strings + offset : data.index(b"\0", strings + offset)].decode())
    return names


def check_contents(wheel: Path) -> str:
    """The wheel's tag, after checking its name, tag and files."""
    name, version, python, abi, platform = wheel.name.removesuffix(".whl").split("-")
    assert name == "gns" and (python, abi) == ("cp310", "abi3"), wheel.name
    if sys.platform.startswith("linux"):
        assert platform.startswith("manylinux"), f"{platform}: not a manylinux platform tag"
    with zipfile.ZipFile(wheel) as archive:
        files = archive.namelist()
        tags = archive.read(f"gns-{version}.dist-info/WHEEL").decode().splitlines()
        extensions = [f for f in files if f.startswith("gns/_core") and f.endswith((".so", ".pyd"))]
        assert len(extensions) == 1, f"one extension module expected, found {extensions}"
        assert extensions[0] in ("gns/_core.abi3.so", "gns/_core.pyd"), extensions
        sections = elf_sections(archive.read(extensions[0]))
    assert f"Tag: {python}-{abi}-{platform}" in tags, tags
    needed = ["gns/__init__.py", "gns/_core.pyi", "gns/models/sand2d-taichi/model.pt"]
    assert set(needed) <= set(files), sorted(set(needed) - set(files))
    if sections is not None:
        extra = [s for s in sections if s == ".symtab" or s.startswith(".debug")]
        assert not extra, f"{extensions[0]} is not stripped: it has {extra}"
    return f"{python}-{abi}-{platform}"


def without_tools(path: str) -> str:
    """PATH less every folder that holds cargo or rustc."""
    folders = [p for p in path.split(os.pathsep) if p]
    return os.pathsep.join(p for p in folders if not any(shutil.which(t, path=p) for t in TOOLS))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    start = time.perf_counter()
    wheel = find_wheel(args.wheel)
    tag = check_contents(wheel)
    print(f"wheel: {wheel.name}, {wheel.stat().st_size / 1e6:.2f} MB, tag {tag}")
    with tempfile.TemporaryDirectory(prefix="gns-wheel-") as tmp:
        venv, empty = Path(tmp) / "venv", Path(tmp) / "empty"
        empty.mkdir()
        # No pip of its own: the environment sees this Python's (system site-packages).
        subprocess.run(
            [sys.executable, "-m", "venv", "--system-site-packages", "--without-pip", venv],
            check=True,
        )
        bin_dir = venv / ("Scripts" if os.name == "nt" else "bin")
        python = bin_dir / ("python.exe" if os.name == "nt" else "python")
        env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
        env["VIRTUAL_ENV"] = str(venv)
        env["PATH"] = os.pathsep.join([str(bin_dir), without_tools(os.environ.get("PATH", ""))])
        # --ignore-installed: an editable gns in this Python is left alone, not replaced.
        install = ["-m", "pip", "install", "--quiet", "--no-deps", "--no-index"]
        install += ["--ignore-installed", "--disable-pip-version-check", str(wheel)]
        subprocess.run([python, *install], check=True, env=env, cwd=empty)
        subprocess.run([python, "-c", INSIDE, venv], check=True, env=env, cwd=empty)
        command = shutil.which("gns", path=env["PATH"])
        assert command is not None and Path(command).parent == bin_dir, command
        done = subprocess.run(
            [command, "--help"], capture_output=True, text=True, env=env, cwd=empty, check=True
        )
        assert done.stdout.startswith("usage: gns"), done.stdout[:200]
        print(f"  gns --help: {len(done.stdout.splitlines())} lines from {command}")
    print(f"wheel check: ok in {time.perf_counter() - start:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
