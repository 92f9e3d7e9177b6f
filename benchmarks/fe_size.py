"""Size of the FE engine: physical lines and code lines (no blank, comment or docstring lines) per module of fe/,
the oracles and benchmark problems (`--exclude`) listed apart.

    python benchmarks/fe_size.py [--root fe] [--exclude axisymmetric.py,dome.py,balloon.py,trajectory_sets.py]
"""

import argparse
import ast
from pathlib import Path

from rich.console import Console
from rich.table import Table

ORACLES_AND_PROBLEMS = "axisymmetric.py,dome.py,balloon.py,trajectory_sets.py"
"""The independent axisymmetric solution and the benchmark problems built on the engine (not the engine)."""


def docstring_lines(tree: ast.Module) -> set[int]:
    """Line numbers of every string-literal statement (module, class, function and attribute docstrings)."""
    lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            lines.update(range(node.lineno, node.end_lineno + 1))
    return lines


def line_counts(path: Path) -> tuple[int, int]:
    """(physical lines, code lines) of one Python file."""
    source = path.read_text()
    skipped = docstring_lines(ast.parse(source))
    lines = source.splitlines()
    code = sum(
        1
        for number, line in enumerate(lines, 1)
        if line.strip() and not line.strip().startswith("#") and number not in skipped
    )
    return len(lines), code


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", type=Path, default=Path("fe"))
    parser.add_argument("--exclude", default=ORACLES_AND_PROBLEMS)
    args = parser.parse_args()
    excluded = set(args.exclude.split(","))
    table = Table("module", "physical lines", "code lines", "counted")
    totals = [0, 0]
    for path in sorted(args.root.glob("*.py")):
        physical, code = line_counts(path)
        counted = path.name not in excluded
        table.add_row(path.name, str(physical), str(code), "yes" if counted else "no (oracle / problem)")
        if counted:
            totals[0] += physical
            totals[1] += code
    table.add_row("engine total", str(totals[0]), str(totals[1]), "")
    Console().print(table)


if __name__ == "__main__":
    main()
