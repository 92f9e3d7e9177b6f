"""Replays of a relaxing skin with held poses solved sparsely (now) against every event solved (before), in one
process.

While the skin relaxes, the plant re-solves a held pose every `RELAXATION_SOLVE_INTERVAL_S` (0.1 s: 50 events in
a 5 s pause). A replay now solves, of each hold, its first `HELD_SOLVES_DENSE` events, every power-of-two one and
its last (`twin.analysis.predict.held_solves`) and fills the others with the relaxation's exponential
(`fill_holds`); the baseline sets `HELD_SOLVES_DENSE` huge, so that every event is solved. Each way replays every
trajectory of a small campaign with long pauses (`Predictor.prefetch`, then `predict` each; a fresh Predictor,
inflation excluded) and the table gives the fe solves, wall seconds, their ratio, and the largest difference of
the full-rate and increment forces (N, and as a fraction of the largest |force|).

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

from twin.analysis import predict
from twin.analysis.data import CampaignData, load_campaign
from twin.analysis.predict import Prediction, Predictor, TwinModel, held_solves, solve_events
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


def fe_solves(data: CampaignData, dense: bool) -> int:
    """Events the replays of every trajectory solve (a relaxing skin's schedule), every one or the sparse ones."""
    events = [solve_events(t.raw, RELAXATION_SOLVE_INTERVAL_S)[1] for t in data.trajectories]
    return sum(len(e) if dense else int(held_solves(e).sum()) for e in events)


def replays(data: CampaignData, model: TwinModel, device: str, dense: bool) -> tuple[float, list[Prediction]]:
    """Wall seconds of a fresh Predictor's prefetch and predictions of every trajectory (inflation excluded), and
    the predictions; with `dense` every held event is solved."""
    predictor = Predictor(device)
    predictor.fe_model(apply_skin(model.skin, model.effects), model.mesh_max_edge, model.inflation)
    sparse_default = predict.HELD_SOLVES_DENSE
    predict.HELD_SOLVES_DENSE = 10**9 if dense else sparse_default
    try:
        start = time.perf_counter()
        predictor.prefetch(model, data.trajectories)
        predictions = [predictor.predict(model, t) for t in data.trajectories]
        return time.perf_counter() - start, predictions
    finally:
        predict.HELD_SOLVES_DENSE = sparse_default


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
    runs = {dense: replays(data, model, args.device, dense) for dense in (True, False)}
    (dense_s, dense), (sparse_s, sparse) = runs[True], runs[False]
    table = Table("schedule", "fe solves", "wall s", "ratio dense / sparse")
    for name, flag, seconds in (("every event (before)", True, dense_s), ("sparse holds (now)", False, sparse_s)):
        table.add_row(name, str(fe_solves(data, flag)), f"{seconds:.1f}", f"{dense_s / seconds:.2f}")
    Console().print(table)
    scale = max(float(np.nanmax(np.abs(p.force_fullrate))) for p in dense)
    differences = Table("force", "largest |dense - sparse| (N)", "of the largest |force|")
    for name, field in (("full rate", "force_fullrate"), ("increments", "increment_force")):
        diff = largest_difference([getattr(p, field) for p in dense], [getattr(p, field) for p in sparse])
        differences.add_row(name, f"{diff:.2e}", f"{diff / scale:.1e}")
    Console().print(differences)
    converged = all(p.converged.all() for p in dense + sparse)
    print(f"largest |force| {scale:.3f} N; every increment converged: {converged}")


if __name__ == "__main__":
    main()
