"""Forces of a saved batched run (`fe_bench.py --batch N --trajectories M --forces F.npz`, e.g. from a GPU
machine) against the serial CPU stepper, trajectory by trajectory, on the machine with the full stack.

    python benchmarks/fe_agreement.py F.npz --problem DIR --rows 100:118 [--mesh-mm 0.5]

The trajectories are rebuilt from the same --problem cache, count (M, from F.npz) and queue order as the
run; each of --rows is stepped by the CPU stepper and compared increment by increment where both paths
converged: relative force difference |F_cpu - F_batched| / max(|F_cpu|, 1 mN). Prints the median, 99th
percentile and largest difference and every increment above --report (default 1e-3).
"""

import argparse
import json
from pathlib import Path

import numpy as np
from fe_bench import queued_paths, serial_agreement

from fe.trajectory_sets import press_travels


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("forces", help=".npz written by fe_bench.py --forces")
    parser.add_argument("--problem", required=True, help="the --problem folder of that run")
    parser.add_argument("--rows", default="0:9", help="trajectories to compare, start:stop")
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
    start, stop = (int(v) for v in args.rows.split(":"))
    rows = np.arange(start, min(stop, len(batched["names"])))
    if not len(rows):
        parser.error(f"--rows {args.rows} selects none of the {len(batched['names'])} trajectories")
    if not all((Path(args.problem) / name).exists() for name in ("skin.npz", "paths.npz")):
        parser.error(f"--problem {args.problem} holds no cached skin and trajectories (skin.npz, paths.npz)")
    args.trajectories = args.batch = len(batched["names"])  # the run's count picks the same cached paths
    _, paths, model = queued_paths(args)
    if not np.array_equal(paths["names"], batched["names"]):
        parser.error("the trajectories rebuilt from --problem are not those of the run (other folder or count)")
    travels = press_travels(args.depth_mm * 1e-3, args.step_mm * 1e-3)
    summary = serial_agreement(args, paths, travels, batched, rows, model, report=args.report)
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
