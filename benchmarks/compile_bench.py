"""Cold compile time of the FE's warp kernels (issue 18's "warp compile on a fresh machine"), per module, with
and without adjoint (backward) kernels, both in this process from an empty kernel cache.

    python benchmarks/compile_bench.py [--device cpu|cuda|cuda:0]

Every `fe/` module that defines a `@wp.kernel` is compiled and loaded on the device twice: first with warp's
default of generating each kernel's adjoint (the code before this benchmark's change), then as the package ships
it (`enable_backward` off: nothing differentiates these kernels). The kernel cache is a fresh temporary folder,
so neither run finds the other's binaries (the option is part of each module's hash). Columns: seconds to
build and load each module (warp's code generation + the C++/CUDA compiler), the ratio, and the totals.
"""

import argparse
import importlib
import tempfile
import time
from pathlib import Path

import warp as wp
from rich.console import Console
from rich.table import Table

FE = Path(__file__).resolve().parents[1] / "fe"


def kernel_modules() -> list[str]:
    """Names of the fe modules that define warp kernels, in file order."""
    return [f"fe.{p.stem}" for p in sorted(FE.glob("*.py")) if "@wp.kernel" in p.read_text()]


def compile_seconds(name: str, device: str, backward: bool) -> float:
    """Wall time (s) to generate, compile and load module `name` on `device` with adjoints on or off."""
    module = importlib.import_module(name)
    wp.set_module_options({"enable_backward": backward}, module=module)
    start = time.perf_counter()
    wp.load_module(module, device=device)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="warp device: cpu, cuda, cuda:0, ...")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="warp-cold-") as cache:
        wp.config.kernel_cache_dir = cache
        wp.config.quiet = True
        wp.init()
        try:
            device = wp.get_device(args.device)
        except (ValueError, RuntimeError) as error:
            raise SystemExit(f"compile_bench: no warp device {args.device!r} here ({error})") from None
        names = kernel_modules()
        before = {n: compile_seconds(n, device, backward=True) for n in names}
        after = {n: compile_seconds(n, device, backward=False) for n in names}
    table = Table(title=f"Cold warp compile of fe/ kernels on {device} (warp {wp.config.version})")
    for column in ("module", "with adjoints (s)", "no adjoints (s)", "ratio"):
        table.add_column(column, justify="left" if column == "module" else "right")
    for name in names:
        table.add_row(name, f"{before[name]:.1f}", f"{after[name]:.1f}", f"{before[name] / after[name]:.2f}")
    total_before, total_after = sum(before.values()), sum(after.values())
    table.add_row("total", f"{total_before:.1f}", f"{total_after:.1f}", f"{total_before / total_after:.2f}")
    Console(width=120).print(table)


if __name__ == "__main__":
    main()
