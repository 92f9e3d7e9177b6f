"""CG work per Newton step of the batched engine's GPU algebra: the warm start and the forcing floor.

Each Newton step solves K u1 = -r and K u2 = grad V per system with block-Jacobi CG (the GPU's algebra;
`linear="cg"` runs it on warp's CPU device too). u2 is a smooth field that block Jacobi converges slowest on and
that the next Newton step barely moves, so the engine starts it from the system's last u2 (`BatchedCG`'s
`warm` columns); and the adaptive forcing asks no tighter than `NewtonSettings.min_forcing` of a step. This
benchmark runs the same presses three times in one process: as before 2026-11-27 (every column from 0,
Eisenstat-Walker alone: the baseline), with the warm start only, and as now (both), and prints per run the CG
iterations of each kind of column, the sum over solves of the slowest column (what a replayed CUDA graph
pays), the Newton rounds, the wall time, the ratio to the baseline and the largest force difference to it (N).

    python benchmarks/cg_work.py [--mesh-mm 0.5] [--trajectories 4] [--steps 12] [--device cpu]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import time
from unittest import mock

import numpy as np
from rich.console import Console
from rich.table import Table

from assets.biotac import make_biotac
from fe import device_solver
from fe.batched_runner import run_trajectories
from fe.params import NewtonSettings
from fe.sensor import BioTacModel
from fe.trajectory_sets import press_travels, random_paths, to_trajectories


def run(skin, trajectories, device: str, warm: bool, floor: float) -> dict:
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
        skin = dataclasses.replace(skin, newton=dataclasses.replace(skin.newton, min_forcing=floor))
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
    parser.add_argument("--trajectories", type=int, default=4)
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
    floor = NewtonSettings().min_forcing
    run(skin, trajectories[:1], args.device, True, floor)  # compiles every kernel
    runs = {
        "before (cold, no floor)": run(skin, trajectories, args.device, False, 0.0),
        "warm u2": run(skin, trajectories, args.device, True, 0.0),
        f"warm u2 + floor {floor:g} (now)": run(skin, trajectories, args.device, True, floor),
    }
    base = runs["before (cold, no floor)"]
    table = Table(title=f"CG per Newton step, {args.mesh_mm} mm mesh, {len(trajectories)} presses, {args.device}")
    columns = ("run", "u1 mean / median", "u2 mean / median", "sum of slowest", "rounds", "wall (s)", "vs before")
    for column in (*columns, "max |dF| vs before (N)"):
        table.add_column(column)
    for name, r in runs.items():
        pairs = list(zip(base["forces"], r["forces"], strict=True))
        same = all(a.shape == b.shape for a, b in pairs)
        difference = max(np.abs(a - b).max() for a, b in pairs) if same else None
        table.add_row(
            name,
            f"{r['u1'].mean():.0f} / {np.median(r['u1']):.0f}",
            f"{r['u2'].mean():.0f} / {np.median(r['u2']):.0f}",
            str(r["slowest"]),
            str(r["rounds"]),
            f"{r['wall']:.1f}",
            f"{r['slowest'] / base['slowest']:.2f}",
            "ended elsewhere" if difference is None else f"{difference:.1e}",
        )
    Console(width=180).print(table)


if __name__ == "__main__":
    main()
