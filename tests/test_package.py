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


def module_imports(root: Path) -> dict[str, set[str]]:
    """Every gns module's imports of other gns modules, at any depth in the file (a lazy import
    inside a function is still a dependency), found with ast, not by importing."""
    import ast

    modules: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        parts = path.relative_to(root.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        found: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                found.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1])
                    base = f"{base}.{node.module}" if node.module else base
                # `from gns.x import y` may import the submodule gns.x.y or a name of gns.x.
                found.update(f"{base}.{a.name}" for a in node.names)
                found.add(base)
        modules[name] = found
    # Keep only imports of gns modules that exist; a name of a module counts as the module.
    return {
        name: {i for i in found if i in modules and i != name} - {"gns"}
        for name, found in modules.items()
    }


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The cycles a depth-first walk of `graph` meets (each as a path back to its start)."""
    cycles: list[list[str]] = []
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(name: str, path: list[str]) -> None:
        state[name] = 1
        for other in sorted(graph.get(name, ())):
            if state.get(other) == 1:
                cycles.append(path[path.index(other) :] + [other])
            elif other not in state:
                visit(other, [*path, other])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])
    return cycles


def test_no_import_cycles_between_modules():
    # The package itself (gns/__init__.py) only maps names to modules, lazily, and the
    # extension (gns._core) has no Python imports: neither can close a cycle that matters.
    graph = module_imports(Path(gns.__file__).parent)
    graph.pop("gns", None)
    assert len(graph) > 40, sorted(graph)  # the walk found the package's modules
    assert import_cycles(graph) == []


def test_the_cycle_check_sees_a_cycle(tmp_path):
    package = tmp_path / "gns"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("def f():\n    from gns.b import g\n")
    (package / "b.py").write_text("from gns import a\n")
    (package / "c.py").write_text("import gns.a\n")
    graph = module_imports(package)
    assert graph == {"gns": set(), "gns.a": {"gns.b"}, "gns.b": {"gns.a"}, "gns.c": {"gns.a"}}
    assert import_cycles(graph) == [["gns.a", "gns.b", "gns.a"]]


def test_the_versions_ci_pins_are_inside_pyproject_ranges():
    # pyproject.toml bounds the dependencies (so a user's torch stays); constraints.txt pins the
    # versions CI installs. A pin outside its range would make `pip install -c` fail, and a
    # range that no longer admits the tested version would promise what was not tested.
    from packaging.requirements import Requirement

    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib

    root = Path(__file__).resolve().parents[1]
    project = tomllib.loads((root / "pyproject.toml").read_text())["project"]
    pins = {}
    for line in (root / "constraints.txt").read_text().splitlines():
        if line.split("#")[0].strip():
            pin = Requirement(line.split("#")[0])
            (spec,) = pin.specifier
            assert spec.operator == "==", line
            pins[pin.name] = spec.version
    ranges = [
        Requirement(r) for r in project["dependencies"] + project["optional-dependencies"]["test"]
    ]
    ranged = {r.name: r for r in ranges if r.marker is None}  # tomli: Python 3.10 only
    # Every dependency of gns and of its tests is pinned, within its range.
    assert set(ranged) <= set(pins), sorted(set(ranged) - set(pins))
    for name, requirement in ranged.items():
        assert requirement.specifier.contains(pins[name]), (name, pins[name])
        # A lower bound, and no exact pin: the range must let an installed version stay.
        assert any(s.operator == ">=" for s in requirement.specifier), requirement
        assert not any(s.operator == "==" for s in requirement.specifier), requirement
