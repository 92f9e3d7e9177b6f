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

With `--generated`, each seed's null campaign (the `none` case's) is also changed by the independent generator
(tests/effect_generator.py: code apart from the plant, the effect library and the analysis) with sizes drawn from
the seed: an F/T gain on z only (expected `ft_calibration`), a stream delay of whole samples (`time_delay`), the
axis that moves most clipped between its rest and peak readings (`ft_saturation`), a PDC drift (`pdc_drift`) and a
quantised F/T reading (expected "nothing"); each is diagnosed (one refit) and counted apart.

With `--pairs a+b,c+d`, each seed's plant hides two library effects at once (each drawn from the seed as alone), and
the search in turn runs (`twin.analysis.in_turn.find_in_turn`, what `twin diagnose --in-turn 2` does): diagnose,
add what is named and refit every effect jointly (`fit_jointly`), diagnose again; an "unexplained" verdict's closest
candidate (`Diagnosis.next_step`) is added once, on trial (`via: closest`). A pair is right when the search ends at
the noise with both effects added, in either order; the RMS / noise before, after the last fit and held out is
printed.

With `--realistic`, each case's plant is this repository's default realistic one (`twin.plant.make_plant` defaults: 5 %
unit-to-unit skin, the arms' joint offsets and registration error, the mount error) with the effect hidden in it, its
campaign pressed past the registration error (`REALISTIC_SETTINGS`), and the diagnosis fits the nuisances first
(`diagnose(..., nuisances=True)`, what `twin diagnose --nuisances` does): a null must end "nothing beyond the
nuisances", a hidden effect be named. The nuisance effects themselves (`NUISANCE_EFFECTS`) are not hidden there
(the nuisance stage fits them). `--generated` then applies to each seed's realistic null. With `--jobs N` the cases run
in N processes at once (campaigns first, then diagnoses; replays are not shared between processes).

    python benchmarks/diagnose_bench.py [--seeds 5,6,7] [--effects a,b|all|""] [--generated] [--pairs a+b,...]
        [--realistic] [--jobs N] [--out runs/diagnose_bench] [--json FILE]

The default (three seeds, three effects) takes minutes on two cores; `--effects all` the whole library.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import replace
from functools import partial
from pathlib import Path

import h5py
import numpy as np

from twin.analysis.data import load_campaign
from twin.analysis.diagnose import diagnose
from twin.analysis.in_turn import find_in_turn
from twin.analysis.nuisances import NUISANCE_EFFECTS
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.refit import fit_jointly
from twin.analysis.residual import base_residual
from twin.analysis.verdict import NOTHING_BEYOND_NUISANCES
from twin.campaign import run_campaign
from twin.demo import CHECK_CONFIG, LoopResult, loop_setup, run_loop
from twin.effects import EFFECTS, UNLISTED_EFFECTS
from twin.hidden import draw_hidden, read_sealed_manifest, write_sealed_manifest
from twin.lanes import usable_cpus
from twin.plant import make_plant

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import effect_generator  # noqa: E402  (the independent generator lives with the tests)

CONFIG = CHECK_CONFIG
NONE = "none"
QUICK_EFFECTS = "none,time_delay,registration_offset"
"""The default cases: nothing hidden, one measurement effect, one physics effect."""
REALISTIC_SETTINGS = replace(CONFIG.settings, normal_depth=1.5e-3, angled_depth=1.0e-3)
"""The realistic cases' presses (m): past the realistic plants' registration error (about a millimetre; at the check
campaign's 0.4 / 0.2 mm some indenters never touch their skin)."""


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


GENERATED = {
    "gen_ft_z_gain": "ft_calibration",
    "gen_ft_delay": "time_delay",
    "gen_ft_clip": "ft_saturation",
    "gen_pdc_drift": "pdc_drift",
    "gen_quantised_null": "nothing",
}
"""The independent generator's cases (`--generated`) and the verdict each must give."""


def _generated(name: str, null: Path, out: Path, rng: np.random.Generator) -> tuple[Path, dict]:
    """The seed's null campaign with the generated effect `name` (sizes from `rng`) applied by
    tests/effect_generator.py, code apart from the plant and the analysis; (its file, the sizes)."""
    if name == "gen_ft_z_gain":
        gain = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.08, 0.15) + 1.0)
        return effect_generator.apply_ft_map(null, out, np.diag([1.0, 1.0, gain])), {"zz": gain}
    if name == "gen_ft_delay":
        samples = int(rng.integers(4, 12))
        return effect_generator.apply_ft_delay(null, out, samples), {"samples": samples}
    if name == "gen_ft_clip":
        with h5py.File(null, "r") as f:
            readings = np.concatenate([f[f"raw/{k}/wrench"][()][:, :3] for k in f["raw"]])
        rest, peak = np.abs(readings[0]), np.abs(readings).max(axis=0)
        axis = int(np.argmax(peak - rest))
        limits = np.full(3, 1e3)
        limits[axis] = rest[axis] + rng.uniform(0.3, 0.7) * (peak[axis] - rest[axis])
        return effect_generator.apply_ft_clip(null, out, limits), {"axis": "xyz"[axis], "limit": limits[axis]}
    if name == "gen_pdc_drift":
        rate = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.2, 0.5))
        return effect_generator.apply_pdc_map(null, out, 1.0, rate), {"rate": rate}
    step = float(rng.uniform(0.02, 0.04))
    return effect_generator.apply_ft_quantise(null, out, step), {"step": step}


