"""FE speed and mesh-convergence table: nodes, wall time and Newton iterations per 0.1 mm increment,
and the force change between a default and a finer mesh at the final depth.

    python benchmarks/fe_bench.py [--meshes-mm 0.5,0.35] [--depth-mm 3] [--indenter sphere_medium]

The issue's target on the 2-core CPU: at most 1 s per 0.1 mm increment at >= 4000 skin nodes.
s / increment is the median wall time of the loaded increments; Newton / incr. their mean iteration count.

Batched throughput (`fe.batched_stepper`, docs/scale.md): B trajectories stepped together on a warp device,

    python benchmarks/fe_bench.py --batch N --device cuda|cpu [--mesh-mm 0.5] [--problem DIR] [--serial K]

prints trajectories/s and loaded increments/s. The inflated skin and the planned trajectories are cached in
--problem DIR (built here with the CPU model when missing), so a GPU machine without trimesh's planning
needs only that folder. --serial K also runs K of the trajectories one by one through the CPU stepper
(`fe.sensor.BioTacModel.stepper`, PARDISO) for the speed ratio and the force agreement.
"""

import argparse
import time
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from assets.biotac import make_biotac
from assets.indenters import INDENTERS, get_indenter
from fe.batched import InflatedSkin
from fe.sensor import BioTacModel


def run(mesh_mm: float, indenter: str, point_mm: list[float], depth_mm: float, step_mm: float) -> dict:
    """Inflate and indent once on a mesh of `mesh_mm` edges; return timings and the final force (N)."""
    start = time.perf_counter()
    model = BioTacModel(make_biotac(max_edge=mesh_mm * 1e-3))
    inflation = model.inflate()
    setup_s = time.perf_counter() - start
    increments = list(model.indent(indenter, np.array(point_mm) * 1e-3, depth_mm * 1e-3, step_mm * 1e-3))
    loaded = increments[1:]
    return {
        "mesh_mm": mesh_mm,
        "nodes": len(model.geometry.skin.vertices),
        "free_nodes": int((~model.geometry.skin.anchored).sum()),
        "setup_s": setup_s,
        "pressure_kpa": inflation.pressure / 1e3,
        "s_per_increment": float(np.median([inc.wall_s for inc in loaded])),
        "newton_per_increment": float(np.mean([inc.newton_iterations for inc in loaded])),
        "reached_mm": increments[-1].depth * 1e3,
        "converged": increments[-1].converged,
        "force": increments[-1].force,
        "backend": model.system.linear_solver.backend,
    }


