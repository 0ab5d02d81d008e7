"""The README's and the how-tos' code runs as written.

Every ```python block of README.md and docs/*.md runs, in order, in one namespace per document
(as a reader pasting them into one session would), in a fresh folder laid out like a clone
(`configs/` beside it, `../shared` only if this checkout has one). A block whose first line is
`# needs: PATH` runs only when PATH exists there: `../shared...` (data a clone does not ship)
is skipped without it; any other PATH must be one this test knows how to make (NEEDS: e.g. a
run trained for a few steps in place of a documented long `gns train`), so it is never skipped.

For ```bash blocks, which may name long jobs, every `gns SUBCOMMAND` (also `-m gns`) must
exist in `gns --help`, every --flag it uses in that subcommand's --help, a value given to a
flag with listed choices must be one of them, paths into configs/, scripts/ or benches/ must
exist, and a `torch==VERSION` must be the version CI tests (constraints.txt's pin).
"""

from __future__ import annotations

import functools
import re
import shlex
import subprocess
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCUMENTS = ["README.md", *sorted(f"docs/{p.name}" for p in (REPO / "docs").glob("*.md"))]
SHARED = REPO.parent / "shared"
FENCE = re.compile(r"^( *)```(\w*)\s*$")  # indented: a block inside a list item


@dataclass(frozen=True)
class Block:
    document: str
    line: int  # of the block's first line of code (1-based)
    language: str
    text: str

    @property
    def where(self) -> str:
        return f"{self.document}:{self.line}"

    @property
    def needs(self) -> str | None:
        first = self.text.split("\n", 1)[0]
        match = re.match(r"#\s*needs:\s*(\S+)", first)
        return match.group(1).rstrip(",.") if match else None


def code_blocks(document: str, language: str) -> list[Block]:
    blocks: list[Block] = []
    current: list[str] = []
    start, indent, opened = 0, "", None
    for number, line in enumerate((REPO / document).read_text().splitlines(), start=1):
        fence = FENCE.match(line)
        if fence and opened is None:
            indent, opened, current, start = fence.group(1), fence.group(2), [], number + 1
        elif line.strip() == "```" and opened is not None:
            if opened == language:
                blocks.append(Block(document, start, language, "\n".join(current) + "\n"))
            opened = None
        elif opened is not None:
            current.append(line.removeprefix(indent))
    assert opened is None, f"{document}: a code block is not closed"
    return blocks


def test_the_block_parser_finds_the_fences_it_should():
    # An oracle the parser does not share: count the fences with a plain regex.
    text = (REPO / "README.md").read_text()
    assert len(code_blocks("README.md", "python")) == len(re.findall(r"^```python$", text, re.M))
    assert len(code_blocks("README.md", "bash")) == len(re.findall(r"^```bash$", text, re.M))
    block = code_blocks("README.md", "python")[0]
    assert text.splitlines()[block.line - 2] == "```python"


# ----------------------------------------------------------------------------- python blocks


def tiny_splash_run(work: Path) -> None:
    """docs/howto-load-model.md's `gns train --config splash.toml`, 3 steps instead of 3000: the
    same data and settings, so the blocks after it load and roll out a real run folder."""
    from gns.config import load_config
    from gns.train import train

    config = load_config(work / "splash.toml")
    train(work / "data/splash", work / "runs/splash", config, steps=3, device="cpu", progress=False)


# What `# needs: PATH` blocks get when PATH is missing: made here, never skipped.
NEEDS: dict[str, Callable[[Path], None]] = {"runs/splash": tiny_splash_run}


def python_documents() -> list[str]:
    return [d for d in DOCUMENTS if code_blocks(d, "python")]


