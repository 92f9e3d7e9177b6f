"""`twin diagnose`, `improve`, `history`, `effects`, `demo`: find the missing effect, add it, watch the error fall."""

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from twin.cli.common import (
    DeviceOption,
    analysis_predictor,
    err_console,
    guarded,
    out_console,
    replay_progress,
    warn_nonfinite_forces,
)

if TYPE_CHECKING:
    from collections.abc import Callable

    from twin.analysis.diagnose import Diagnosis
    from twin.analysis.predict import Predictor, TwinModel
    from twin.analysis.refit import EffectFit

loop_app = typer.Typer()

Datasets = Annotated[list[Path], typer.Argument(help="Campaign HDF5 file(s).")]
ModelOption = Annotated[Path | None, typer.Option("--model", help="Model JSON (default: nominal).")]
HistoryOption = Annotated[
    Path | None,
    typer.Option(
        "--history",
        help="History file (JSON lines); default twin-history.jsonl beside --model, else beside the first dataset.",
    ),
]


def _inputs(datasets: list[Path], model_path: Path | None):
    from twin.analysis.data import load_campaign
    from twin.analysis.history import load_model
    from twin.analysis.predict import TwinModel

    data = [guarded(lambda p=p: load_campaign(p)) for p in datasets]
    warn_nonfinite_forces(datasets)
    model = guarded(lambda: load_model(model_path)) if model_path else TwinModel(mesh_max_edge=data[0].mesh_max_edge)
    return data, model


@loop_app.command()
def diagnose(
    datasets: Datasets,
    model: ModelOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON (strict: NaN as null).")] = False,
    refit_top: Annotated[
        int,
        typer.Option(
            "--refit-top",
            min=0,
            help="How many of the best-ranked candidates are refitted (when none holds held out, close ones too, "
            "up to 4 in all).",
        ),
    ] = 3,
    device: DeviceOption = "cpu",
    nuisances: Annotated[
        bool,
        typer.Option(
            "--nuisances",
            help="First fit the standard unknowns of a real campaign (registration per arm, skin per sensor, F/T "
            "bias; docs/analysis.md) and rank candidates on what remains.",
        ),
    ] = False,
    rank_per_stratum: Annotated[
        int | None,
        typer.Option(
            "--rank-per-stratum",
            min=1,
            help="Rank the candidates on at most this many trajectories of each sensor x indenter x path kind "
            "(large campaigns); the top ones are refitted and judged held out on all (JSON: ranked_on).",
        ),
    ] = None,
    per_stratum: Annotated[
        int | None,
        typer.Option(
            "--per-stratum",
            min=1,
            help="Diagnose only at most this many trajectories of each sensor x indenter x path kind, spread over "
            "the campaign (every stage; large campaigns; JSON: sampled).",
        ),
    ] = None,
    rank_mesh_mm: Annotated[
        float | None,
        typer.Option(
            "--rank-mesh-mm",
            min=0.1,
            help="Rank and refit the candidates on fe replays of this mesh size (mm; a coarser one is several times "
            "cheaper); each physics refit is finished on the campaign's mesh and each refitted one judged held out "
            "about that mesh's residual at its fit (JSON: ranked_mesh_mm).",
        ),
    ] = None,
    in_turn: Annotated[
        int,
        typer.Option(
            "--in-turn",
            min=0,
            help="Search in turn for up to this many missing effects: diagnose, add what is named (or once, on trial, "
            "an unexplained verdict's closest candidate), refit every effect jointly, diagnose again, until the "
            "residual is noise (JSON: turns, added, model; docs/analysis.md). 0: one diagnosis.",
        ),
    ] = 0,
) -> None:
    """Rank candidate effects by how much of the model-vs-measurement residual each explains."""
    from twin.analysis.diagnose import diagnose as run_diagnosis
    from twin.effects import EFFECTS

    predictor = analysis_predictor(device, electrodes=False)  # force and PDC only
    data, twin_model = _inputs(datasets, model)
    err_console.print("diagnosing (replaying every trajectory per candidate parameter) ...")
    if hint := large_campaign_hint(sum(len(d.trajectories) for d in data), twin_model, per_stratum, rank_mesh_mm):
        err_console.print(hint)

    def diagnosed(of: "TwinModel") -> "Diagnosis":
        steps = sum(1 for k in EFFECTS if k not in of.effects)
        with replay_progress(predictor) as progress:
            total, done = steps + min(refit_top, steps), 0
            task = progress.add_task("diagnosing", total=total)

            def report(stage: str, name: str) -> None:
                nonlocal total, done
                done += stage != "nuisances"
                total = max(total, done)  # close candidates refitted after the first ones (`verdict.to_refit`)
                progress.update(task, description=f"{stage} {name}", completed=done, total=total)

            return guarded(
                lambda: run_diagnosis(
                    data,
                    of,
                    predictor,
                    top=refit_top,
                    on_progress=report,
                    nuisances=nuisances,
                    rank_per_stratum=rank_per_stratum,
                    per_stratum=per_stratum,
                    rank_mesh=None if rank_mesh_mm is None else 1e-3 * rank_mesh_mm,
                )
            )

    if in_turn:
        _search_in_turn(diagnosed, data, twin_model, predictor, in_turn, as_json)
        return
    result = diagnosed(twin_model)
    if as_json:
        print(result.to_json())
        return
    _print_diagnosis(result, twin_model.mesh_max_edge)


