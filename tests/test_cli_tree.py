"""The `twin` command tree is the one README.md and docs/*.md name: every command they name exists, and every
command the CLI has is named there (README and the docs are the contract of the CLI's commands); the tree is
built without loading a solver, so `twin --help` answers at once."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import typer

from twin.cli import app

ROOT = Path(__file__).resolve().parents[1]
WORD = re.compile(r"[a-z][a-z-]*")


def cli_commands() -> set[tuple[str, ...]]:
    """(command,) for each top-level command and group, (group, command) for each command of a group."""
    root = typer.main.get_command(app)
    context = typer.Context(root)
    found: set[tuple[str, ...]] = set()
    for name in root.list_commands(context):
        found.add((name,))
        command = root.get_command(context, name)
        if hasattr(command, "list_commands"):
            found |= {(name, sub) for sub in command.list_commands(typer.Context(command))}
    return found


def named_commands(text: str, groups: set[str]) -> set[tuple[str, ...]]:
    """The commands a Markdown text names in code spans `twin CMD ...` and `twin GROUP SUB[|SUB...] ...`
    (alternatives split by `|`, escaped or spaced as in tables and prose)."""
    named: set[tuple[str, ...]] = set()
    for span in re.findall(r"`twin ([^`]+)`", text):
        tokens = re.sub(r"\s*\\?\|\s*", "|", span).split()
        if not WORD.fullmatch(tokens[0]):
            continue
        named.add((tokens[0],))
        if tokens[0] in groups and len(tokens) > 1:
            named |= {(tokens[0], sub) for sub in tokens[1].split("|") if WORD.fullmatch(sub)}
    return named


def _docs_text() -> str:
    return "\n".join(p.read_text() for p in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))])


def test_named_commands_reads_groups_alternatives_and_options() -> None:
    """The reader the two tests below rely on: options, placeholders and prose are not commands."""
    text = "`twin fe indent --depth-mm D`, `twin learn train\\|eval ...`, `twin devices serve | check`, `twin --help`"
    assert named_commands(text, {"fe", "learn", "devices"}) == {
        ("fe",),
        ("fe", "indent"),
        ("learn",),
        ("learn", "train"),
        ("learn", "eval"),
        ("devices",),
        ("devices", "serve"),
        ("devices", "check"),
    }


def test_every_command_the_docs_name_exists() -> None:
    commands = cli_commands()
    groups = {c[0] for c in commands if len(c) == 2}
    missing = named_commands(_docs_text(), groups) - commands
    assert not missing, f"README/docs name commands the CLI does not have: {sorted(missing)}"


def test_every_command_is_named_in_the_docs() -> None:
    commands = cli_commands()
    groups = {c[0] for c in commands if len(c) == 2}
    undocumented = commands - named_commands(_docs_text(), groups)
    assert not undocumented, f"commands neither README.md nor docs/*.md names: {sorted(undocumented)}"


HEAVY = ("fe", "warp", "trimesh", "torch", "scipy", "h5py", "mujoco", "matplotlib", "rerun")
"""Top-level packages that only a command's body may import (the FE and its solvers, learning, files, plots)."""


def test_the_command_tree_loads_no_solver() -> None:
    """`twin --help` in a fresh interpreter: the commands import their heavy modules when they run."""
    code = (
        "import json, sys\nfrom twin.cli import app\n"
        "try:\n    app(['--help'], prog_name='twin')\nexcept SystemExit:\n    pass\n"
        f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & {set(HEAVY)!r})))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert result.returncode == 0, result.stderr
    assert "fe" in result.stdout and "campaign" in result.stdout, "the help lists the commands"
    assert json.loads(result.stdout.strip().splitlines()[-1]) == []
