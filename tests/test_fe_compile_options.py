"""Every fe/ module that defines warp kernels compiles them without adjoints (issue 18's cold start: nothing
differentiates the FE's kernels, and the adjoints were most of the compile time, benchmarks/compile_bench.py)."""

import importlib
from pathlib import Path

import pytest
import warp as wp

FE = Path(__file__).resolve().parents[1] / "fe"
KERNEL_MODULES = [f"fe.{p.stem}" for p in sorted(FE.glob("*.py")) if "@wp.kernel" in p.read_text()]


def test_the_fe_has_kernel_modules_to_check():
    assert {"fe.membrane", "fe.contact", "fe.device_solver"} <= set(KERNEL_MODULES)


@pytest.mark.parametrize("name", KERNEL_MODULES)
def test_kernel_module_generates_no_adjoints(name):
    module = importlib.import_module(name)
    assert wp.get_module(module.__name__).options["enable_backward"] is False