def _print_diagnosis(result: "Diagnosis", mesh_max_edge: float) -> None:
    """`twin diagnose`'s table, stages and verdict; `mesh_max_edge` (m) the diagnosed model's fe mesh."""
    table = Table("rank", "effect", "kind", "evidence", "explains", "held-out RMS/noise", "refit RMS/noise", "fit")
    for rank, c in enumerate(result.candidates, start=1):
        bound = set(c.at_bound)
        fit = ", ".join(
            f"{k}={v:.4g}{' (at bound)' if k in bound else ''}" for k, v in (c.refit_parameters or c.parameters).items()
        )
        held = _figure(c.heldout_rms)
        if c.heldout_is_noise is not None:
            held += " (noise)" if c.heldout_is_noise else " (not noise)"
        if c.heldout_has_power is False:
            held += f"; the base passes it too ({c.heldout_base_rms:.2f})"
        refit = _figure(c.refit_rms)
        table.add_row(str(rank), c.name, c.kind, f"{c.evidence:.0f}", f"{c.explained_fraction:.0%}", held, refit, fit)
    out_console.print(
        f"residual RMS = {result.base_rms:.2f} x noise (noise test: {result.rms_threshold:.3f} x noise on these data)"
    )
    if (samples := result.samples) is not None and samples["reached"] < samples["of"]:
        out_console.print(
            f"the model's replays reached {samples['reached']} of the data's {samples['of']} samples (an fe increment "
            "that does not converge stops a replay): its residual and the ranking cover those only"
        )
    if result.nuisances is not None:
        _print_nuisances(result.nuisances)
    if (joint := result.jointly) is not None:
        judged = "named" if joint["named"] else "not the noise"
        out_console.print(
            f"the closest, {joint['effect']}, fitted jointly with the nuisances: RMS {joint['rms_after']:.2f} x noise "
            f"(held out {_figure(joint['heldout_rms'])}; {_figure(joint['heldout_predictive_rms'])} of its predictive "
            f"spread): {judged}"
        )
    if (on := result.sampled) is not None:
        out_console.print(
            f"diagnosed on {len(on['trajectories'])} of {on['of']} trajectories (at most {on['per_stratum']} per "
            "sensor x indenter x path kind)"
        )
    if (on := result.ranked_on) is not None:
        out_console.print(
            f"candidates ranked on {len(on['trajectories'])} of {on['of']} trajectories (at most {on['per_stratum']} "
            "per sensor x indenter x path kind); the refits and held-out judgements on all of them"
        )
    if result.ranked_mesh is not None:
        out_console.print(
            f"candidates ranked and refitted on a {1e3 * result.ranked_mesh:g} mm fe mesh; the held-out judgements "
            f"about the residual at each fit on the model's ({1e3 * mesh_max_edge:g} mm)"
        )
    out_console.print(table)
    out_console.print(f"verdict: [bold]{result.verdict}[/bold] - {result.reason}")
    if (step := result.next_step()) is not None:
        out_console.print(
            f"next: {step.name} explains part of it held out ({result.base_rms:.2f} -> {step.heldout_rms:.2f}x "
            f"the noise); if two effects are missing, add it (`twin improve ... --add {step.name}`) and diagnose the "
            "improved model: keep it only if the effect named next brings the held-out residual to the noise; a "
            "'nothing' there is no proof (docs/analysis.md, two effects at once)"
        )
    if nuisances := result.nuisances_closest():
        out_console.print(
            f"note: {', '.join(nuisances)} among the closest: every real campaign carries registration and "
            "unit-to-unit skin errors together; `twin diagnose --nuisances` fits them first and searches what remains "
            "(docs/analysis.md, nuisances first)"
        )


