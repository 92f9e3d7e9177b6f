"""Replays of a relaxing skin with held poses solved sparsely (now) against every event solved (before), in one
process.

While the skin relaxes, the plant re-solves a held pose every `RELAXATION_SOLVE_INTERVAL_S` (0.1 s: 50 events in
a 5 s pause). A replay now solves, of each hold, its first `HELD_SOLVES_FIRST` events and its last
(`twin.analysis.predict.held_solves`) and fills the others with the relaxation's exponential (`fill_holds`); the
baseline (`Predictor(held_first=...)` above any hold's events) solves every event, and a middle schedule its first
five and its last. Each way replays every trajectory of a small campaign with long pauses (`Predictor.prefetch`,
then `predict` each; a fresh Predictor, inflation excluded) and the tables give the fe solves, wall seconds, their
ratio to the baseline, and the largest difference from it of the full-rate and increment forces (N, and as a
fraction of the largest |force|).

    python benchmarks/hold_solves.py [--campaign FILE] [--out runs/hold_solves] [--pause-s 5.0]
        [--normal-depth-mm 1.0] [--angled-depth-mm 0.5] [--fraction 0.15] [--time-s 1.0] [--device cpu]

Without --campaign the campaign (sensor 2, sphere_medium and cylinder_long, 2 mm mesh, `QUICK_SETTINGS` with
these depths and pauses) is built under --out once and reused.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import warp as wp
from rich.console import Console
from rich.table import Table

from twin.analysis.data import CampaignData, load_campaign
from twin.analysis.predict import HELD_SOLVES_FIRST, Prediction, Predictor, TwinModel, held_solves, solve_events
from twin.campaign import QUICK_CONFIG, run_campaign
from twin.effects import apply_skin
from twin.protocol import QUICK_SETTINGS
from twin.sim_backend import RELAXATION_SOLVE_INTERVAL_S

SENSOR = 2
INDENTERS = ("sphere_medium", "cylinder_long")


def campaign_file(out: Path, normal_depth: float, angled_depth: float, pause_s: float) -> Path:
    """The benchmark's campaign (depths m, pauses s) under `out`, built on the first call and reused after."""
    folder = out / f"campaign_n{normal_depth * 1e3:g}mm_a{angled_depth * 1e3:g}mm_p{pause_s:g}s"
    path = folder / f"biotac{SENSOR}.hdf5"
    if not path.exists():
        settings = replace(QUICK_SETTINGS, normal_depth=normal_depth, angled_depth=angled_depth, pause_s=pause_s)
        config = replace(QUICK_CONFIG, sensors=(SENSOR,), indenters=INDENTERS, settings=settings)
        path = run_campaign(config, folder, workers=1).files[SENSOR]
    return path


EVERY_EVENT = 10**9
"""`held_first` that solves every event of every hold (the baseline)."""


def fe_solves(data: CampaignData, held_first: int) -> int:
    """Events the replays of every trajectory solve (a relaxing skin's schedule) with `held_first` (`held_solves`)."""
    events = [solve_events(t.raw, RELAXATION_SOLVE_INTERVAL_S)[1] for t in data.trajectories]
    return sum(int(held_solves(e, held_first).sum()) for e in events)


def replays(data: CampaignData, model: TwinModel, device: str, held_first: int) -> tuple[float, list[Prediction]]:
    """Wall seconds of a fresh Predictor's prefetch and predictions of every trajectory (inflation excluded), and
    the predictions, each hold solved at its first `held_first` events and its last."""
    predictor = Predictor(device, held_first=held_first)
    predictor.fe_model(apply_skin(model.skin, model.effects), model.mesh_max_edge, model.inflation)
    start = time.perf_counter()
    predictor.prefetch(model, data.trajectories)
    predictions = [predictor.predict(model, t) for t in data.trajectories]
    return time.perf_counter() - start, predictions


def largest_difference(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    """Largest absolute difference (NaN-skipping) between two lists of arrays of matching shapes."""
    return max(float(np.nanmax(np.abs(x - y))) for x, y in zip(a, b, strict=True))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--campaign", type=Path, default=None, help="a campaign file (default: build one)")
    parser.add_argument("--out", type=Path, default=Path("runs/hold_solves"), help="where the campaign is cached")
    parser.add_argument("--pause-s", type=float, default=5.0, help="pause at each increment (s; the paper's 5)")
    parser.add_argument("--normal-depth-mm", type=float, default=1.0)
    parser.add_argument("--angled-depth-mm", type=float, default=0.5)
    parser.add_argument("--fraction", type=float, default=0.15, help="skin_relaxation fraction")
    parser.add_argument("--time-s", type=float, default=1.0, help="skin_relaxation time (s)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    start = time.perf_counter()
    depths = args.normal_depth_mm * 1e-3, args.angled_depth_mm * 1e-3
    path = args.campaign or campaign_file(args.out, *depths, args.pause_s)
    data = load_campaign(path)
    print(f"{path}: {len(data.trajectories)} trajectories (ready in {time.perf_counter() - start:.1f} s)")
    relaxing = {"skin_relaxation": {"fraction": args.fraction, "time_s": args.time_s}}
    model = TwinModel(effects=relaxing, mesh_max_edge=data.mesh_max_edge)
    wp.force_load(device=args.device)  # every kernel module loaded before either timed run
    schedules = {
        "every event (baseline)": EVERY_EVENT,
        "first 5 and last": 5,
        "first and last (now)": HELD_SOLVES_FIRST,
    }
    runs = {name: replays(data, model, args.device, first) for name, first in schedules.items()}
    base_s, base = runs["every event (baseline)"]
    scale = max(float(np.nanmax(np.abs(p.force_fullrate))) for p in base)
    table = Table("schedule", "fe solves", "wall s", "ratio baseline / it", "full rate |diff| N", "increments |diff| N")
    for name, first in schedules.items():
        seconds, predictions = runs[name]
        diffs = [
            largest_difference([getattr(p, field) for p in base], [getattr(p, field) for p in predictions])
            for field in ("force_fullrate", "increment_force")
        ]
        row = [name, str(fe_solves(data, first)), f"{seconds:.1f}", f"{base_s / seconds:.2f}"]
        table.add_row(*row, *(f"{d:.2e} ({d / scale:.1e})" for d in diffs))
    Console().print(table)
    converged = all(p.converged.all() for _, predictions in runs.values() for p in predictions)
    print(f"largest |force| {scale:.3f} N; every increment converged: {converged}")


if __name__ == "__main__":
    main()