def add_batch_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the batched benchmark."""
    parser.add_argument("--batch", type=int, default=None, help="trajectories solved together (batched mode)")
    parser.add_argument("--device", default="cpu", help="warp device of the batched solve: cpu, cuda, cuda:0, ...")
    parser.add_argument("--mesh-mm", type=float, default=0.5, help="skin mesh of the batched benchmark")
    parser.add_argument("--indenters", default="sphere_medium", help="comma-separated names or 'all', cycled")
    parser.add_argument("--problem", default=None, help="folder caching the inflated skin and trajectories")
    parser.add_argument("--serial", type=int, default=0, help="trajectories also run serially on the CPU")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None, help="also write the batched results to this JSON file")
    parser.add_argument("--forces", default=None, help="write the batched forces (poses, B, 3) N to this .npz")
    parser.add_argument("--force-limit", type=float, default=25.0, help="N; a trajectory stops above it")
    parser.add_argument("--time-limit", type=float, default=1e9, help="stop stepping after this many seconds")


def plan_batch(args: argparse.Namespace) -> tuple[InflatedSkin, dict[str, np.ndarray], BioTacModel | None]:
    """The inflated skin and B straight trajectories (touch points, directions, rotations, indenters) at
    random ventral points, tilted up to 20 degrees; loaded from --problem when cached there."""
    folder = Path(args.problem) if args.problem else None
    if folder is not None and (folder / "skin.npz").exists():
        with np.load(folder / "paths.npz") as data:
            paths = {k: data[k] for k in data.files}
        if len(paths["names"]) >= args.batch:  # an even spread over the cached ones keeps the indenter mix
            pick = np.linspace(0, len(paths["names"]) - 1, args.batch).round().astype(int)
            return InflatedSkin.load(folder / "skin.npz"), {k: v[pick] for k, v in paths.items()}, None
    model = BioTacModel(make_biotac(max_edge=args.mesh_mm * 1e-3))
    if not model.inflate().converged:
        raise RuntimeError("inflation did not converge")
    names = list(INDENTERS) if args.indenters == "all" else args.indenters.split(",")
    rng = np.random.default_rng(args.seed)
    ventral = model.reference[model.geometry.skin.ventral]
    rows: dict[str, list] = {"names": [], "touch": [], "direction": [], "rotation": []}
    while len(rows["names"]) < args.batch:
        name = names[len(rows["names"]) % len(names)]
        point = ventral[rng.integers(len(ventral))]
        try:
            path = model.plan_trajectory(
                get_indenter(name), point, rng.uniform(0, 20), rng.uniform(0, 360), args.depth_mm * 1e-3, 1e-3
            )
        except ValueError:
            continue
        for key, value in zip(rows, (name, path.touch_point, path.direction, path.rotation), strict=True):
            rows[key].append(value)
    order = np.argsort(rows["names"], kind="stable")  # equal indenters contiguous: one contact launch per run
    paths = {k: np.asarray(v)[order] for k, v in rows.items()}
    skin = InflatedSkin.from_model(model)
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        skin.save(folder / "skin.npz")
        np.savez(folder / "paths.npz", **paths)
    return skin, paths, model


def run_batch_benchmark(args: argparse.Namespace) -> None:
    """Step B trajectories together (first pose 0.1 mm before touch, then to --depth-mm in --step-mm) and
    print throughput; with --serial K, the same K trajectories through the CPU stepper beside it."""
    import json

    import warp as wp

    from fe.batched_stepper import BatchedStepper

    skin, paths, model = plan_batch(args)
    travels = np.arange(-1, int(round(args.depth_mm / args.step_mm)) + 1) * args.step_mm * 1e-3
    console = Console(width=200)
    start = time.perf_counter()
    first = {k: v[:1] for k, v in paths.items()}
    warmup = BatchedStepper(skin, list(first["names"]), args.device)  # compiles (or loads) every kernel
    for t in travels[:3]:
        warmup.step(first["rotation"], _poses(first, t))
    compile_s = time.perf_counter() - start
    start = time.perf_counter()
    stepper = BatchedStepper(skin, list(paths["names"]), args.device)
    setup_s = time.perf_counter() - start
    wp.synchronize()
    start = time.perf_counter()
    results = []
    running = np.ones(args.batch, dtype=bool)
    for t in travels:
        if time.perf_counter() - start > args.time_limit:
            break
        results.append(stepper.step(paths["rotation"], _poses(paths, t), running))
        # As in a campaign, a failed trajectory stops, and so does one past the controller's force limit.
        pressed = np.array([r is not None and np.linalg.norm(r.force) > args.force_limit for r in results[-1]])
        running &= ~pressed & np.array([f is None for f in stepper.failure])
    wall = time.perf_counter() - start
    loaded = [r for step in results for r in step if r is not None and r.message != "no contact"]
    failed = sum(not r.converged for r in loaded)
    row = {
        "device": str(wp.get_device(args.device)),
        "mesh_mm": args.mesh_mm,
        "nodes": len(skin.vertices),
        "batch": args.batch,
        "poses_per_trajectory": len(travels),
        "poses_stepped": len(results),
        "loaded_increments": len(loaded),
        "failed": failed,
        "stopped_at_force_limit": int(args.batch - running.sum() - len([f for f in stepper.failure if f])),
        "compile_s": compile_s,
        "setup_s": setup_s,
        "wall_s": wall,
        "trajectories_per_s": args.batch * len(results) / len(travels) / wall,
        "increments_per_s": len(loaded) / wall,
        "newton_per_increment": float(np.mean([r.newton_iterations for r in loaded])) if loaded else 0.0,
    }
    solves = max(stepper.shell.counters["linear_solves"], 1)
    row |= {
        "evaluate_s": stepper.shell.counters["evaluate_s"],
        "linear_solve_s": stepper.shell.counters["linear_solve_s"],
        "cg_iterations_per_solve_max": stepper.shell.counters["cg_iterations_max"] / solves,
        "cg_iterations_per_solve_mean": stepper.shell.counters["cg_iterations_mean"] / solves,
    }
    if args.serial:
        row.update(_serial(args, paths, travels, results, model))
    table = Table("quantity", "value")
    for key, value in row.items():
        table.add_row(key, f"{value:.4g}" if isinstance(value, float) else str(value))
    console.print(table)
    per_trajectory = len(travels) - 1  # every pose after the free approach pose is loaded
    minutes = 700 * per_trajectory / row["increments_per_s"] / 60 if loaded else float("inf")
    console.print(
        f"extrapolated: 700 trajectories x {per_trajectory} loaded increments at {row['increments_per_s']:.3g} "
        f"increments/s = {minutes:.1f} min"
    )
    row["extrapolated_700_min"] = minutes
    if args.json:
        Path(args.json).write_text(json.dumps(row, indent=1))
    if args.forces:
        nan = np.full(3, np.nan)
        forces = [[nan if r is None else r.force for r in step] for step in results]
        force = np.array(forces).reshape(len(results), args.batch, 3)
        np.savez(args.forces, force=force, travel=travels[: len(results)], names=paths["names"])


def _poses(paths: dict[str, np.ndarray], travel: float) -> np.ndarray:
    """Tip positions (B,3) m at `travel` past first touch along each trajectory."""
    return paths["touch"] + travel * paths["direction"]


def _serial(args: argparse.Namespace, paths: dict, travels: np.ndarray, batched: list, model) -> dict:
    """The first --serial trajectories one by one through the CPU stepper: speed and agreement with the batch."""
    if model is None:
        model = BioTacModel(make_biotac(max_edge=args.mesh_mm * 1e-3))
        model.inflate()
    worst, increments = 0.0, 0
    start = time.perf_counter()
    for i in range(min(args.serial, args.batch)):
        stepper = model.stepper(str(paths["names"][i]))
        for k, t in enumerate(travels):
            result = stepper.step(paths["rotation"][i], paths["touch"][i] + t * paths["direction"][i])
            increments += result.message != "no contact"
            if k >= len(batched) or batched[k][i] is None:
                break
            other = batched[k][i]
            worst = max(worst, np.linalg.norm(result.force - other.force) / max(np.linalg.norm(result.force), 1e-3))
    wall = time.perf_counter() - start
    return {
        "serial_trajectories": min(args.serial, args.batch),
        "serial_increments_per_s": increments / wall,
        "serial_trajectories_per_s": min(args.serial, args.batch) / wall,
        "max_rel_force_diff": worst,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes-mm", default="0.5,0.35")
    parser.add_argument("--depth-mm", type=float, default=3.0)
    parser.add_argument("--step-mm", type=float, default=0.1)
    parser.add_argument("--indenter", default="sphere_medium")
    parser.add_argument("--point-mm", default="-6,0,-9")
    add_batch_arguments(parser)
    args = parser.parse_args()
    if args.batch is not None:
        run_batch_benchmark(args)
        return
    point = [float(v) for v in args.point_mm.split(",")]
    rows = [run(float(h), args.indenter, point, args.depth_mm, args.step_mm) for h in args.meshes_mm.split(",")]
    table = Table(
        "mesh (mm)",
        "nodes",
        "free",
        "inflate (s)",
        "p (kPa)",
        "s / increment",
        "Newton / incr.",
        "depth reached (mm)",
        "F (N), biotac frame",
        "|dF| / |F| vs first",
    )
    reference = rows[0]["force"]
    for r in rows:
        change = np.linalg.norm(r["force"] - reference) / max(np.linalg.norm(reference), 1e-12)
        table.add_row(
            f"{r['mesh_mm']:.2f}",
            str(r["nodes"]),
            str(r["free_nodes"]),
            f"{r['setup_s']:.1f}",
            f"{r['pressure_kpa']:.2f}",
            f"{r['s_per_increment']:.2f}",
            f"{r['newton_per_increment']:.1f}",
            f"{r['reached_mm']:.2f}{'' if r['converged'] else ' (stopped)'}",
            "[" + ", ".join(f"{f:.3f}" for f in r["force"]) + "]",
            f"{change:.1%}",
        )
    console = Console(width=200)
    console.print(table)
    console.print(f"sparse factorisation: {rows[0]['backend']} (BIOTAC_TWIN_SPARSE=superlu forces SciPy's SuperLU)")


if __name__ == "__main__":
    main()
