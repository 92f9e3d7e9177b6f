"""CG work per Newton step with and without the warm start of the volume-gradient columns (`BatchedCG`).

Each Newton step of the batched engine solves K u1 = -r and K u2 = grad V per system with block-Jacobi CG (the
GPU's algebra; `linear="cg"` runs it on warp's CPU device too). u2 is a smooth field that block Jacobi converges
slowest on, and the next Newton step barely moves it, so the engine starts it from the system's last u2
(`warm`). This benchmark runs the same presses twice in one process, warm (the engine's default) and cold
(every column from 0, the engine before 2026-11-27), and prints per run the CG iterations of each kind of
column, the sum over solves of the slowest column (what a replayed CUDA graph pays), the Newton rounds, the
wall time and the largest force difference between the runs (N).

    python benchmarks/cg_warm_start.py [--mesh-mm 0.5] [--trajectories 2] [--steps 12] [--device cpu]
"""

from __future__ import annotations

import argparse
import contextlib
import time
from unittest import mock

import numpy as np
from rich.console import Console
from rich.table import Table

from assets.biotac import make_biotac
from fe import device_solver
from fe.batched_runner import run_trajectories
from fe.sensor import BioTacModel
from fe.trajectory_sets import press_travels, random_paths, to_trajectories


def run(skin, trajectories, device: str, warm: bool) -> dict:
    """One run of the presses, counting each CG solve's iterations per column."""
    solves: list[np.ndarray] = []
    solve, init = device_solver.BatchedCG.solve, device_solver.BatchedCG.__init__

    def counted(self, *args, **kwargs):
        x, iterations, state = solve(self, *args, **kwargs)
        solves.append(iterations.copy())
        return x, iterations, state

    def cold(self, *args, warm=None, **kwargs):
        init(self, *args, **kwargs)

    start = time.perf_counter()
    with contextlib.ExitStack() as patches:
        patches.enter_context(mock.patch.object(device_solver.BatchedCG, "solve", counted))
        if not warm:
            patches.enter_context(mock.patch.object(device_solver.BatchedCG, "__init__", cold))
        result = run_trajectories(skin, trajectories, device, slots=len(trajectories), linear="cg")
    half = len(solves[0]) // 2
    u1 = np.concatenate([s[:half][s[:half] > 0] for s in solves])
    u2 = np.concatenate([s[half:][s[half:] > 0] for s in solves])
    return {
        "u1": u1,
        "u2": u2,
        "slowest": int(sum(s.max() for s in solves)),
        "rounds": result.iterations,
        "wall": time.perf_counter() - start,
        "forces": [np.array([r.force for r in t]) for t in result.results],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mesh-mm", type=float, default=0.5)
    parser.add_argument("--trajectories", type=int, default=2)
    parser.add_argument("--steps", type=int, default=12, help="0.1 mm increments past first touch")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    model = BioTacModel(make_biotac(max_edge=args.mesh_mm * 1e-3))
    if not model.inflate().converged:
        raise SystemExit("inflation did not converge")
    paths = random_paths(model, args.trajectories, ["sphere_medium", "cylinder_long"], args.seed, 3e-3)
    trajectories = to_trajectories(paths, press_travels(3e-3, 1e-4)[: args.steps + 1])
    skin = model.inflated_skin()
    run(skin, trajectories[:1], args.device, True)  # compiles every kernel
    cold = run(skin, trajectories, args.device, False)
    warm = run(skin, trajectories, args.device, True)
    table = Table(title=f"CG per Newton step, {args.mesh_mm} mm mesh, {len(trajectories)} presses, {args.device}")
    for column in ("run", "u1 mean / median", "u2 mean / median", "sum of slowest", "rounds", "wall (s)", "vs cold"):
        table.add_column(column)
    for name, r in (("cold (baseline)", cold), ("warm u2", warm)):
        table.add_row(
            name,
            f"{r['u1'].mean():.0f} / {np.median(r['u1']):.0f}",
            f"{r['u2'].mean():.0f} / {np.median(r['u2']):.0f}",
            str(r["slowest"]),
            str(r["rounds"]),
            f"{r['wall']:.1f}",
            f"{r['slowest'] / cold['slowest']:.2f}",
        )
    console = Console(width=160)
    console.print(table)
    if all(a.shape == b.shape for a, b in zip(cold["forces"], warm["forces"], strict=True)):
        difference = max(np.abs(a - b).max() for a, b in zip(cold["forces"], warm["forces"], strict=True))
        console.print(f"largest force difference warm vs cold: {difference:.2e} N")
    else:
        console.print("the runs ended at different increments")


if __name__ == "__main__":
    main()
