"""The curated `gns` namespace: every name it promises can be reached."""

import importlib
import subprocess
import sys
from pathlib import Path

import gns
import pytest


def test_every_public_name_resolves():
    # The torch-based names load lazily from the module that defines them: a name whose module
    # moved would only fail when a user first touches it.
    for name in gns.__all__:
        value = getattr(gns, name)
        assert value is not None, name
        if name in gns._LAZY:
            assert value is getattr(importlib.import_module(gns._LAZY[name]), name), name


def test_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="no_such_name"):
        gns.no_such_name  # noqa: B018


def run_fresh(code: str) -> str:
    """stdout of `code` in a new interpreter: attribute access must work without any earlier
    import having bound the submodule (this process has imported most of gns already)."""
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )
    assert done.returncode == 0, done.stderr
    return done.stdout


def test_subpackages_are_attributes_after_a_plain_import_without_torch():
    out = run_fresh(
        "import sys, gns\n"
        # Nothing beyond the Rust core is loaded by `import gns` itself.
        "print(sorted(m for m in ('torch', 'h5py', 'gns.data', 'gns.mpm') if m in sys.modules))\n"
        "print(gns.data.open_dataset.__module__, gns.data.write_dataset.__module__)\n"
        "print(gns.mpm.simulate.__module__, gns.metrics.__name__)\n"
        "print('torch' in sys.modules)\n"
        # The torch-based modules come on first touch like the rest.
        "print(gns.rollout.rollout.__module__, gns.checkpoints.load_simulator.__module__)\n"
    )
    assert out.splitlines() == [
        "[]",
        "gns.data.dataset gns.data.write",
        "gns.mpm gns.metrics",
        "False",
        "gns.rollout gns.checkpoints",
    ]


def test_every_module_of_the_package_is_an_attribute():
    # gns lists its modules with pkgutil; here they are the files on disk, globbed.
    package = Path(gns.__file__).parent
    on_disk = {p.stem for p in package.glob("*.py") if not p.name.startswith("_")}
    on_disk |= {p.parent.name for p in package.glob("*/__init__.py")}
    assert gns._SUBMODULES == on_disk - {"cli"}
    assert {"data", "metrics", "mpm", "rollout"} <= gns._SUBMODULES <= set(dir(gns))


def test_the_version_has_one_source():
    # Cargo.toml holds it; pyproject.toml takes it from there (dynamic) and gns from the
    # installed metadata, so the three can never disagree.
    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib

    root = Path(__file__).resolve().parents[1]
    cargo = tomllib.loads((root / "Cargo.toml").read_text())["package"]["version"]
    pyproject = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    assert "version" not in pyproject and "version" in pyproject["dynamic"]
    assert gns.__version__ == cargo