def _generated_case(out: Path, name: str, seed: int, predictor: Predictor) -> dict:
    """Diagnose the seed's null campaign (the `none` case's, run first when missing) with a generated effect."""
    null = out / f"seed{seed}_{NONE}" / "campaign" / f"biotac{CONFIG.sensors[0]}.hdf5"
    if not null.exists():
        _case(out, NONE, seed, predictor)
    start = time.perf_counter()
    path, sizes = _generated(name, null, out / f"seed{seed}_{name}.hdf5", _generated_rng(seed, name))
    return _diagnosed(path, seed, name, sizes, predictor, start, nuisances=False)


def _generated_rng(seed: int, name: str) -> np.random.Generator:
    """The sizes of generated effect `name` on seed `seed`'s null campaign."""
    return np.random.default_rng(np.random.SeedSequence([seed, sum(map(ord, name))]))


def _diagnosed(
    path: Path, seed: int, hidden: str, sizes: dict, predictor: Predictor, start: float, nuisances: bool
) -> dict:
    """One diagnosis (one refit; the nuisances fitted first with `nuisances`) of the campaign file `path`, where
    `hidden` was hidden at `sizes`: the case's row."""
    data = load_campaign(path)
    diagnosis = diagnose([data], TwinModel(mesh_max_edge=data.mesh_max_edge), predictor, top=1, nuisances=nuisances)
    names = [c.name for c in diagnosis.candidates]
    ambiguous = diagnosis.verdict == "ambiguous"  # the first of the tied ones is added, as the loop does
    first = next((c for c in diagnosis.candidates if ambiguous or c.name == diagnosis.verdict), None)
    named = first is not None
    stage, joint = diagnosis.nuisances or {}, diagnosis.jointly or {}
    jointly = joint.get("named", False)  # named by its fit jointly with the nuisances: that fit's figures
    return {
        "seed": seed,
        "hidden": hidden,
        "sizes": sizes,
        "added": first.name if named else diagnosis.verdict,
        "verdict": diagnosis.verdict,
        "rank_of_hidden": names.index(hidden) + 1 if hidden in names else None,
        "fitted": first.refit_parameters if named else None,
        "rms_before": diagnosis.base_rms,
        "noise_rms_threshold": diagnosis.rms_threshold,
        "rms_after": joint["rms_after"] if jointly else first.refit_rms if named else None,
        "heldout_rms": joint["heldout_predictive_rms"] if jointly else first.heldout_rms if named else None,
        **{f"nuisances_{k}": stage.get(k) for k in ("rms_before", "rms_after", "heldout_predictive_rms")},
        "jointly": {k: joint[k] for k in ("effect", "named", "rms_after", "heldout_predictive_rms")} if joint else None,
        "cannot_tell_apart": stage.get("cannot_tell_apart"),
        "seconds": {"total": time.perf_counter() - start},
        "reason": diagnosis.reason,
    }


