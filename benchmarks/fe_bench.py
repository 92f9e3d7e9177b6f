"""FE speed and mesh-convergence table: nodes, wall time and Newton iterations per 0.1 mm increment,
and the force change between a default and a finer mesh at the final depth.

    python benchmarks/fe_bench.py [--meshes-mm 0.5,0.35] [--depth-mm 3] [--indenter sphere_medium]

The issue's target on the 2-core CPU: at most 1 s per 0.1 mm increment at >= 4000 skin nodes.
s / increment is the median wall time of the loaded increments; Newton / incr. their mean iteration count.

Batched throughput (`fe.batched_runner`, docs/scale.md): M trajectories through N continuously batched
slots on a warp device,

    python benchmarks/fe_bench.py --batch N --device cuda|cpu [--trajectories M] [--mesh-mm 0.5]
        [--problem DIR] [--lockstep-s T] [--serial K] [--kernel-timing]

prints trajectories/s, loaded increments/s, the share of slot time spent solving, and the time for 700
trajectories (measured when M = 700 finish within --time-limit; extrapolated from the increment rate,
which leaves out the tail where slots run empty). The queue cycles through the indenters.
--lockstep-s T first runs the previous scheme for T seconds in the same process as the baseline of the
ratio: the first N trajectories stepped pose by pose in lock-step (`BatchedStepper.step`), every system
waiting for the slowest. The inflated skin and the planned trajectories are cached in --problem DIR
(built here with the CPU model when missing), so a GPU machine without trimesh's planning needs only that
folder. --serial K also runs K of the trajectories one by one through the CPU stepper
(`fe.sensor.BioTacModel.stepper`, PARDISO) for the CPU ratio and the force agreement. --kernel-timing
prints the GPU time per warp kernel over a short extra run. --json also writes each round's end time and
busy systems ("trace").
"""

import argparse
import dataclasses
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np
import warp as wp
from rich.console import Console
from rich.progress import Progress, TimeElapsedColumn
from rich.table import Table

from assets.biotac import make_biotac
from assets.indenters import INDENTERS
from fe.batched import InflatedSkin
from fe.batched_runner import run_trajectories
from fe.batched_stepper import BatchedStepper
from fe.linsolve import SymmetricSolver
from fe.sensor import BioTacModel
from fe.trajectory_sets import press_travels, random_paths, round_robin, to_trajectories


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
        "backend": SymmetricSolver().backend,
    }


