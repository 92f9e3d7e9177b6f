"""The loop end to end: a plant with a hidden effect, a quick campaign, compare, diagnose, improve.

The hidden effect and its size are drawn from a seed (twin.hidden) into a sealed manifest written next
to the data and read by nothing but the final reveal; the analysis only ever sees the campaign file.
The same runner serves the `twin demo` command, the hidden-effect tests and the confusion-matrix
benchmark.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from twin.analysis.compare import compare
from twin.analysis.data import load_campaign
from twin.analysis.diagnose import Diagnosis, diagnose
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.refit import EffectFit, fit_effect
from twin.analysis.report import write_report
from twin.campaign import QUICK_CONFIG, CampaignConfig, run_campaign
from twin.hidden import draw_hidden, write_sealed_manifest
from twin.plant import Plant, make_plant

DEMO_EFFECTS = (
    "time_delay",
    "ft_drift",
    "ft_crosstalk",
    "registration_offset",
    "skin_relaxation",
    "skin_stiffening",
    "skin_thickness",
    "indenter_friction",
)
"""Hidden effects `twin demo` draws from: each one leaves its own mark on the data."""

DEMO_CONFIG = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_small", "sphere_large", "cylinder_long"))
"""The demo's campaign: one sensor, three indenter sizes, normal and angled paths with unloading."""
CHECK_CONFIG = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_small", "cylinder_long"))
"""The hidden-effect checks' campaign (tests, `benchmarks/diagnose_bench.py`): one sensor, the small sphere and the
long cylinder, normal and angled paths with unloading."""


@dataclass(frozen=True)
class LoopResult:
    """What the loop found, what was hidden, and how long each stage took (s, wall)."""

    dataset: Path
    diagnosis: Diagnosis
    fit: EffectFit | None
    hidden: str | None
    seconds: dict[str, float]

    @property
    def found(self) -> str:
        """The effect the loop added ("nothing" / "unexplained" when it added none)."""
        return self.fit.name if self.fit is not None else self.diagnosis.verdict


def run_loop(
    out_dir: Path,
    hidden: str | None,
    seed: int,
    config: CampaignConfig = DEMO_CONFIG,
    workers: int = 2,
    reports: bool = True,
    say: Callable[[str], None] = print,
    predictor: Predictor | None = None,
    top: int = 3,
) -> LoopResult:
    """Hide `hidden` (None: nothing) in a plant, run `config`'s campaign into `out_dir`, then compare,
    diagnose and, when the diagnosis names an effect (or ranks one first among tied ones), add it.

    `seed` draws the hidden effect's size, the campaign's points and its noise (`loop_setup`).
    `predictor` may be shared between runs on the same paths (same seed; its fe replays are cached);
    `top` candidates are refitted.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    config, plant = loop_setup(hidden, seed, config)
    write_sealed_manifest(out_dir / "sealed_manifest.json", hidden, plant.effects, seed)
    seconds = {}
    start = time.perf_counter()
    say("1/4 running a quick campaign on a plant with a hidden effect ...")
    result = run_campaign(config, out_dir / "campaign", workers=workers, plant=plant)
    path = next(iter(result.files.values()))
    seconds["campaign"] = time.perf_counter() - start
    data = load_campaign(path)
    predictor = predictor or Predictor()
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    say("2/4 comparing and diagnosing the nominal model against the measurements ...")
    start = time.perf_counter()
    if reports:
        write_report(compare([data], model, predictor), out_dir / "report_before")
    diagnosis = diagnose([data], model, predictor, top=top)
    seconds["diagnose"] = time.perf_counter() - start
    say(f"    verdict: {diagnosis.verdict} ({diagnosis.reason})")
    fit = None
    if diagnosis.verdict not in ("nothing", "unexplained"):
        name = diagnosis.candidates[0].name
        say(f"3/4 adding {name} and refitting ...")
        start = time.perf_counter()
        fit = fit_effect([data], model, name, predictor)
        seconds["improve"] = time.perf_counter() - start
        if reports:
            write_report(compare([data], fit.model, predictor), out_dir / "report_after")
        say(f"    RMS error / noise: {fit.rms_before:.2f} -> {fit.rms_after:.2f}")
    else:
        say("3/4 nothing to add")
    say(f"4/4 the hidden effect was: {hidden or 'none'}")
    return LoopResult(path, diagnosis, fit, hidden, seconds)


def loop_setup(hidden: str | None, seed: int, config: CampaignConfig) -> tuple[CampaignConfig, Plant]:
    """The campaign and the plant of one loop, both drawn from `seed`: the hidden effect's size, the
    trajectory points and the measurement noise (the campaign's seed). The plant has no unit-to-unit
    variability and exact registration, so the hidden effect is the only difference between it and the
    nominal model besides noise and the sensor's electrode read-out."""
    plant = make_plant(
        list(config.sensors),
        seed,
        variability=0.0,
        mount_rotation_error=0.0,
        mount_translation_error=0.0,
        effects=draw_hidden(hidden, seed),
        exact_registration=True,
    )
    return replace(config, seed=seed), plant


def run_demo(
    out_dir: Path, seed: int = 0, config: CampaignConfig = DEMO_CONFIG, say: Callable[[str], None] = print
) -> LoopResult:
    """`twin demo`: the loop with a hidden effect drawn by `seed` from `DEMO_EFFECTS`."""
    hidden = DEMO_EFFECTS[int(np.random.default_rng(seed).integers(len(DEMO_EFFECTS)))]
    return run_loop(out_dir, hidden, seed, config, say=say, top=2)