def _realistic_campaign(out: Path, hidden: str, seed: int) -> Path:
    """The campaign file of seed `seed`'s realistic plant with `hidden` (`NONE`: nothing) hidden at its draw for
    the seed, made once (`REALISTIC_SETTINGS`)."""
    folder = out / f"realistic_seed{seed}_{hidden}"
    path = folder / "campaign" / f"biotac{CONFIG.sensors[0]}.hdf5"
    if not path.exists():
        plant = make_plant(list(CONFIG.sensors), seed, effects=draw_hidden(None if hidden == NONE else hidden, seed))
        folder.mkdir(parents=True, exist_ok=True)
        write_sealed_manifest(folder / "sealed_manifest.json", hidden, plant.effects, seed)
        config = replace(CONFIG, seed=seed, settings=REALISTIC_SETTINGS)
        run_campaign(config, folder / "campaign", workers=2, plant=plant)
    return path


def _realistic_case(out: Path, hidden: str, seed: int, workers: int) -> dict:
    """`hidden` on seed `seed`'s realistic plant (a generated effect: applied to its null's file), diagnosed with
    the nuisances fitted first, replays in `workers` processes."""
    start = time.perf_counter()
    if hidden in GENERATED:
        made = out / f"realistic_seed{seed}_{hidden}.hdf5"
        path, sizes = _generated(hidden, _realistic_campaign(out, NONE, seed), made, _generated_rng(seed, hidden))
    else:
        path, sizes = _realistic_campaign(out, hidden, seed), draw_hidden(None if hidden == NONE else hidden, seed)
    return _diagnosed(path, seed, hidden, sizes, Predictor(workers=workers), start, nuisances=True)


