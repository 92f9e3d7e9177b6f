"""Confusion matrix of the compare-diagnose-improve loop over hidden effects.

For each seed and each effect (the library's, none, and the unlisted ones), a plant hides the effect
with a size drawn from the seed (twin.hidden), a small campaign runs on trajectory points and noise
drawn from the same seed, and the loop diagnoses and, when it names an effect, adds it. Prints a
per-case table (rank of the hidden effect, verdict, RMS / noise before, after and held out, wall
seconds per stage), the confusion matrix hidden -> added over all seeds, the score per seed, and the
in-library top-1 rate. A library effect whose true size (read from the sealed manifest after the loop)
would leave, in expectation, a residual within the noise test's threshold (`_signal`) is below what the
noise test can see on these data: the loop rightly says "nothing", and such a case is counted apart, not
as a miss.

    python benchmarks/diagnose_bench.py [--seeds 5,6,7] [--effects a,b|all] [--out runs/diagnose_bench] [--json FILE]

The default (three seeds, three effects) takes minutes on two cores; `--effects all` the whole library.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from twin.analysis.data import load_campaign
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.residual import base_residual
from twin.campaign import QUICK_CONFIG
from twin.demo import LoopResult, run_loop
from twin.effects import EFFECTS, UNLISTED_EFFECTS
from twin.hidden import read_sealed_manifest

CONFIG = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_small", "cylinder_long"))
NONE = "none"
QUICK_EFFECTS = "none,time_delay,registration_offset"
"""The default cases: nothing hidden, one measurement effect, one physics effect."""


def _signal(result: LoopResult, manifest: Path, predictor: Predictor) -> dict:
    """The hidden effect at its true size (the sealed manifest) against the noise test of its case's data: the
    chi-square of the nominal model's profiled, whitened prediction change to the model with that effect
    (`Base.shifted`, noise-free), the whitened RMS a residual of that signal plus the noise has in expectation,
    sqrt(1 + chi2 / n), and whether that exceeds the noise test's RMS threshold on the case's base residual."""
    data = load_campaign(result.dataset)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    base = base_residual([data], model, predictor)
    shift = base.shifted(predictor, model.with_effects(read_sealed_manifest(manifest)["values"]))
    chi2 = float(np.nansum(shift**2))
    expected = float(np.sqrt(1.0 + chi2 / np.isfinite(shift).sum()))
    threshold = base.noise_test(base.residual.values).rms_threshold
    return {"signal_chi2": chi2, "expected_rms": expected, "above_noise_test": expected > threshold}


def _case(out: Path, hidden: str, seed: int, predictor: Predictor) -> dict:
    start = time.perf_counter()
    result = run_loop(
        out / f"seed{seed}_{hidden}",
        None if hidden == NONE else hidden,
        seed,
        CONFIG,
        reports=False,
        say=lambda _: None,
        predictor=predictor,
        top=1,
    )
    names = [c.name for c in result.diagnosis.candidates]
    fit = result.fit
    manifest = out / f"seed{seed}_{hidden}" / "sealed_manifest.json"
    signal = _signal(result, manifest, predictor) if hidden in EFFECTS else {}
    return {
        "seed": seed,
        "hidden": hidden,
        "added": result.found,
        "verdict": result.diagnosis.verdict,
        "rank_of_hidden": names.index(hidden) + 1 if hidden in names else None,
        "runner_up": names[1] if len(names) > 1 else None,
        "evidence_margin": result.diagnosis.candidates[0].evidence - result.diagnosis.candidates[1].evidence,
        "rms_before": result.diagnosis.base_rms,
        "noise_rms_threshold": result.diagnosis.rms_threshold,
        "rms_after": fit.rms_after if fit else None,
        "heldout_rms": fit.heldout_rms if fit else None,
        "refitted": [c.name for c in result.diagnosis.candidates if c.refitted],
        "seconds": {**result.seconds, "total": time.perf_counter() - start},
        "reason": result.diagnosis.reason,
        **signal,
    }


def _print(cases: list[dict], effects: list[str]) -> None:
    header = ("seed", "hidden", "rank", "verdict", "added", "before", "after", "held", "s")
    print(f"{header[0]:>4} {header[1]:20} {header[2]:>4} {header[3]:20} {header[4]:20}", end="")
    print("".join(f" {h:>7}" for h in header[5:]))
    for c in cases:

        def fmt(v: float | None) -> str:
            return "-" if v is None else f"{v:.2f}"

        print(
            f"{c['seed']:>4} {c['hidden']:20} {c['rank_of_hidden'] or '-':>4} {c['verdict']:20} {c['added']:20} "
            f"{fmt(c['rms_before']):>7} {fmt(c['rms_after']):>7} {fmt(c['heldout_rms']):>7} "
            f"{c['seconds']['total']:7.0f}"
        )
    columns = sorted({c["added"] for c in cases})
    print("\nconfusion (rows: hidden, columns: what the loop added or said)")
    print(" " * 20 + " ".join(f"{c[:10]:>10}" for c in columns))
    for hidden in effects:
        counts = [sum(1 for c in cases if c["hidden"] == hidden and c["added"] == col) for col in columns]
        print(f"{hidden:20}" + " ".join(f"{n:>10}" for n in counts))
    print(f"\ncorrect: {sum(map(_correct, cases))}/{len(cases)}")
    for seed in sorted({c["seed"] for c in cases}):
        mine = [c for c in cases if c["seed"] == seed]
        print(f"  seed {seed}: {sum(map(_correct, mine))}/{len(mine)}")
    library = [c for c in cases if c["hidden"] in EFFECTS]
    seen = [c for c in library if c["above_noise_test"]]
    unseen = [f"seed {c['seed']} {c['hidden']} ({c['expected_rms']:.3f}x)" for c in library if c not in seen]
    print(f"in-library top-1: {sum(map(_correct, library))}/{len(library)}; ", end="")
    print(f"on effects the noise test can see: {sum(map(_correct, seen))}/{len(seen)}; ", end="")
    print(f"below the noise test: {', '.join(unseen) or 'none'}")


def _correct(case: dict) -> bool:
    """The loop added the hidden effect, claimed nothing on none, or called an unlisted one unexplained."""
    return (
        case["added"] == case["hidden"]
        or (case["hidden"] == NONE and case["added"] == "nothing")
        or (case["hidden"] in UNLISTED_EFFECTS and case["added"] == "unexplained")
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", default="5,6,7", help="comma-separated seeds")
    parser.add_argument(
        "--effects", default=QUICK_EFFECTS, help="comma-separated effects, or all (the library, none, unlisted)"
    )
    parser.add_argument("--out", type=Path, default=Path("runs/diagnose_bench"))
    parser.add_argument("--json", type=Path, default=None, help="write every case here")
    args = parser.parse_args()
    effects = [*sorted(EFFECTS), NONE, *sorted(UNLISTED_EFFECTS)] if args.effects == "all" else args.effects.split(",")
    unknown = set(effects) - set(EFFECTS) - set(UNLISTED_EFFECTS) - {NONE}
    if unknown:
        parser.error(f"unknown effects {sorted(unknown)}")
    cases = []
    for seed in (int(s) for s in args.seeds.split(",")):
        predictor = Predictor()  # same seed, same points: fe replays are shared between its cases
        for hidden in effects:
            cases.append(_case(args.out, hidden, seed, predictor))
            print(json.dumps(cases[-1]), flush=True)
            if args.json:
                args.json.write_text(json.dumps(cases, indent=2))
    _print(cases, effects)


if __name__ == "__main__":
    main()
