"""Run the FE-simulated campaign behind the results table of docs/learn.md.

Three sensors (BioTac 1 spheres only, as in the paper), all nine indenters, the 2 mm skin mesh, a few
seeded ventral points per indenter, one normal and `--angled` 30 deg paths per point, the paper's
depths (3 mm normal, 1.5 mm angled) in 0.1 mm increments with loading and unloading, short pauses.
Everything goes through the real pipeline (FE skin, plant, electrode physics, processing) via
`twin.campaign.run_campaign`; the files are the schema of docs/dataset.md.

    python3 scripts/make_learn_campaign.py --out runs/learn_fe --workers 2 --time-limit 1740
        # docs/learn.md's table: 162 of the 228 reachable trajectories in 32 min on 2 shared cores;
        # without --time-limit (or run again on the same --out) it finishes all 228
    python3 scripts/make_learn_campaign.py --out runs/learn_fe --plan-only          # what would run
    python3 scripts/make_learn_campaign.py --out runs/learn_fe --compact runs/learn_fe_compact

--compact writes, from the finished files, copies that hold only what `learn` reads (electrodes,
targets, ids, per-trajectory metadata) and the skin displacements of the 128 field nodes `learn.data`
draws (seed 0) instead of all nodes, with no full-rate `raw/` recordings: `learn.data.load` gives the
same arrays on both (checked when written); small enough to carry to the GPU machine.

A killed run resumes from its parts when started again with the same --out and options.
Then (docs/learn.md):

    python3 benchmarks/learn_bench.py --data runs/learn_fe --table 3 ...
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from twin.campaign import QUICK_CONFIG, plan_campaign, run_campaign  # noqa: E402
from twin.executors import LocalExecutor  # noqa: E402
from twin.protocol import ProtocolSettings  # noqa: E402


class ShuffledExecutor(LocalExecutor):
    """Local processes running the trajectories in a seeded random order, stopping after `time_limit` s.

    The order spreads a cut-short run evenly over sensors, indenters and points; at the limit, pending
    trajectories are cancelled (running ones finish) and `run_campaign` assembles the parts it has. A
    later run with the same --out resumes the rest.
    """

    def __init__(self, workers: int, seed: int, time_limit: float | None) -> None:
        super().__init__(workers)
        self.seed, self.time_limit, self.cut = seed, time_limit, 0

    def map_unordered(self, task, jobs, setup, setup_args):
        from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
        from multiprocessing import get_context

        if not jobs:
            return
        order = np.random.default_rng(self.seed).permutation(len(jobs))
        start = time.time()
        with ProcessPoolExecutor(self.workers, get_context("spawn"), setup, setup_args) as pool:
            pending = {pool.submit(task, *jobs[i]) for i in order}
            while pending:
                done, pending = wait(pending, timeout=5.0, return_when=FIRST_COMPLETED)
                for future in done:
                    if not future.cancelled():
                        yield future.result()
                if self.time_limit is not None and time.time() - start > self.time_limit:
                    cancelled = {f for f in pending if f.cancel()}
                    self.cut += len(cancelled)
                    pending -= cancelled


def config_from(args: argparse.Namespace):
    settings = ProtocolSettings(
        points_per_indenter=args.points,
        angled_per_point=args.angled,
        normal_depth=args.normal_depth_mm * 1e-3,
        angled_depth=args.angled_depth_mm * 1e-3,
        pause_s=args.pause,
        unload=True,
        replacement_rounds=args.replacement_rounds,
    )
    changes = {"settings": settings, "mesh_max_edge": args.mesh_mm * 1e-3, "seed": args.seed}
    if args.sensors:
        changes["sensors"] = tuple(int(s) for s in args.sensors.split(","))
    if args.indenters:
        changes["indenters"] = tuple(s.strip() for s in args.indenters.split(","))
    return replace(QUICK_CONFIG, **changes)


ROW_FEATURES = (
    "electrode_vals",
    "contact_loc",
    "force",
    "trajectory_id",
    "indenter_type",
    "depth",
    "phase",
    "fe_force",
    "fe_pressure",
    "fe_converged",
    "pdc",
)


def compact(src: Path, dst: Path) -> None:
    """Copy src (a campaign file) to dst keeping learn's inputs and the 128 field nodes only."""
    import h5py

    from learn.data import load, pick_field_nodes

    dst.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(src, "r") as f, h5py.File(dst, "w") as g:
        for key, value in f.attrs.items():
            g.attrs[key] = value
        for name in ROW_FEATURES:
            if name in f:
                f.copy(f[name], g, name=name)
        if "trajectories" in f:
            f.copy(f["trajectories"], g, name="trajectories")
        ids = pick_field_nodes(np.flatnonzero(f["mesh/ventral"][:]), 0)
        grp = g.create_group("nodal_res")
        data = f["nodal_res/data"][:][:, ids, :]
        ds = grp.create_dataset("data", data=data, compression="gzip", compression_opts=4, shuffle=True)
        for key, value in f["nodal_res/data"].attrs.items():
            ds.attrs[key] = value
        ds.attrs["source_node_ids"] = ids
        mesh = g.create_group("mesh")
        mesh.create_dataset("vertices", data=f["mesh/vertices"][:][ids])
        mesh.create_dataset("ventral", data=np.ones(len(ids), bool))
        g.attrs["compacted_from"] = str(src)
    a, b = load(src), load(dst)
    for field in ("electrodes", "trajectory", "indenter", "contact_loc", "force", "nodal", "nodes"):
        if not np.array_equal(getattr(a, field), getattr(b, field)):
            raise RuntimeError(f"{dst}: {field} differs from {src}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("runs/learn_fe"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--points", type=int, default=4, help="ventral points per indenter")
    ap.add_argument("--angled", type=int, default=2, help="30 deg paths per point (besides the normal one)")
    ap.add_argument("--normal-depth-mm", type=float, default=3.0)
    ap.add_argument("--angled-depth-mm", type=float, default=1.5)
    ap.add_argument("--pause", type=float, default=0.5, help="pause per increment (s); the paper's is 5")
    ap.add_argument("--mesh-mm", type=float, default=2.0)
    ap.add_argument("--replacement-rounds", type=int, default=2)
    ap.add_argument("--sensors", default=None, help="comma-separated ids (default 1,2,3)")
    ap.add_argument("--indenters", default=None, help="comma-separated names (default all nine)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--time-limit", type=float, default=None, help="stop starting trajectories after this (s)")
    ap.add_argument("--compact", type=Path, default=None, help="write learn-only copies of the files here, stop")
    ap.add_argument("--plan-only", action="store_true", help="print the plan statistics and stop")
    args = ap.parse_args()
    config = config_from(args)
    if args.compact is not None:
        for src in sorted(args.out.glob("biotac*.hdf5")):
            compact(src, args.compact / src.name)
            print(f"{args.compact / src.name}: {(args.compact / src.name).stat().st_size / 1e6:.1f} MB")
        return
    if args.plan_only:
        print(json.dumps(plan_campaign(config).statistics(), indent=1, default=str))
        return
    start = time.time()

    def report(done: int, total: int) -> None:
        print(f"{time.strftime('%H:%M:%S')} {done}/{total} trajectories ({time.time() - start:.0f} s)", flush=True)

    executor = ShuffledExecutor(args.workers, args.seed, args.time_limit)
    result = run_campaign(config, args.out, on_progress=report, executor=executor)
    wall = time.time() - start
    summary = {
        "files": {str(k): str(v) for k, v in result.files.items()},
        "ran": result.ran,
        "resumed_past": result.skipped,
        "incomplete": result.incomplete,
        "not_run_time_limit": executor.cut,
        "wall_s_this_run": round(wall, 1),
        "args": {k: str(v) for k, v in vars(args).items()},
    }
    print(json.dumps(summary, indent=1))
    (args.out / "make_learn_campaign.json").write_text(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
