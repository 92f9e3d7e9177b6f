"""Speed of `twin diagnose` on a campaign file: its batched replays in this process (before) and split over
worker processes, one per usable CPU (now).

On warp's CPU device `Predictor` splits each batch of replays into shares of about equal work, each share's batched
runs in a worker process of its own (`Predictor.workers`, default one per usable CPU; `ReplayWorkers`). The
baseline is `workers=1` (one run per batch in this process). Wall seconds only: the workers' CPU time is not this
process's. (Session 15 compared the creep warm start of held poses here, session 17 threads against one thread;
their figures are in docs/scale.md.)

Part 1 replays every trajectory of the file under the `skin_relaxation` probe's skin (timed replays, the largest
batch of the diagnosis until it ranked the relaxation on elastic replays, `twin.analysis.surrogate`; now solved only
for a relaxation it refits; `Predictor.prefetch`, one batch, as diagnose does) both ways and prints wall seconds, their
ratio and the largest difference of the predicted increment forces (N; 0 expected: each system
iterates on its own). Part 2 (`--diagnose`) runs the whole `twin diagnose` (nominal model, 3 refits, as the CLI)
both ways: wall per stage, ratio, and whether the two diagnoses agree (verdict, ranking, largest relative
difference of any number).

Part 3 (`--diagnose --rank-per-stratum K`) runs it once more (workers as now) with the candidates ranked on at
most K trajectories per sensor x indenter x path kind (`twin.analysis.subset`): wall, verdict, and whether the
first candidate's name, refit and held-out figures are those of the diagnosis on every trajectory.

    python benchmarks/diagnose_speed.py CAMPAIGN.hdf5 [--diagnose] [--device cpu] [--workers N] [--rank-per-stratum K]

The demo campaign: `twin demo` writes it (runs/demo/campaign/biotac2.hdf5).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from twin.analysis.data import CampaignData, load_campaign
from twin.analysis.diagnose import diagnose, strict_json
from twin.analysis.predict import Predictor, TwinModel
from twin.effects import EFFECTS, apply_skin
from twin.lanes import usable_cpus

RELAXATION = "skin_relaxation"


def probe_replays(data: CampaignData, device: str, workers: int) -> tuple[float, np.ndarray]:
    """Wall seconds of the relaxation probe's replays of every trajectory (one batched prefetch on `workers`
    processes; the skin inflated in this process first, not timed, which worker processes do again inside the
    timed prefetch) and their increment forces (N, all trajectories stacked)."""
    model = TwinModel(mesh_max_edge=data.mesh_max_edge).with_effects({RELAXATION: EFFECTS[RELAXATION].probe})
    predictor = Predictor(device, workers=workers)
    predictor.fe_model(apply_skin(model.skin, model.effects), model.mesh_max_edge, model.inflation)  # kernels loaded
    start = time.perf_counter()
    predictor.prefetch(model, data.trajectories)
    seconds = time.perf_counter() - start
    return seconds, np.concatenate([predictor.predict(model, t).increment_force for t in data.trajectories])


def diagnosis(
    data: CampaignData, device: str, workers: int, rank_per_stratum: int | None = None
) -> tuple[dict[str, float], dict]:
    """Wall seconds of `twin diagnose`'s stages on the file with replays on `workers` processes and its JSON form;
    candidates ranked on a stratified subset with `rank_per_stratum`."""
    start = time.perf_counter()
    stamps: dict[str, float] = {}
    result = diagnose(
        [data],
        TwinModel(mesh_max_edge=data.mesh_max_edge),
        Predictor(device, workers=workers),
        on_progress=lambda stage, _: stamps.setdefault(stage, time.perf_counter() - start),
        rank_per_stratum=rank_per_stratum,
    )
    total = time.perf_counter() - start
    evidence, refit = stamps.get("evidence", total), stamps.get("refit", total)
    stages = {"base and sensitivities": evidence, "scores": refit - evidence, "refits and held out": total - refit}
    return stages | {"total": total}, strict_json(result.to_dict())


def largest_relative_difference(a: object, b: object) -> float:
    """Largest relative difference between the numbers of two JSON-like values of one shape (inf where their
    strings, Nones or shapes differ)."""
    if isinstance(a, dict) and isinstance(b, dict) and a.keys() == b.keys():
        return max((largest_relative_difference(a[k], b[k]) for k in a), default=0.0)
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return max((largest_relative_difference(x, y) for x, y in zip(a, b, strict=True)), default=0.0)
    if isinstance(a, int | float) and isinstance(b, int | float) and not isinstance(a, bool):
        return abs(a - b) / max(abs(a), abs(b), 1e-300) if a != b else 0.0
    return 0.0 if a == b else float("inf")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("campaign", type=Path, help="a campaign file (e.g. the demo's)")
    parser.add_argument("--diagnose", action="store_true", help="also run the whole diagnosis both ways")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--workers", type=int, default=usable_cpus(), help="processes now (default: usable CPUs)")
    parser.add_argument("--rank-per-stratum", type=int, default=None, help="with --diagnose: also rank on a subset")
    args = parser.parse_args()
    data = load_campaign(args.campaign)
    ways = {"this process (before)": 1, f"{args.workers} workers (now)": args.workers}
    print(f"{len(data.trajectories)} trajectories; load average at start {os.getloadavg()[0]:.2f}")
    replays = {name: probe_replays(data, args.device, workers) for name, workers in ways.items()}
    (before, f0), (now, f1) = replays.values()
    print("\nthe relaxation probe's timed replays (one batch)")
    print(f"{'replays solved in':28} {'wall s':>8}")
    for name, (wall, _) in replays.items():
        print(f"{name:28} {wall:8.1f}")
    print(f"ratio before / now: wall {before / now:.2f}; largest force difference {np.nanmax(np.abs(f0 - f1)):.1e} N")
    print(f"load average now {os.getloadavg()[0]:.2f}")
    if not args.diagnose:
        return
    runs = {name: diagnosis(data, args.device, workers) for name, workers in ways.items()}
    print("\n`twin diagnose` (s)")
    print(f"{'stage':28}" + "".join(f" {name:>26}" for name in runs))
    for stage in next(iter(runs.values()))[0]:
        print(f"{stage:28}" + "".join(f" {stages[stage]:26.1f}" for stages, _ in runs.values()))
    (old_stages, old), (new_stages, new) = runs.values()
    old_total, new_total = old_stages["total"], new_stages["total"]
    print(f"ratio before / now: wall {old_total / new_total:.2f} (target: 60 s wall)")
    same_ranking = [c["name"] for c in old["candidates"]] == [c["name"] for c in new["candidates"]]
    print(f"verdicts {old['verdict']!r} / {new['verdict']!r}; same ranking: {same_ranking}; largest relative")
    print(f"difference of any number: {largest_relative_difference(old, new):.1e}; load {os.getloadavg()[0]:.2f}")
    print(json.dumps({"before_s": old_total, "now_s": new_total}))
    if args.rank_per_stratum is not None:
        subset_stages, subset = diagnosis(data, args.device, args.workers, args.rank_per_stratum)
        used, named = len(subset["ranked_on"]["trajectories"]), subset["candidates"][0]
        same = {k: named[k] == new["candidates"][0][k] for k in ("name", "refit_rms", "heldout_rms")}
        print(f"\nranked on {used} of {len(data.trajectories)} trajectories: {subset_stages['total']:.1f} s wall")
        print(f"verdict {subset['verdict']!r} (all: {new['verdict']!r}); first candidate as all's: {same}")


if __name__ == "__main__":  # the replay workers are spawned processes
    main()