def _search_in_turn(
    diagnosed: "Callable[[TwinModel], Diagnosis]",
    data: list,
    model: "TwinModel",
    predictor: "Predictor",
    additions: int,
    as_json: bool,
) -> None:
    """`twin diagnose --in-turn`: `twin.analysis.in_turn.find_in_turn` with `diagnosed` and `fit_jointly`; a line a
    turn and the verdict, or the JSON."""
    from twin.analysis.in_turn import find_in_turn
    from twin.analysis.refit import fit_jointly

    def improved(of: "TwinModel", name: str) -> "EffectFit":
        err_console.print(f"adding {name} and refitting every effect jointly ...")
        with replay_progress(predictor):
            return guarded(lambda: fit_jointly(data, of, name, predictor))

    found = find_in_turn(diagnosed, improved, model, additions)
    if as_json:
        print(found.to_json())
        return
    for k, turn in enumerate(found.turns, start=1):
        d, fit = turn.diagnosis, turn.fit
        line = f"turn {k}: residual {d.base_rms:.2f} x noise, verdict {d.verdict}"
        if fit is not None:
            held = _figure(fit.heldout_rms)
            line += f"; added {turn.added} ({turn.via}): {fit.rms_before:.2f} -> {fit.rms_after:.2f} x noise"
            line += f", held out {held}"
        out_console.print(line)
    out_console.print(f"verdict: [bold]{found.verdict}[/bold] - {found.reason}")


HELDOUT_WORST_SHOWN = 3
"""Presses named where the nuisances do not hold out (the worst first)."""
LARGE_CAMPAIGN = 100
"""Trajectories above which `twin diagnose` without a sample says how to take one (the paper campaign: 905)."""


def large_campaign_hint(
    trajectories: int, model: "TwinModel", per_stratum: int | None, rank_mesh_mm: float | None
) -> str:
    """A one-line hint for a large campaign diagnosed whole (every trajectory replayed per candidate parameter: hours
    for the paper campaign), or "" when it is small or already sampled."""
    if trajectories <= LARGE_CAMPAIGN or per_stratum is not None:
        return ""
    coarse = " and `--rank-mesh-mm 1`" if rank_mesh_mm is None and model.mesh_max_edge < 1e-3 else ""
    return (
        f"{trajectories} trajectories: the whole campaign is replayed per candidate parameter; for a first look "
        f"diagnose a sample with `--per-stratum 1`{coarse} (docs/scale.md, the paper diagnose)"
    )


def _figure(value: float | None) -> str:
    """A whitened RMS as printed (- when there is none)."""
    return "-" if value is None else f"{value:.2f}"


