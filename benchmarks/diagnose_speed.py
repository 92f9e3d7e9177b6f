"""Speed of `twin diagnose` on a campaign file, and of the replays its relaxation candidate costs, old warm start
against new in one process.

The skin_relaxation candidate is linearised at its probe (a relaxing fraction of 0.15): its replays are timed
(the skin re-solved every `RELAXATION_SOLVE_INTERVAL_S` while a pose is held), about 8 times the solves of an
untimed replay, and were a third of the whole diagnosis on the demo campaign (session 15). Since 2026-11-27 a
pose held after a held one starts its Newton solve from the creep's extrapolation (`BatchedStepper._predict`);
`creep_start=False` is the warm start before (the last state). Part 1 replays every trajectory of the file under
the probe's skin both ways, on one `BatchedStepper` stepped in lock step (the same for both), and prints wall,
Newton rounds, linear solves and the largest force difference (N) between the two (both converge to the same
tolerances, so it is of the order of the Newton tolerance). Part 2 (`--diagnose`) times the whole
`twin diagnose` (nominal model, 3 refits) with the new warm start, per stage.

    python benchmarks/diagnose_speed.py CAMPAIGN.hdf5 [--diagnose] [--device cpu]

The demo campaign: `twin demo` writes it (runs/demo/campaign/biotac2.hdf5).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from fe.batched_stepper import BatchedStepper
from twin.analysis.data import load_campaign
from twin.analysis.diagnose import diagnose
from twin.analysis.predict import Predictor, TwinModel, _pose_trajectory
from twin.effects import EFFECTS

RELAXATION = "skin_relaxation"


def timed_replays(path: Path, creep_start: bool, device: str) -> dict:
    """Replay every trajectory of the file under the relaxation probe's skin on one lock-stepped BatchedStepper;
    wall (s), Newton rounds, linear solves and each trajectory's forces (K, 3) N (NaN after a failure)."""
    data = load_campaign(path)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge).with_effects({RELAXATION: EFFECTS[RELAXATION].probe})
    predictor = Predictor(device)
    poses = [_pose_trajectory(t, predictor._plan(model, t)) for t in data.trajectories]
    skin = predictor._model_fe(model).inflated_skin()
    stepper = BatchedStepper(skin, [p.indenter for p in poses], device)
    stepper.creep_start = creep_start
    lengths = np.array([len(p.rotations) for p in poses])
    forces = np.full((len(poses), lengths.max(), 3), np.nan)
    going = np.ones(len(poses), dtype=bool)
    start = time.perf_counter()
    for k in range(lengths.max()):
        active = going & (k < lengths)
        last = np.minimum(k, lengths - 1)
        rotation = np.stack([p.rotations[j] for p, j in zip(poses, last, strict=True)])
        translation = np.stack([p.translations[j] for p, j in zip(poses, last, strict=True)])
        times = np.array([p.times[j] for p, j in zip(poses, last, strict=True)])
        for i, result in enumerate(stepper.step(rotation, translation, active, times)):
            if result is None:
                continue
            going[i] &= result.converged
            forces[i, k] = result.force if result.converged else np.nan
    wall = time.perf_counter() - start
    counters = stepper.shell.counters
    return {"wall": wall, "rounds": counters["evaluations"], "solves": counters["linear_solves"], "forces": forces}


def diagnose_stages(path: Path, device: str) -> dict[str, float]:
    """Wall seconds of `twin diagnose`'s stages on the file (nominal model, 3 refits, as the CLI)."""
    start = time.perf_counter()
    data = load_campaign(path)
    stamps: dict[str, float] = {}
    result = diagnose(
        [data],
        TwinModel(mesh_max_edge=data.mesh_max_edge),
        Predictor(device),
        on_progress=lambda stage, _: stamps.setdefault(stage, time.perf_counter() - start),
    )
    total = time.perf_counter() - start
    evidence, refit = stamps.get("evidence", total), stamps.get("refit", total)
    print(f"verdict: {result.verdict} ({result.reason})")
    return {"base and sensitivities": evidence, "scores": refit - evidence, "refits and held out": total - refit}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("campaign", type=Path, help="a campaign file (e.g. the demo's)")
    parser.add_argument("--diagnose", action="store_true", help="also time the whole diagnosis")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    old = timed_replays(args.campaign, False, args.device)
    new = timed_replays(args.campaign, True, args.device)
    difference = np.nanmax(np.abs(old["forces"] - new["forces"]))
    print("\nthe relaxation probe's timed replays, every trajectory of the file, lock-stepped")
    print(f"{'warm start at a held pose':34} {'wall s':>8} {'rounds':>8} {'solves':>8}")
    for name, run in (("last state (before)", old), ("creep extrapolated (now)", new)):
        print(f"{name:34} {run['wall']:8.1f} {run['rounds']:8.0f} {run['solves']:8.0f}")
    print(f"ratio (before / now): {old['wall'] / new['wall']:.2f}; largest force difference {difference:.2e} N")
    print(f"load average: {os.getloadavg()[0]:.2f}")
    if args.diagnose:
        stages = diagnose_stages(args.campaign, args.device)
        print("\n`twin diagnose` with the new warm start (s)")
        for name, seconds in stages.items():
            print(f"{name:34} {seconds:8.1f}")
        print(f"{'total':34} {sum(stages.values()):8.1f}   (target: 60 s; load average {os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
