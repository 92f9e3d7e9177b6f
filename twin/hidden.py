"""Hidden effects for tests, benchmarks and the demo: an effect and its size drawn from a seed.

The analysis never sees what is drawn here: callers put the values into a plant and write them to a
sealed manifest beside the data, which only the final reveal reads. Sizes are drawn well above the
noise of a quick campaign but within what a real testbed shows (a few tenths of a millimetre of
registration error, a few percent of calibration error, tens of milliseconds of stream delay, a
bubble of a fifth to a third of the fluid, a backlash of 0.05-0.15 mm, an arm and tool compliance of
0.05-0.1 mm/N, an F/T range of 1.2-2 N on its axial force (bias included), a PDC drift of 0.2-0.5 counts/s).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from twin.effects import EFFECTS, SKIN_KNOBS, UNLISTED_EFFECTS, EffectValues


def _either(rng: np.random.Generator, low: float, high: float, centre: float = 1.0) -> float:
    """centre +- U(low, high), sign drawn: a deviation of a drawn size in a drawn direction."""
    return float(centre + rng.choice([-1.0, 1.0]) * rng.uniform(low, high))


def _signed(rng: np.random.Generator, low: float, high: float) -> float:
    return _either(rng, low, high, centre=0.0)


def _registration(rng: np.random.Generator) -> dict[str, float]:
    direction = rng.standard_normal(3)
    offset = direction / np.linalg.norm(direction) * rng.uniform(0.3e-3, 0.6e-3)
    return dict(zip(("dx", "dy", "dz"), (float(v) for v in offset), strict=True))


def _crosstalk(rng: np.random.Generator) -> dict[str, float]:
    terms = rng.choice(["xy", "xz", "yx", "yz", "zx", "zy"], size=2, replace=False)
    return {str(t): _signed(rng, 0.08, 0.15) for t in terms}


def _calibration(rng: np.random.Generator) -> dict[str, float]:
    """One axis's gain off by 8-15 % and one cross-axis term of 5-10 % (a sensor calibrated per axis)."""
    axis = str(rng.choice(list("xyz")))
    cross = str(rng.choice([a + b for a in "xyz" for b in "xyz" if a != b]))
    return {axis + axis: _either(rng, 0.08, 0.15), cross: _signed(rng, 0.05, 0.1)}


def _from_table(name: str) -> Callable[[np.random.Generator], dict[str, float]]:
    """The draw of a skin effect from its knobs' hidden ranges (fe.params), parameter by parameter."""
    pairs = tuple(zip(EFFECTS[name].parameters, (knob for _, knob in SKIN_KNOBS[name]), strict=True))

    def draw(rng: np.random.Generator) -> dict[str, float]:
        return {
            parameter.name: _either(rng, *knob.hidden, centre=parameter.off)
            if knob.hidden_both_ways
            else float(rng.uniform(*knob.hidden))
            for parameter, knob in pairs
        }

    return draw


HIDDEN_DRAWS: dict[str, Callable[[np.random.Generator], dict[str, float]]] = {
    name: _from_table(name) for name in SKIN_KNOBS
} | {
    "registration_offset": _registration,
    "robot_backlash": lambda rng: {"lag": float(rng.uniform(0.05e-3, 0.15e-3))},
    "robot_compliance": lambda rng: {"compliance": float(rng.uniform(0.05e-3, 0.1e-3))},
    "time_delay": lambda rng: {"seconds": float(rng.uniform(0.04, 0.12))},
    "ft_drift": lambda rng: {f"f{a}_rate": _signed(rng, 0.002, 0.006) for a in "xyz"},
    "ft_crosstalk": _crosstalk,
    "ft_gain": lambda rng: {"scale": _either(rng, 0.08, 0.15)},
    "ft_calibration": _calibration,
    "ft_nonlinearity": lambda rng: {"coefficient": _signed(rng, 0.08, 0.15)},
    "ft_saturation": lambda rng: {"fz": float(rng.uniform(1.2, 2.0))},
    "pdc_drift": lambda rng: {"rate": _signed(rng, 0.2, 0.5)},
}
"""How each effect's hidden size is drawn (the library's and the unlisted ones): the skin effects from the
parameter table, the structured ones (registration, the F/T maps) by their own draw."""

if set(HIDDEN_DRAWS) != set(EFFECTS) | set(UNLISTED_EFFECTS):
    raise RuntimeError("every effect needs a hidden-size draw")


def draw_hidden(name: str | None, seed: int) -> EffectValues:
    """The hidden effect values for effect `name` (None: no hidden effect), drawn from `seed`."""
    if name is None:
        return {}
    if name not in HIDDEN_DRAWS:
        raise ValueError(f"no hidden draw for {name!r}; known: {sorted(HIDDEN_DRAWS)}")
    return {name: HIDDEN_DRAWS[name](np.random.default_rng(np.random.SeedSequence([seed, 0x41D])))}


def write_sealed_manifest(path: Path, hidden: str | None, values: EffectValues, seed: int) -> None:
    """Write what was hidden, for the reveal only (the analysis reads the campaign file, never this)."""
    Path(path).write_text(json.dumps({"hidden_effect": hidden, "values": values, "seed": seed}, indent=2))


def read_sealed_manifest(path: Path) -> dict:
    """The reveal: {"hidden_effect", "values", "seed"}."""
    return json.loads(Path(path).read_text())