def _realistic(out: Path, seeds: list[int], names: list[str], jobs: int) -> list[dict]:
    """Every realistic case, `jobs` at once: the campaigns first (each seed's null before its generated cases),
    then the diagnoses (each effect on every seed in turn), each printed as it ends."""
    plants = sorted({(seed, NONE if name in GENERATED else name) for seed in seeds for name in names})
    cases = []
    with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        made = pool.map(partial(_realistic_campaign, out), [name for _, name in plants], [seed for seed, _ in plants])
        for (seed, name), _ in zip(plants, made, strict=True):
            print(f"campaign of seed {seed}'s realistic plant with {name} made", flush=True)
        workers = max(1, usable_cpus() // jobs)
        runs = [pool.submit(_realistic_case, out, name, seed, workers) for name in names for seed in seeds]
        for run in as_completed(runs):
            cases.append(run.result())
            print(json.dumps(cases[-1]), flush=True)
    return cases


def _pair_case(out: Path, pair: str, seed: int, predictor: Predictor) -> dict:
    """Two library effects hidden at once (`pair` "a+b", each at its own draw for `seed`); the search in turn
    (`twin.analysis.in_turn.find_in_turn`, as `twin diagnose --in-turn 2`, one refit a diagnosis)."""
    start = time.perf_counter()
    names = pair.split("+")
    config, plant = loop_setup(names[0], seed, CONFIG)
    plant = replace(plant, effects={**plant.effects, **draw_hidden(names[1], seed)})
    result = run_campaign(config, out / f"seed{seed}_{pair}" / "campaign", workers=2, plant=plant)
    data = load_campaign(next(iter(result.files.values())))
    found = find_in_turn(
        lambda model: diagnose([data], model, predictor, top=1),
        lambda model, name: fit_jointly([data], model, name, predictor),
        TwinModel(mesh_max_edge=data.mesh_max_edge),
        additions=len(names),
    )
    fits = [t.fit for t in found.turns if t.fit is not None]
    steps = [
        {"verdict": t.diagnosis.verdict, "rms_before": t.diagnosis.base_rms, "added": t.added, "via": t.via}
        for t in found.turns
    ]
    return {
        "seed": seed,
        "hidden": pair,
        "hidden_values": plant.effects,
        "added": "+".join(found.added) or found.verdict,
        "verdict": found.verdict,
        "rank_of_hidden": None,
        "rms_before": found.turns[0].diagnosis.base_rms,
        "rms_after": fits[-1].rms_after if fits else None,
        "heldout_rms": fits[-1].heldout_rms if fits else None,
        "steps": steps,
        "fitted": found.model.effects,
        "seconds": {"total": time.perf_counter() - start},
        "reason": found.reason,
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
    seen = [c for c in library if c.get("above_noise_test", True)]
    unseen = [f"seed {c['seed']} {c['hidden']} ({c['expected_rms']:.3f}x)" for c in library if c not in seen]
    print(f"in-library top-1: {sum(map(_correct, library))}/{len(library)}; ", end="")
    print(f"on effects the noise test can see: {sum(map(_correct, seen))}/{len(seen)}; ", end="")
    print(f"below the noise test: {', '.join(unseen) or 'none'}")
    generated = [c for c in cases if c["hidden"] in GENERATED]
    if generated:
        print(f"generated by tests/effect_generator.py: {sum(map(_correct, generated))}/{len(generated)}")
    pairs = [c for c in cases if "+" in c["hidden"]]
    if pairs:
        print(f"pairs, both named in turn: {sum(map(_correct, pairs))}/{len(pairs)}")


def _correct(case: dict) -> bool:
    """The loop added the hidden effect (both of a pair, in either order), claimed nothing (beyond the nuisances, on a
    realistic plant) on none, or called an unlisted one unexplained."""
    return (
        case["added"] == case["hidden"]
        or (
            "+" in case["hidden"]
            and sorted(case["added"].split("+")) == sorted(case["hidden"].split("+"))
            and case["verdict"] == " + ".join(case["added"].split("+"))  # and the residual reached the noise
        )
        or case["added"] == GENERATED.get(case["hidden"])
        or (case["hidden"] == NONE and case["added"] == "nothing")
        or (case["hidden"] in (NONE, "gen_quantised_null") and case["added"] == NOTHING_BEYOND_NUISANCES)
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
    parser.add_argument(
        "--generated",
        action="store_true",
        help="also each seed's null campaign with effects applied by tests/effect_generator.py (GENERATED)",
    )
    parser.add_argument("--pairs", default="", help="comma-separated pairs a+b of library effects hidden together")
    parser.add_argument(
        "--realistic", action="store_true", help="realistic plants, the nuisances fitted first (see above)"
    )
    parser.add_argument("--jobs", type=int, default=1, help="realistic cases run at once (processes)")
    args = parser.parse_args()
    library = sorted(set(EFFECTS) - set(NUISANCE_EFFECTS)) if args.realistic else sorted(EFFECTS)
    every = [*library, NONE, *sorted(UNLISTED_EFFECTS)]
    effects = every if args.effects == "all" else [e for e in args.effects.split(",") if e]
    unknown = set(effects) - set(EFFECTS) - set(UNLISTED_EFFECTS) - {NONE}
    if unknown:
        parser.error(f"unknown effects {sorted(unknown)}")
    pairs = [p for p in args.pairs.split(",") if p]
    if args.realistic and (pairs or set(effects) & set(NUISANCE_EFFECTS)):
        parser.error(f"--realistic runs no pairs and hides none of the nuisances {sorted(NUISANCE_EFFECTS)}")
    if args.jobs < 1 or (args.jobs > 1 and not args.realistic):
        parser.error("--jobs is a positive count of realistic cases run at once (with --realistic)")
    for pair in pairs:
        names = pair.split("+")
        if len(names) != 2 or names[0] == names[1] or not set(names) <= set(EFFECTS):
            parser.error(f"a pair is two different library effects a+b, got {pair!r}")
    seeds = [int(s) for s in args.seeds.split(",")]
    names = effects + (list(GENERATED) if args.generated else [])
    if args.realistic:
        cases = _realistic(args.out, seeds, names, args.jobs)
        if args.json:
            args.json.write_text(json.dumps(cases, indent=2))
        _print(cases, names)
        return
    cases = []
    for seed in seeds:
        predictor = Predictor()  # same seed, same points: fe replays are shared between its cases
        generated = [partial(_generated_case, args.out, name, seed, predictor) for name in GENERATED]
        plant = [partial(_case, args.out, hidden, seed, predictor) for hidden in effects]
        both = [partial(_pair_case, args.out, pair, seed, predictor) for pair in pairs]
        for case in plant + (generated if args.generated else []) + both:
            cases.append(case())
            print(json.dumps(cases[-1]), flush=True)
            if args.json:
                args.json.write_text(json.dumps(cases, indent=2))
    _print(cases, names + pairs)


if __name__ == "__main__":
    main()
