"""The core install (no torch, no PARDISO/MKL, no Ray) runs everything but the learned models, quietly.

Each check runs in a fresh interpreter in which the optional packages cannot be imported: a
``sys.meta_path`` finder refuses them, as on a machine where `pip install biotac-twin` left them out.
"""

import json
import pkgutil
import subprocess
import sys
import tomllib
from importlib.metadata import version
from pathlib import Path

from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
OPTIONAL = ("torch", "pypardiso", "ray")
"""Top-level packages that only the extras install."""
LEARN_EXTRA_MODULES = {
    "learn.checkpoint",
    "learn.dataset",
    "learn.experiment",
    "learn.forward",
    "learn.nets",
    "learn.train",
}
"""The learned models: the only modules allowed to need torch."""
CORE_PACKAGES = ("assets", "fe", "twin", "learn", "hardware")

BLOCKER = f"""
import importlib.abc
import sys


class _Refuse(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {OPTIONAL!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}} (not in the core install)", name=name)
        return None


sys.meta_path.insert(0, _Refuse())
"""


def _run(code: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-c", BLOCKER + code], cwd=ROOT, capture_output=True, text=True, timeout=timeout
    )


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def test_every_core_module_imports_without_the_extras() -> None:
    packages = ", ".join(repr(p) for p in CORE_PACKAGES)
    code = f"""
import importlib, json, pkgutil, traceback
failed = {{}}
for package in ({packages}):
    root = importlib.import_module(package)
    for info in pkgutil.walk_packages(root.__path__, package + "."):
        if info.name in {LEARN_EXTRA_MODULES!r} or info.name.endswith(".__main__"):
            continue
        try:
            importlib.import_module(info.name)
        except Exception:
            failed[info.name] = traceback.format_exc(limit=1)
print(json.dumps({{"failed": failed, "loaded": sorted(m for m in sys.modules if m.split(".")[0] in {OPTIONAL!r})}}))
"""
    result = _run(code)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["failed"] == {}
    assert report["loaded"] == []


def test_blocker_refuses_torch() -> None:
    """The check above means something: torch is installed here, and the finder hides it."""
    result = _run("import torch")
    assert result.returncode != 0 and "not in the core install" in result.stderr


def test_learn_without_torch_names_the_install_line() -> None:
    code = "from twin.cli import app\napp(['learn', 'train', 'missing.hdf5'], prog_name='twin')"
    result = _run(code)
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and 'pip install "biotac-twin[learn]"' in lines[0]
    assert "Traceback" not in result.stderr


def test_core_dependencies_leave_out_the_extras() -> None:
    project = _pyproject()["project"]
    core = {Requirement(r).name for r in project["dependencies"]}
    assert core.isdisjoint({"torch", "pypardiso", "ray", "mkl"})
    extras = project["optional-dependencies"]
    assert [str(Requirement(r).specifier) for r in extras["learn"]] == ["==2.13.0"]
    dev = [Requirement(r) for r in extras["dev"]]
    assert any(r.name == "biotac-twin" and {"learn", "pardiso", "ray"} <= r.extras for r in dev)
    assert {"pytest", "ruff"} <= {r.name for r in dev}


def test_pardiso_only_on_x86_64() -> None:
    (req,) = [Requirement(r) for r in _pyproject()["project"]["optional-dependencies"]["pardiso"]]
    assert req.name == "pypardiso"
    for machine, wanted in (("x86_64", True), ("AMD64", True), ("aarch64", False), ("arm64", False)):
        assert req.marker.evaluate({"platform_machine": machine}) is wanted, machine


def test_bounded_packages_admit_the_versions_tested_here_and_not_the_next_major() -> None:
    requirements = {Requirement(r).name: Requirement(r) for r in _pyproject()["project"]["dependencies"]}
    for name in ("mujoco", "rerun-sdk", "warp-lang"):
        spec = requirements[name].specifier
        installed = version(name)
        assert spec.contains(installed), (name, installed, spec)
        major, minor = (int(p) for p in installed.split(".")[:2])
        breaking = f"{major}.{minor + 1}.0" if major == 0 else f"{major + 1}.0.0"
        assert not spec.contains(breaking), (name, breaking, spec)


def test_cpu_machine_prints_no_cuda_warning() -> None:
    """Warp on a machine without the CUDA driver: a tiny CPU run of fe's warp set-up stays quiet."""
    code = """
import fe.wptypes
import warp as wp
a = wp.zeros(4, dtype=wp.float64, device="cpu")
print(float(a.numpy().sum()))
"""
    result = _run(code)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "0.0"
    assert "CUDA" not in result.stderr


def test_modules_walked_are_the_ones_on_disk() -> None:
    """The import check walks real packages: each has modules, and the learn-extra list names real ones."""
    on_disk = {info.name for p in CORE_PACKAGES for info in pkgutil.walk_packages([str(ROOT / p)], p + ".")}
    assert LEARN_EXTRA_MODULES <= on_disk
    assert len(on_disk - LEARN_EXTRA_MODULES) > 50