@pytest.mark.parametrize("document", python_documents())
def test_python_blocks_run_as_written(document, tmp_path, monkeypatch, torch_one_thread):
    work = tmp_path / "gns"
    work.mkdir()
    (work / "configs").symlink_to(REPO / "configs")
    if SHARED.is_dir():
        (tmp_path / "shared").symlink_to(SHARED)
    monkeypatch.chdir(work)
    namespace: dict[str, object] = {"__name__": "__main__"}
    skipped = []
    for block in code_blocks(document, "python"):
        needed = block.needs
        if needed is not None and not (work / needed).exists():
            if needed.startswith("../shared"):
                skipped.append(f"{block.where} needs {needed}")
                continue
            assert needed in NEEDS, f"{block.where}: nothing here makes {needed}"
            NEEDS[needed](work)
            assert (work / needed).exists(), f"{block.where}: {needed} was not made"
        # Padded so that a traceback's line numbers are the document's.
        code = compile("\n" * (block.line - 1) + block.text, document, "exec")
        exec(code, namespace)
    if skipped:
        pytest.skip("; ".join(skipped))


# ------------------------------------------------------------------------------- toml blocks


@pytest.mark.parametrize(
    "block",
    [b for d in DOCUMENTS for b in code_blocks(d, "toml")],
    ids=lambda b: b.where,
)
def test_toml_blocks_are_settings_gns_accepts(block, tmp_path):
    from gns.config import load_config

    (tmp_path / "settings.toml").write_text(block.text)
    load_config(tmp_path / "settings.toml")  # unknown keys and bad values are errors


# ------------------------------------------------------------------------------- bash blocks


HELP_SCRIPT = """
import contextlib, io, sys
from gns.cli import main

for argv in [[], *([name] for name in sys.argv[1:])]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.suppress(SystemExit):
        main([*argv, "--help"])
    print(f"=== {' '.join(argv)}\\n{out.getvalue()}", end="")
"""