def add_batch_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of the batched benchmark."""
    parser.add_argument("--batch", type=int, default=None, help="slots: trajectories solved together (batched mode)")
    parser.add_argument("--trajectories", type=int, default=None, help="trajectories to run (default: --batch)")
    parser.add_argument("--lockstep-s", type=float, default=0.0, help="seconds of the lock-step baseline first")
    parser.add_argument("--kernel-timing", action="store_true", help="GPU time per kernel over a short run")
    parser.add_argument("--forcing", default="adaptive", help="CG tolerance rule of the continuous run")
    parser.add_argument("--strict-s", type=float, default=0.0, help="seconds of a continuous 'strict' run first")
    parser.add_argument("--device", default="cpu", help="warp device of the batched solve: cpu, cuda, cuda:0, ...")
    parser.add_argument("--mesh-mm", type=float, default=0.5, help="skin mesh of the batched benchmark")
    parser.add_argument("--indenters", default="sphere_medium", help="comma-separated names or 'all', cycled")
    parser.add_argument("--problem", default=None, help="folder caching the inflated skin and trajectories")
    parser.add_argument("--serial", type=int, default=0, help="trajectories also run serially on the CPU")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", default=None, help="also write the batched results to this JSON file")
    parser.add_argument("--forces", default=None, help="write the batched forces (M, poses, 3) N to this .npz")
    parser.add_argument("--force-limit", type=float, default=25.0, help="N; a trajectory stops above it")
    parser.add_argument("--time-limit", type=float, default=1e9, help="stop the continuous run after this many s")
    parser.add_argument("--max-cuts", type=int, default=3, help="halvings of a failed step before it ends a trajectory")


def plan_batch(args: argparse.Namespace) -> tuple[InflatedSkin, dict[str, np.ndarray], BioTacModel | None]:
    """The inflated skin and B straight trajectories (touch points, directions, rotations, indenters) at
    random ventral points, tilted up to 20 degrees; loaded from --problem when cached there."""
    folder = Path(args.problem) if args.problem else None
    if folder is not None and (folder / "skin.npz").exists():
        with np.load(folder / "paths.npz") as data:
            paths = {k: data[k] for k in data.files}
        if len(paths["names"]) >= _count(args):  # an even spread over the cached ones keeps the indenter mix
            pick = np.linspace(0, len(paths["names"]) - 1, _count(args)).round().astype(int)
            return InflatedSkin.load(folder / "skin.npz"), {k: v[pick] for k, v in paths.items()}, None
    model = BioTacModel(make_biotac(max_edge=args.mesh_mm * 1e-3))
    if not model.inflate().converged:
        raise RuntimeError("inflation did not converge")
    names = list(INDENTERS) if args.indenters == "all" else args.indenters.split(",")
    paths = random_paths(model, _count(args), names, args.seed, args.depth_mm * 1e-3)
    skin = model.inflated_skin()
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
        skin.save(folder / "skin.npz")
        np.savez(folder / "paths.npz", **paths)
    return skin, paths, model


def _count(args: argparse.Namespace) -> int:
    """Trajectories of the batched benchmark."""
    return args.trajectories or args.batch


def queued_paths(args: argparse.Namespace) -> tuple[InflatedSkin, dict[str, np.ndarray], BioTacModel | None]:
    """`plan_batch`'s skin, paths (in the benchmark's queue order: cycling through the indenters) and model."""
    skin, paths, model = plan_batch(args)
    return skin, {k: v[round_robin(paths["names"])] for k, v in paths.items()}, model


def run_batch_benchmark(args: argparse.Namespace) -> None:
    """Run the trajectories (first pose 0.1 mm before touch, then to --depth-mm in --step-mm) through --batch
    continuously batched slots and print throughput, beside the lock-step baseline and the CPU stepper."""
    skin, paths, model = queued_paths(args)
    travels = press_travels(args.depth_mm * 1e-3, args.step_mm * 1e-3)
    trajectories = to_trajectories(paths, travels)
    console = Console(width=200)
    start = time.perf_counter()
    first = trajectories[0]
    first = dataclasses.replace(first, rotations=first.rotations[:3], translations=first.translations[:3])
    run_trajectories(skin, [first], args.device, slots=1)  # compiles (or loads) every kernel
    compile_s = time.perf_counter() - start
    rows = []
    if args.lockstep_s > 0:
        rows.append(_lockstep(skin, trajectories[: args.batch], args))
    if args.strict_s > 0:
        rows.append(_continuous(skin, trajectories, args, "strict", args.strict_s)[0])
    row, run = _continuous(skin, trajectories, args, args.forcing, args.time_limit)
    rows.append(row)
    # Extrapolated with the continuous run's mean trajectory length (lock-step ones are cut by time); measured
    # only where 700 trajectories ran to the end.
    per_trajectory = rows[-1]["loaded_increments_per_trajectory"]
    for row in rows:
        row["minutes_for_700_extrapolated"] = 700 * per_trajectory / max(row["increments_per_s"], 1e-12) / 60
        measured = row["complete"] and row["finished_trajectories"] == 700
        row["minutes_for_700_measured"] = row["wall_s"] / 60 if measured else float("nan")
        row |= {"device": str(wp.get_device(args.device)), "mesh_mm": args.mesh_mm, "nodes": len(skin.vertices)}
        row["compile_s"] = compile_s
    forces = forces_of(run.results, paths["names"], len(travels), args.force_limit)
    if args.serial:
        count = min(args.serial, len(run.results))
        rows[-1].update(serial_agreement(args, paths, travels, forces, np.arange(count), model))
    table = Table("quantity", *(row["mode"] for row in rows))
    for key in rows[-1]:
        cells = [row.get(key, "") for row in rows]
        table.add_row(key, *(f"{v:.4g}" if isinstance(v, float) else str(v) for v in cells))
    console.print(table)
    for row in rows[:-1]:
        ratio = rows[-1]["increments_per_s"] / max(row["increments_per_s"], 1e-12)
        console.print(f"{rows[-1]['mode']} / {row['mode']} increments per second: {ratio:.2f}x (same process)")
    if args.kernel_timing:
        _kernel_timing(skin, trajectories[: args.batch], args, console)
    if args.json:
        trace = {"round_end_s": run.round_end_s.round(4).tolist(), "round_systems": run.round_systems.tolist()}
        Path(args.json).write_text(json.dumps({"rows": rows, "trace": trace}, indent=1))
    if args.forces:
        np.savez(args.forces, **forces)


def _summary(mode: str, slots: int, results: list, wall: float, counters: dict, complete: bool, finished: int) -> dict:
    """Throughput of one run: trajectories started and finished, loaded increments, and their rates."""
    loaded = [r for trajectory in results for r in trajectory if r.message != "no contact"]
    per_trajectory = len(loaded) / max(sum(bool(t) for t in results), 1)
    increments_per_s = len(loaded) / wall
    solves = max(counters["linear_solves"], 1)
    return {
        "mode": mode,
        "slots": slots,
        "trajectories": sum(bool(t) for t in results),
        "complete": complete,
        "loaded_increments": len(loaded),
        "not_converged": sum(not r.converged for r in loaded),
        "wall_s": wall,
        "increments_per_s": increments_per_s,
        "loaded_increments_per_trajectory": per_trajectory,
        "finished_trajectories": finished,
        "finished_trajectories_per_s": finished / wall,
        "newton_per_increment": float(np.mean([r.newton_iterations for r in loaded])) if loaded else 0.0,
        "system_evaluations_per_increment": counters["system_evaluations"] / max(len(loaded), 1),
        "cut_backs": counters.get("cut_backs", 0),
        "failures": dict(Counter(r.message for r in loaded if not r.converged)),
        "evaluations": counters["evaluations"],
        "linear_solves": counters["linear_solves"],
        "evaluate_s": counters["evaluate_s"],
        "linear_solve_s": counters["linear_solve_s"],
        "cg_iterations_per_solve_max": counters["cg_iterations_max"] / solves,
        "cg_iterations_per_solve_mean": counters["cg_iterations_mean"] / solves,
    }


def _continuous(skin: InflatedSkin, trajectories: list, args: argparse.Namespace, forcing: str, limit_s: float):
    """A continuous run with the `forcing` rule for at most `limit_s` seconds: its summary row (with the
    times by which half, 90 %, 99 % and all trajectories had ended) and the run."""
    wp.synchronize()
    ended: list[float] = []
    start = time.perf_counter()
    with Progress(*Progress.get_default_columns(), TimeElapsedColumn(), transient=True) as progress:
        task = progress.add_task(f"{forcing}: trajectories", total=len(trajectories))

        def finished(_index: int, _increments: list) -> None:
            ended.append(time.perf_counter() - start)
            progress.advance(task)

        run = run_trajectories(
            skin, trajectories, args.device, args.batch, args.force_limit, finished, limit_s, forcing, args.max_cuts
        )
    mode = f"continuous, {forcing}"
    row = _summary(mode, args.batch, run.results, run.wall_s, run.counters, run.complete, len(ended))
    row["rounds"] = run.iterations
    durations = np.diff(run.round_end_s, prepend=0.0)
    row["slot_occupancy"] = float(durations @ run.round_systems / max(run.slots * run.wall_s, 1e-12))
    for share in (0.5, 0.9, 0.99, 1.0):
        k = int(np.ceil(share * len(trajectories)))
        row[f"s_to_{share:.0%}_ended"] = ended[k - 1] if len(ended) >= k else float("nan")
    return row, run


def _lockstep(skin: InflatedSkin, trajectories: list, args: argparse.Namespace) -> dict:
    """The baseline, the previous scheme: one `BatchedStepper.step` per pose for all systems, strict CG
    tolerances, for --lockstep-s seconds."""

    stepper = BatchedStepper(skin, [t.indenter for t in trajectories], args.device, forcing="strict")
    results: list[list] = [[] for _ in trajectories]
    running = np.ones(len(trajectories), dtype=bool)
    start = time.perf_counter()
    rotation = np.stack([t.rotations[0] for t in trajectories])
    for k in range(len(trajectories[0].translations)):
        if time.perf_counter() - start > args.lockstep_s or not running.any():
            break
        translation = np.stack([t.translations[k] for t in trajectories])
        for i, result in enumerate(stepper.step(rotation, translation, running)):
            if result is not None:
                results[i].append(result)
                # As in a campaign, a failed trajectory stops, and so does one past the force limit.
                running[i] &= result.converged and np.linalg.norm(result.force) <= args.force_limit
    wall, finished = time.perf_counter() - start, int((~running).sum())
    return _summary("lock-step", len(trajectories), results, wall, stepper.shell.counters, False, finished)


def _kernel_timing(skin: InflatedSkin, trajectories: list, args: argparse.Namespace, console: Console) -> None:
    """GPU time per kernel (summed over launches) of a 20 s continuous run, largest first."""
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_GRAPH)
    run_trajectories(skin, trajectories, args.device, args.batch, args.force_limit, None, 20.0, args.forcing)
    timings = wp.timing_end()
    totals: dict[str, list[float]] = {}
    for t in timings:
        entry = totals.setdefault(t.name, [0.0, 0])
        entry[0] += t.elapsed
        entry[1] += 1
    table = Table("kernel / copy", "GPU ms", "calls", "ms / call")
    for name, (ms, calls) in sorted(totals.items(), key=lambda item: -item[1][0])[:25]:
        table.add_row(name[:80], f"{ms:.1f}", str(calls), f"{ms / calls:.3f}")
    console.print(table)


def forces_of(results: list, names: np.ndarray, poses: int = 0, force_limit: float = np.inf) -> dict:
    """Forces (M, poses, 3) N and convergence (M, poses) of a run's trajectories, NaN and False after a
    trajectory stopped; the indenter names (M,); why each ended (M,): the failure text of its last increment,
    "force limit", "all poses", "running" (cut by the time limit) or "" (not started). `poses`: of every
    trajectory (0: the longest result's)."""
    poses = poses or max(len(t) for t in results)
    force = np.full((len(results), poses, 3), np.nan)
    converged = np.zeros((len(results), poses), dtype=bool)
    end = np.full(len(results), "", dtype=object)
    for i, trajectory in enumerate(results):
        for k, r in enumerate(trajectory):
            force[i, k], converged[i, k] = r.force, r.converged
        if trajectory:
            end[i] = _end_reason(trajectory[-1], len(trajectory) == poses, force_limit)
    return {"force": force, "converged": converged, "names": names[: len(results)], "end": end.astype(str)}


def _end_reason(last, at_last_pose: bool, force_limit: float) -> str:
    """Why a trajectory whose last increment is `last` ended (see `forces_of`)."""
    if not last.converged:
        return last.message
    if np.linalg.norm(last.force) > force_limit:
        return "force limit"
    return "all poses" if at_last_pose else "running"


def serial_agreement(
    args: argparse.Namespace,
    paths: dict,
    travels: np.ndarray,
    batched: dict,
    rows: np.ndarray,
    model: BioTacModel | None,
    report: float = np.inf,
) -> dict:
    """The trajectories `rows` one by one through the CPU stepper, stopping like the batch: speed and the force
    differences from the batched forces (`forces_of`; relative to |F|, at least 1 mN) over the increments both
    converged; those above `report` are printed."""
    if model is None:
        model = BioTacModel(make_biotac(max_edge=args.mesh_mm * 1e-3))
        model.inflate()
    differences, increments = [], 0
    start = time.perf_counter()
    for i in rows:
        stepper = model.stepper(str(paths["names"][i]))
        for k, t in enumerate(travels):
            result = stepper.step(paths["rotation"][i], paths["touch"][i] + t * paths["direction"][i])
            increments += result.message != "no contact"
            if k < batched["force"].shape[1] and result.converged and batched["converged"][i, k]:
                force = batched["force"][i, k]
                differences.append(np.linalg.norm(result.force - force) / max(np.linalg.norm(result.force), 1e-3))
                if differences[-1] > report:
                    print(f"trajectory {i} ({paths['names'][i]}) pose {k}: CPU {result.force} N, batched {force} N")
            if not result.converged or np.linalg.norm(result.force) > args.force_limit:
                break
    wall = time.perf_counter() - start
    diffs = np.array(differences) if differences else np.full(1, np.nan)
    return {
        "serial_trajectories": len(rows),
        "serial_increments_per_s": increments / wall,
        "serial_trajectories_per_s": len(rows) / wall,
        "rel_force_diff_median": float(np.median(diffs)),
        "rel_force_diff_p99": float(np.percentile(diffs, 99)),
        "max_rel_force_diff": float(diffs.max()),
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
