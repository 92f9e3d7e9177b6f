"""Package edges run one way: assets <- fe <- twin <- cli; learn -> assets/fe; hardware -> twin.backend/assets.

Every `import` and `from ... import` statement of every module of the five packages is read with
`ast` (function-level and TYPE_CHECKING imports included, relative imports resolved) and checked
against the layers of issue 23. The CLI layer is the package `twin/cli/` and `twin/__main__.py`: it may
import anything, and only it may import from the CLI.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("assets", "fe", "twin", "learn", "hardware")
ALLOWED_LAYERS = {
    "assets": {"assets"},
    "fe": {"assets", "fe"},
    "twin": {"assets", "fe", "twin"},
    "learn": {"assets", "fe", "learn"},
    "hardware": {"assets", "hardware"},
    "cli": {"assets", "fe", "twin", "learn", "hardware", "cli"},
}
"""Layer -> the layers its modules may import from."""
SEAMS = {"hardware": {"twin.backend"}}
"""Single modules of a forbidden layer that a layer may import: hardware implements twin.backend's Backend."""
TEMPORARY_ALLOWANCES: dict[tuple[str, str], str] = {}
"""(importing layer or module, imported module) -> why it is tolerated. Nothing else is."""


def module_name(path: Path) -> str:
    """Dotted module name of a source file under ROOT (a package's __init__ is the package)."""
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer(module: str) -> str | None:
    """The layer of a first-party module (None for stdlib and third-party)."""
    parts = module.split(".")
    if parts[0] not in PACKAGES:
        return None
    if parts[0] == "twin" and len(parts) > 1 and parts[1] in ("cli", "__main__"):
        return "cli"
    return parts[0]


def _is_module(name: str) -> bool:
    base = ROOT.joinpath(*name.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def imported_modules(source: str, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, dotted module) of every import in `source` (of `module`), at any depth of the tree.

    `from X import Y` counts as importing X.Y when X.Y is a first-party module, else X.
    """
    found = []
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                found.append((node.lineno, sub if layer(sub) and _is_module(sub) else base))
    return found


def violations(source: str, module: str, is_package: bool = False) -> list[str]:
    """Every import of `source` (the text of `module`) that runs against the layers, as readable lines."""
    here = layer(module)
    bad = []
    for line, target in imported_modules(source, module, is_package):
        there = layer(target)
        if there is None or there in ALLOWED_LAYERS[here] or target in SEAMS.get(here, set()):
            continue
        if (here, target) in TEMPORARY_ALLOWANCES or (module, target) in TEMPORARY_ALLOWANCES:
            continue
        bad.append(f"{module}:{line} ({here}) imports {target} ({there})")
    return bad


def _sources() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def test_no_import_runs_against_the_edges() -> None:
    bad = [v for path in _sources() for v in violations(path.read_text(), module_name(path), path.stem == "__init__")]
    assert bad == [], "\n".join(bad)


def test_the_temporary_allowances_are_still_needed() -> None:
    """An allowance nobody uses any more must go: each one matches at least one import today."""
    used = set()
    for path in _sources():
        module = module_name(path)
        for _, target in imported_modules(path.read_text(), module, path.stem == "__init__"):
            used |= {key for key in TEMPORARY_ALLOWANCES if key in ((layer(module), target), (module, target))}
    assert used == set(TEMPORARY_ALLOWANCES)


@pytest.mark.parametrize(
    ("module", "source", "flagged"),
    [
        ("learn.data", "def f():\n    from twin.dataset import check_campaign_file\n", "twin.dataset"),
        ("learn.data", "from twin.cli import common\n", "twin.cli.common"),
        ("hardware.backend", "import twin.kinematics\n", "twin.kinematics"),
        ("hardware.egm.client", "from ...twin import scene\n", "twin.scene"),
        ("twin.plant", "if True:\n    from hardware.config import HardwareConfig\n", "hardware.config"),
        ("twin.campaign", "from twin.cli.common import guarded\n", "twin.cli.common"),
        ("twin.dataset", "from .cli.campaign import campaign_app\n", "twin.cli.campaign"),
        ("fe.sensor", "from twin.backend import ARMS\n", "twin.backend"),
        ("assets.yumi", "from fe import params\n", "fe.params"),
    ],
)
def test_the_checker_sees_a_violation(module: str, source: str, flagged: str) -> None:
    """The check can fail: nested, relative and `from package import module` edges are all caught."""
    (found,) = violations(source, module)
    assert f"imports {flagged} " in found


@pytest.mark.parametrize(
    ("module", "source"),
    [
        ("hardware.backend", "from twin.backend import ARMS\nfrom assets.yumi import joint_limits\n"),
        ("learn.data", "from assets.biotac import make_biotac\nimport fe.params\nimport numpy\n"),
        ("twin.cli.devices", "from hardware.backend import HardwareBackend\nfrom twin.cli.common import guarded\n"),
        ("twin.cli.campaign", "from .common import campaign_config\nfrom ..campaign import plan_campaign\n"),
        ("twin.__main__", "from twin.cli import app\n"),
        ("twin.scene", "from .kinematics import forward\n"),
    ],
)
def test_the_checker_passes_what_the_edges_allow(module: str, source: str) -> None:
    assert violations(source, module) == []