def _print_nuisances(fit: dict) -> None:
    """The nuisance stage of `twin diagnose --nuisances`: fitted values and the residual before / after."""
    held = _figure(fit["heldout_rms"])
    if fit.get("heldout_predictive_rms") is not None:
        judged = "passes" if fit["heldout_is_noise"] else "fails"
        held += f"; {fit['heldout_predictive_rms']:.2f} of its predictive spread: {judged} the noise test"
    out_console.print(
        f"nuisances fitted first: RMS {fit['rms_before']:.2f} -> {fit['rms_after']:.2f} x noise (held out {held})"
    )
    bound = set(fit["at_bound"])
    values = ", ".join(f"{k}={v:.4g}{' (at bound)' if k in bound else ''}" for k, v in fit["values"].items())
    out_console.print(f"  {values}")
    if fit["cannot_tell_apart"]:
        out_console.print(f"  these data cannot tell {', '.join(fit['cannot_tell_apart'])} from the nuisances")
    if not fit["heldout_is_noise"] and fit["heldout_by_trajectory"]:
        worst = ", ".join(
            f"sensor {t['sensor']} trajectory {t['trajectory']} ({t['indenter']}, {t['path']}) {t['held_out']:.2f}x"
            f" ({t['held_out_predictive']:.2f} of its spread)"
            for t in fit["heldout_by_trajectory"][:HELDOUT_WORST_SHOWN]
            if t["held_out"] is not None
        )
        out_console.print(f"  worst held out (each press predicted by the nuisances fitted without it): {worst}")
    loaded = ", ".join(
        f"sensor {t['sensor']} trajectory {t['trajectory']} ({t['indenter']}, {t['path']}) {t['standoff_force']:.2f} N"
        for t in fit["heldout_by_trajectory"]
        if t.get("starts_in_contact")
    )
    if loaded:
        out_console.print(
            "  presses that start in contact at the fitted nuisances (tared under load; on a real testbed the arm's "
            f"move to the standoff, not in the data, sets the skin's friction there): {loaded}"
        )


@loop_app.command()
def improve(
    datasets: Datasets,
    add: Annotated[str, typer.Option("--add", help="Effect to add (see `twin effects`).")],
    model: ModelOption = None,
    history: HistoryOption = None,
    out: Annotated[Path | None, typer.Option(help="Also write the new model JSON here.")] = None,
    device: DeviceOption = "cpu",
    as_json: Annotated[
        bool, typer.Option("--json", help="Print the history entry as JSON (strict: NaN as null) instead of tables.")
    ] = False,
) -> None:
    """Fit an effect's parameters, then refit every effect of the model in turn with it (`fit_jointly`: an earlier
    fit biased by the effect that was missing is corrected), show the error before and after, save the model in the
    history (beside the model or the dataset unless --history names one)."""
    from twin.analysis.diagnose import strict_json
    from twin.analysis.history import append_entry, history_beside
    from twin.analysis.refit import fit_jointly

    predictor = analysis_predictor(device, electrodes=False)  # force and PDC only
    data, twin_model = _inputs(datasets, model)
    history = history if history is not None else history_beside(datasets, model)
    with replay_progress(predictor):
        fit = guarded(lambda: fit_jointly(data, twin_model, add, predictor))
    refitted = {name: values for name, values in fit.model.effects.items() if name != add}
    entry = append_entry(
        history,
        {
            "model": fit.model.to_dict(),
            "added": {"effect": add, "values": fit.values},
            "refitted": refitted,
            "datasets": [{"path": str(d.path), "sha256_16": d.digest} for d in data],
            "rms_before": fit.rms_before,
            "rms_after": fit.rms_after,
            "heldout_rms": fit.heldout_rms,
            "heldout_is_noise": fit.heldout_is_noise,
            "at_bound": fit.at_bound,
            "heldout_rms_threshold": fit.heldout_rms_threshold,
            "heldout_base_rms": fit.heldout_base_rms,
            "heldout_has_power": fit.heldout_has_power,
        },
    )
    if out is not None:
        out.write_text(json.dumps(fit.model.to_dict(), indent=2))
    if as_json:
        print(json.dumps(strict_json(entry), allow_nan=False))
    else:
        _print_fit(fit, add)
        for name, values in refitted.items():
            was = twin_model.effects[name]
            shown = ", ".join(f"{k}={v:.5g} (was {was.get(k, v):.5g})" for k, v in values.items() if v != was.get(k, v))
            out_console.print(f"refitted with it: {name}: {shown or 'unchanged'}")
    (err_console if as_json else out_console).print(f"saved as step {entry['step']} in {history}")


