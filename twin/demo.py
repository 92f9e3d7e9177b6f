"""The loop end to end: a plant with a hidden effect, a quick campaign, compare, diagnose, improve.

The hidden effect and its size are drawn from a seed into a sealed manifest (written next to the
data, read by nothing but the final reveal); the analysis only ever sees the campaign file.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from twin.analysis.compare import compare
from twin.analysis.data import load_campaign
from twin.analysis.diagnose import Diagnosis, EffectFit, diagnose, fit_effect
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.report import write_report
from twin.campaign import QUICK_CONFIG, CampaignConfig, run_campaign
from twin.effects import EffectValues
from twin.plant import make_plant

DEMO_EFFECTS: dict[str, EffectValues] = {
    "time_delay": {"time_delay": {"seconds": 0.08}},
    "ft_drift": {"ft_drift": {"fz_rate": 0.004, "fx_rate": -0.002}},
    "ft_gain": {"ft_gain": {"scale": 1.12}},
    "ft_crosstalk": {"ft_crosstalk": {"zx": 0.08, "xz": -0.06}},
}
"""Hidden effects the demo draws from, with sizes well above the noise."""

DEMO_CONFIG = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_small", "sphere_large", "cylinder_long"))


@dataclass(frozen=True)
class DemoResult:
    """What the demo found, and what was hidden."""

    dataset: Path
    diagnosis: Diagnosis
    fit: EffectFit | None
    hidden: str


def draw_hidden_effect(seed: int) -> tuple[str, EffectValues]:
    """The demo's hidden effect for `seed` (name, values)."""
    names = sorted(DEMO_EFFECTS)
    name = names[int(np.random.default_rng(seed).integers(len(names)))]
    return name, DEMO_EFFECTS[name]


def run_demo(
    out_dir: Path, seed: int = 0, config: CampaignConfig = DEMO_CONFIG, say: Callable[[str], None] = print
) -> DemoResult:
    """Run the whole loop into `out_dir`; `say` receives progress lines."""
    out_dir = Path(out_dir)
    hidden, effects = draw_hidden_effect(seed)
    sealed = out_dir / "sealed_manifest.json"
    out_dir.mkdir(parents=True, exist_ok=True)
    sealed.write_text(json.dumps({"hidden_effect": hidden, "values": effects, "seed": seed}))
    plant = make_plant(
        list(config.sensors),
        seed,
        variability=0.0,
        mount_rotation_error=0.0,
        mount_translation_error=0.0,
        effects=effects,
        exact_registration=True,
    )
    say("1/4 running a quick campaign on a plant with a hidden effect ...")
    result = run_campaign(config, out_dir / "campaign", workers=2, plant=plant)
    path = next(iter(result.files.values()))
    data = load_campaign(path)
    predictor = Predictor()
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    say("2/4 comparing and diagnosing the nominal model against the measurements ...")
    write_report(compare([data], model, predictor), out_dir / "report_before")
    diagnosis = diagnose([data], model, predictor)
    say(f"    verdict: {diagnosis.verdict} ({diagnosis.reason})")
    fit = None
    if diagnosis.verdict not in ("nothing", "unexplained"):
        say(f"3/4 adding {diagnosis.verdict} and refitting ...")
        fit = fit_effect([data], model, diagnosis.verdict, predictor)
        write_report(compare([data], fit.model, predictor), out_dir / "report_after")
        say(f"    RMS error / noise: {fit.rms_before:.2f} -> {fit.rms_after:.2f}")
    say(f"4/4 the hidden effect was: {hidden}")
    return DemoResult(path, diagnosis, fit, hidden)
