"""Forces of a saved batched run (`fe_bench.py --batch N --trajectories M --forces F.npz`, e.g. from a GPU
machine) against the serial CPU stepper, trajectory by trajectory, on the machine with the full stack.

    python benchmarks/fe_agreement.py F.npz --problem DIR --rows 100:118 [--mesh-mm 0.5] [--engine batched]

The trajectories are rebuilt from the same --problem cache, count (M, from F.npz) and queue order as the
run; each of --rows (start:stop, or a comma-separated list such as 143,377) is stepped by the CPU stepper
and compared increment by increment where both paths converged: relative force difference
|F_cpu - F_batched| / max(|F_cpu|, 1 mN). Prints the median, 99th percentile and largest difference and
every increment above --report (default 1e-3). `--engine batched` steps the rows instead through the batched
engine on warp's CPU device (direct solves) from the cached skin, the run's own code path but for the device,
and also prints how each row ended on both (`end`) and its Newton iterations per increment: whether a
press that ended early on a GPU does so on the CPU too.
"""

import argparse
import json
from pathlib import Path

import numpy as np
from fe_bench import forces_of, queued_paths, serial_agreement

from fe.batched import InflatedSkin
from fe.batched_runner import run_trajectories
from fe.trajectory_sets import press_travels, to_trajectories


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("forces", help=".npz written by fe_bench.py --forces")
    parser.add_argument("--problem", required=True, help="the --problem folder of that run")
    parser.add_argument("--rows", default="0:9", help="trajectories to compare, start:stop or i,j,k")
    parser.add_argument("--engine", choices=("serial", "batched"), default="serial", help="CPU path to compare")
    parser.add_argument("--mesh-mm", type=float, default=0.5)
    parser.add_argument("--depth-mm", type=float, default=3.0)
    parser.add_argument("--step-mm", type=float, default=0.1)
    parser.add_argument("--force-limit", type=float, default=25.0)
    parser.add_argument("--report", type=float, default=1e-3, help="print increments differing by more")
    args = parser.parse_args()
    with np.load(args.forces) as data:
        batched = {k: data[k] for k in data.files}
    if "converged" not in batched:
        parser.error(f"{args.forces} has no 'converged' array: rerun fe_bench.py --forces with this version")
    rows = _rows(args.rows, len(batched["names"]))
    if not len(rows):
        parser.error(f"--rows {args.rows} selects none of the {len(batched['names'])} trajectories")
    if not all((Path(args.problem) / name).exists() for name in ("skin.npz", "paths.npz")):
        parser.error(f"--problem {args.problem} holds no cached skin and trajectories (skin.npz, paths.npz)")
    args.trajectories = args.batch = len(batched["names"])  # the run's count picks the same cached paths
    skin, paths, model = queued_paths(args)
    if not np.array_equal(paths["names"], batched["names"]):
        parser.error("the trajectories rebuilt from --problem are not those of the run (other folder or count)")
    travels = press_travels(args.depth_mm * 1e-3, args.step_mm * 1e-3)
    if args.engine == "batched":
        summary = batched_cpu_agreement(skin, paths, travels, batched, rows, args.force_limit, args.report)
    else:
        summary = serial_agreement(args, paths, travels, batched, rows, model, report=args.report)
    print(json.dumps(summary, indent=1))


def _rows(text: str, count: int) -> np.ndarray:
    """Row indices (< count) of --rows: "start:stop" or a comma-separated list."""
    if ":" in text:
        start, stop = (int(v) for v in text.split(":"))
        return np.arange(start, min(stop, count))
    return np.array([int(v) for v in text.split(",") if int(v) < count], dtype=int)


def batched_cpu_agreement(
    skin: InflatedSkin,
    paths: dict,
    travels: np.ndarray,
    batched: dict,
    rows: np.ndarray,
    force_limit: float,
    report: float,
) -> dict:
    """The trajectories `rows` through the batched engine on the CPU (one system each, stopping above
    `force_limit` N like the run), printed per row: how it ended there and in `batched` (`fe_bench.forces_of`'s
    `end`) and its Newton iterations per loaded increment; the relative force differences (as
    `serial_agreement`) over the increments both converged, those above `report` printed."""
    trajectories = to_trajectories({k: v[rows] for k, v in paths.items()}, travels)
    run = run_trajectories(skin, trajectories, "cpu", len(rows), force_limit)
    cpu = forces_of(run.results, paths["names"][rows], len(travels), force_limit)
    both = cpu["converged"] & batched["converged"][rows]
    relative = np.linalg.norm(cpu["force"] - batched["force"][rows], axis=2)
    relative /= np.maximum(np.linalg.norm(cpu["force"], axis=2), 1e-3)
    for j, i in enumerate(rows):
        loaded = [r.newton_iterations for r in run.results[j] if r.message != "no contact"]
        print(
            f"row {i} ({paths['names'][i]}): CPU {len(run.results[j])} poses, ended '{cpu['end'][j]}'; run "
            f"{int(batched['converged'][i].sum())} converged, ended '{batched['end'][i]}'; Newton {np.mean(loaded):.1f}"
        )
        for k in np.flatnonzero(both[j] & (relative[j] > report)):
            print(f"  pose {k}: CPU {cpu['force'][j, k]} N, run {batched['force'][i, k]} N")
    diffs = relative[both] if both.any() else np.full(1, np.nan)
    return {
        "rows": len(rows),
        "cpu_s": run.wall_s,
        "rel_force_diff_median": float(np.median(diffs)),
        "rel_force_diff_p99": float(np.percentile(diffs, 99)),
        "max_rel_force_diff": float(diffs.max()),
    }


if __name__ == "__main__":
    main()