def _print_fit(fit: "EffectFit", add: str) -> None:
    """`twin improve`'s tables: the RMS before, after and held out, with the held-out test's figures (the RMS
    it allows and, by the power rule, whether the residual without the effect fails it too), and the values."""
    table = Table("", "RMS / noise")
    table.add_row("before", f"{fit.rms_before:.2f}")
    table.add_row(f"after adding {add}", f"{fit.rms_after:.2f}")
    held = _figure(fit.heldout_rms)
    if fit.heldout_is_noise is not None:
        held += " (passes the noise test)" if fit.heldout_is_noise else " (fails the noise test)"
    if fit.heldout_rms_threshold is not None:
        held += f", its test allows {fit.heldout_rms_threshold:.3f}"
    table.add_row("held out (leave one indenter out)", held)
    if fit.heldout_base_rms is not None:
        power = "fails it: the test has power" if fit.heldout_has_power else "passes it too: the test has no power"
        table.add_row("held out without the effect (same samples)", f"{fit.heldout_base_rms:.2f} ({power})")
    out_console.print(table)
    bound = set(fit.at_bound)
    out_console.print(
        "fitted: " + ", ".join(f"{k}={v:.5g}{' (at its bound)' if k in bound else ''}" for k, v in fit.values.items())
    )


@loop_app.command("history")
def show_history(
    beside: Annotated[
        Path | None, typer.Argument(help="A dataset or model file: show the history beside it (as improve keeps it).")
    ] = None,
    history: HistoryOption = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON.")] = False,
) -> None:
    """The sequence of models and how the error fell (default: twin-history.jsonl here)."""
    from twin.analysis.history import HISTORY_NAME, history_beside, read_history

    if history is None:
        history = history_beside([beside]) if beside is not None else Path(HISTORY_NAME)
    entries = guarded(lambda: read_history(history))
    if as_json:
        print(json.dumps(entries))
        return
    table = Table("step", "time (UTC)", "added", "RMS before", "RMS after", "held out", "datasets")
    for e in entries:
        held = e.get("heldout_rms")
        table.add_row(
            str(e["step"]),
            e["time_utc"],
            e["added"]["effect"],
            f"{e['rms_before']:.2f}",
            f"{e['rms_after']:.2f}",
            _figure(held),
            ", ".join(Path(d["path"]).name for d in e["datasets"]),
        )
    out_console.print(table)


@loop_app.command("effects")
def list_effects() -> None:
    """The library of candidate effects and their parameters."""
    from twin.effects import EFFECTS

    table = Table("effect", "kind", "parameters (off [lower, upper] units)", "description")
    for e in EFFECTS.values():
        params = "; ".join(f"{p.name}={p.off:g} [{p.lower:g}, {p.upper:g}] {p.units}" for p in e.parameters)
        table.add_row(e.name, e.kind, params, e.description)
    out_console.print(table)


@loop_app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Output folder.")] = Path("runs/demo"),
    seed: Annotated[
        int, typer.Option(help="Seed of the hidden effect and of the campaign (its points and noise).")
    ] = 0,
) -> None:
    """The loop end to end: hidden effect, quick campaign, report, diagnosis, the effect added, error falling."""
    from twin.demo import run_demo

    result = guarded(lambda: run_demo(out, seed, say=out_console.print))
    mark = "[green]found[/green]" if result.found == result.hidden else "[red]missed[/red]"
    out_console.print(f"the loop added {result.found!r}; hidden was {result.hidden!r}: {mark}")
    out_console.print(f"reports: {out / 'report_before'}, {out / 'report_after'}")