@functools.cache
def all_help() -> dict[tuple[str, ...], str]:
    """`gns --help` and `gns SUBCOMMAND --help` for every subcommand, from one fresh process
    (the same parser the `gns` script runs, without a process per subcommand)."""

    def run(*names: str) -> str:
        done = subprocess.run(
            [sys.executable, "-c", HELP_SCRIPT, *names],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        return done.stdout

    top = run().split("\n", 1)[1]
    listed = re.search(r"\{([\w,-]+)\}", top)
    assert listed, top
    names = listed.group(1).split(",")
    sections = run(*names).split("=== ")[1:]
    texts = {tuple(s.split("\n", 1)[0].split()): s.split("\n", 1)[1] for s in sections}
    assert set(texts) == {(), *((n,) for n in names)}, texts.keys()
    return texts


def gns_help(*subcommand: str) -> str:
    return all_help()[subcommand]


def subcommands() -> set[str]:
    return {names[0] for names in all_help() if names}


def flags_and_choices(help_text: str) -> tuple[set[str], dict[str, set[str]]]:
    flags = set(re.findall(r"(?<![\w-])--[a-z][\w-]*", help_text))
    choices = {
        flag: set(values.split(","))
        for flag, values in re.findall(r"(--[a-z][\w-]*) \{([\w,.-]+)\}", help_text)
    }
    return flags, choices


def commands(text: str) -> list[list[str]]:
    """The commands of a bash block as token lists: continuation lines joined, comments
    dropped, `&&`, `||`, `;` and `|` separating commands."""
    joined = re.sub(r"\\\n", " ", text)
    out: list[list[str]] = []
    for line in joined.splitlines():
        current: list[str] = []
        for token in shlex.split(line, comments=True):
            if token in ("&&", "||", ";", "|"):
                out.append(current)
                current = []
            else:
                current.append(token)
        out.append(current)
    return [c for c in out if c]


def gns_arguments(command: list[str]) -> list[str] | None:
    """What follows `gns` (or `-m gns`) in a command, or None when it does not run gns."""
    if command[0] == "gns":
        return command[1:]
    for i in range(len(command) - 2):
        if command[i] == "-m" and command[i + 1] == "gns":
            return command[i + 2 :]
    return None


def check_gns(arguments: list[str]) -> list[str]:
    problems = []
    # "[--frame-stride K]" marks an optional part in the README: the brackets are not the flag.
    tokens = [t.strip("[]") for t in arguments]
    subcommand: tuple[str, ...] = ()
    if tokens and not tokens[0].startswith("-"):
        if tokens[0] not in subcommands():
            return [f"`gns {tokens[0]}` is not a subcommand of `gns --help`"]
        subcommand = (tokens[0],)
    flags, choices = flags_and_choices(gns_help(*subcommand))
    name = " ".join(("gns", *subcommand))
    for i, token in enumerate(tokens):
        if not token.startswith("--"):
            continue
        flag, _, value = token.partition("=")
        if flag not in flags:
            problems.append(f"`{name}` has no {flag} (its --help lists {sorted(flags)})")
            continue
        if flag in choices:
            value = value or (tokens[i + 1] if i + 1 < len(tokens) else "")
            # "deepmind|npz|h5" in prose lists alternatives: each must be a choice.
            bad = [v for v in value.split("|") if v not in choices[flag]]
            if bad:
                problems.append(f"`{name} {flag}` takes {sorted(choices[flag])}, not {bad}")
    return problems


def torch_pin() -> str:
    """constraints.txt's torch==VERSION: the one CI installs (pyproject.toml holds a range)."""
    lines = (REPO / "constraints.txt").read_text().splitlines()
    (pin,) = [line.split("#")[0].strip() for line in lines if line.startswith("torch==")]
    return pin


def check_command(command: list[str]) -> list[str]:
    problems = []
    arguments = gns_arguments(command)
    if arguments is not None:
        problems.extend(check_gns(arguments))
    for token in command:
        path = token.partition("=")[2] if token.startswith("--") else token
        if re.match(r"(configs|scripts|benches)/", path) and not (REPO / path).exists():
            problems.append(f"{path} does not exist in the repository")
        if token.startswith("torch==") and token != torch_pin():
            problems.append(f"{token} is not constraints.txt's {torch_pin()}")
    return problems


def bash_documents() -> list[str]:
    return [d for d in DOCUMENTS if code_blocks(d, "bash")]


@pytest.mark.parametrize("document", bash_documents())
def test_bash_blocks_name_real_commands_and_flags(document):
    problems = []
    for block in code_blocks(document, "bash"):
        for command in commands(block.text):
            problems.extend(f"{block.where}: {p}" for p in check_command(command))
    assert problems == []


@pytest.mark.parametrize(
    ("line", "problem"),
    [
        pytest.param("gns trian --data d", "`gns trian` is not a subcommand", id="subcommand"),
        pytest.param("gns train --data d --epochs 3", "`gns train` has no --epochs", id="flag"),
        pytest.param(
            "torchrun --nproc_per_node 2 -m gns rollout --run r --dat d",
            "has no --dat",
            id="torchrun",
        ),
        pytest.param(
            "pip install . && gns convert a b --to deepmind|zarr", "not ['zarr']", id="choices"
        ),
        pytest.param(
            "gns eval --run r \\\n    --data d [--nope]", "`gns eval` has no --nope", id="continued"
        ),
        pytest.param(
            "gns train --config configs/missing.toml", "missing.toml does not exist", id="path"
        ),
        pytest.param(
            "pip install torch==1.0.0 --index-url x",
            "torch==1.0.0 is not constraints.txt's",
            id="pin",
        ),
    ],
)
def test_the_bash_checks_catch_what_they_should(line, problem):
    found = [p for command in commands(line) for p in check_command(command)]
    assert any(problem in p for p in found), found


def test_the_bash_checks_pass_correct_commands():
    line = "gns convert a b --to h5 [--frame-stride 3] && gns demo --size tiny --out=x  # note"
    assert [p for command in commands(line) for p in check_command(command)] == []
