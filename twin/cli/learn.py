"""`twin learn ...`: train, evaluate and apply the electrode models (torch is imported lazily).

Lengths on the command line are mm; files and checkpoints are SI.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from twin.cli.common import err_console, guarded, out_console, progress_bar, warn_nonfinite_forces

if TYPE_CHECKING:
    from learn.checkpoint import Checkpoint

learn_app = typer.Typer(help="Learned electrode models: train, eval, predict.", no_args_is_help=True)

TORCH_FREE_COMMANDS = frozenset({"synth"})
"""The learn commands that run on the core install; the others need the `learn` extra (torch)."""


@learn_app.callback()
def _require_torch(ctx: typer.Context) -> None:
    """Without torch, a torch command stops with the install line (exit code 2)."""
    if ctx.invoked_subcommand in TORCH_FREE_COMMANDS:
        return
    try:
        import torch  # noqa: F401
    except ImportError:
        err_console.print('[red]error:[/red] this command needs torch: pip install "biotac-twin\\[learn]"')
        raise typer.Exit(code=2) from None


METRIC_COLUMNS = (
    ("contact_loc_mean_mm", "loc mean (mm)"),
    ("contact_loc_median_mm", "loc median (mm)"),
    ("force_magnitude_median_N", "|F| median (N)"),
    ("force_angle_mean_rad", "angle mean (rad)"),
    ("force_angle_median_rad", "angle median (rad)"),
    ("nodal_mean_mm", "nodal mean (mm)"),
    ("n_samples", "samples"),
)


def _metrics_table(title: str, result: dict) -> Table:
    table = Table("sensor", *(label for _, label in METRIC_COLUMNS), title=title)
    rows = list(result["per_sensor"].items())
    if len(rows) > 1:
        rows.append(("combined", result["combined"]))
    for sensor, metrics in rows:
        cells = [f"{metrics[k]:.3g}" if k in metrics else "-" for k, _ in METRIC_COLUMNS]
        table.add_row(sensor, *cells)
    return table


def data_files(paths: list[Path]) -> list[Path]:
    """The data files of `paths` (a folder stands for its *.hdf5 files, sorted), each checked to exist and,
    when it is a campaign HDF5, to follow the schema (`twin.dataset.check_campaign`); ValueError otherwise."""
    import h5py

    from twin.dataset import check_campaign_file

    files: list[Path] = []
    for path in paths:
        if path.is_dir():
            found = sorted(p for p in path.glob("*.hdf5") if p.is_file())
            if not found:
                raise ValueError(f"{path}: a folder without campaign files (*.hdf5)")
            files += found
        elif not path.is_file():
            raise ValueError(f"{path}: no such file")
        else:
            files.append(path)
    for path in files:
        if h5py.is_hdf5(path):
            check_campaign_file(path)
    return files


def load_checkpoint(path: Path) -> Checkpoint:
    """`learn.checkpoint.Checkpoint.load`, with a missing, empty or foreign file as a one-line ValueError."""
    from learn.checkpoint import Checkpoint

    if not path.is_file():
        raise ValueError(f"{path}: no such checkpoint file")
    try:
        return Checkpoint.load(path)
    except ValueError:
        raise
    except Exception as exc:  # torch.load of foreign bytes raises many kinds (pickle, zip, index errors)
        raise ValueError(f"{path}: not a biotac-twin learn checkpoint ({type(exc).__name__}: {exc})") from exc


@learn_app.command()
def train(
    files: Annotated[
        list[Path], typer.Argument(help="Data files (campaign HDF5, paper HDF5, Ruppel CSV) or folders of *.hdf5.")
    ],
    out: Annotated[Path, typer.Option(help="Checkpoint to write.")] = Path("model.pt"),
    model: Annotated[str, typer.Option(help="pointnet | mlp | classical | mean.")] = "pointnet",
    split: Annotated[
        str, typer.Option(help="contiguous | noncontiguous | indenter:<name> | none (train on every row).")
    ] = "contiguous",
    test_fraction: Annotated[float, typer.Option(help="Share of trajectories (samples) held out.")] = 0.2,
    seed: Annotated[int, typer.Option(help="Seed of split, initialisation and batches.")] = 0,
    min_force: Annotated[
        float, typer.Option(help="N: train and score only rows with |force| >= this (0: all rows).")
    ] = 0.0,
    targets: Annotated[
        str, typer.Option(help="Comma-separated: contact_loc, force, nodal.")
    ] = "contact_loc,force,nodal",
    max_epochs: Annotated[int, typer.Option(help="Epoch limit.")] = 300,
    patience: Annotated[int, typer.Option(help="Stop after this many epochs without improvement.")] = 15,
    batch_size: Annotated[int, typer.Option(help="Minibatch size.")] = 128,
    learning_rate: Annotated[float, typer.Option(help="Adam learning rate.")] = 1e-3,
    time_limit: Annotated[float, typer.Option(help="Stop training after this many seconds.")] = float("inf"),
    threads: Annotated[int, typer.Option(help="Torch CPU threads.")] = 2,
    device: Annotated[str, typer.Option(help="cpu, cuda, or auto (cuda when present).")] = "auto",
    init: Annotated[Path | None, typer.Option(help="Pretrained checkpoint to fine-tune.")] = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print the metrics as JSON.")] = False,
) -> None:
    """Fit a model on the training rows of every file; score it per sensor and combined; save it."""
    from learn.experiment import SplitSpec
    from learn.experiment import train as run_training
    from learn.train import TrainConfig

    paths = guarded(lambda: data_files(files))
    config = guarded(
        lambda: TrainConfig(
            network=model if model in ("pointnet", "mlp") else "pointnet",
            targets=tuple(t.strip() for t in targets.split(",") if t.strip()),
            max_epochs=max_epochs,
            batch_size=batch_size,
            learning_rate=learning_rate,
            patience=patience,
            time_limit_s=time_limit,
            seed=seed,
            threads=threads,
            device=device,
        )
    )
    pretrained = guarded(lambda: load_checkpoint(init)) if init is not None else None
    with progress_bar() as bar:
        task = bar.add_task(f"training {model}", total=max_epochs)

        def show(record) -> None:
            bar.update(task, completed=record.epoch + 1, description=f"{model} val {record.val_loss:.4g}")

        checkpoint = guarded(
            lambda: run_training(
                paths, model, SplitSpec(split, test_fraction, seed, min_force), config, pretrained, 0, show
            )
        )
    checkpoint.save(out)
    err_console.print(f"wrote {out}")
    if as_json:
        print(json.dumps({"model": model, "split": split, **checkpoint.metrics}))
    else:
        out_console.print(_metrics_table(f"{model}, split {split} (test rows)", checkpoint.metrics))


@learn_app.command("eval")
def evaluate(
    checkpoints: Annotated[list[Path], typer.Argument(help="Checkpoints to score.")],
    data: Annotated[
        list[Path] | None, typer.Option(help="Data files (repeat); default: each checkpoint's training files.")
    ] = None,
    on: Annotated[str, typer.Option(help="test: the checkpoint's test rows; all: every row (unseen sensor).")] = "test",
    as_json: Annotated[bool, typer.Option("--json", help="Print the paper's table as JSON.")] = False,
) -> None:
    """The paper's table per sensor and combined, for every checkpoint (model and split)."""
    from learn.experiment import evaluate_checkpoint

    results = []
    for path in checkpoints:
        ckpt = guarded(lambda path=path: load_checkpoint(path))
        files = guarded(lambda ckpt=ckpt: data_files(data if data else [Path(p) for p in ckpt.training["files"]]))
        warn_nonfinite_forces(files)
        scores = guarded(lambda ckpt=ckpt, files=files: evaluate_checkpoint(ckpt, files, on))
        split = ckpt.training["split"]["name"] if on == "test" else "all rows"
        results.append({"checkpoint": str(path), "model": ckpt.model, "split": split, "on": on, **scores})
    if as_json:
        print(json.dumps(results, indent=1))
        return
    for r in results:
        out_console.print(_metrics_table(f"{r['model']}, {r['split']} ({r['checkpoint']})", r))


@learn_app.command()
def predict(
    checkpoint: Annotated[Path, typer.Argument(help="Checkpoint.")],
    file: Annotated[Path, typer.Argument(help="Data file whose electrode values to map.")],
    out: Annotated[Path, typer.Option(help="HDF5 to write: <target>/data per predicted target.")] = Path(
        "predictions.h5"
    ),
) -> None:
    """Predict contact location (m), force (N) and nodal displacements (m) for every row of a file."""
    import h5py

    from learn.experiment import load_files

    ckpt = guarded(lambda: load_checkpoint(checkpoint))
    guarded(lambda: data_files([file]))
    (data,) = guarded(lambda: load_files([file], ckpt.training.get("node_ids"), ckpt.training.get("node_seed", 0)))
    predictions = ckpt.estimator.predict(data)
    units = {"contact_loc": "m", "force": "N", "nodal": "m"}
    with h5py.File(out, "w") as f:
        f.attrs.update(checkpoint=str(checkpoint), model=ckpt.model, source=str(file))
        for name, values in predictions.items():
            ds = f.create_dataset(f"{name}/data", data=values)
            ds.attrs.update(units=units[name], frame="biotac")
        if data.node_ids is not None:
            f["nodal/node_ids"] = data.node_ids
    err_console.print(f"wrote {len(data)} rows of {', '.join(predictions)} to {out}")


@learn_app.command()
def synth(
    out: Annotated[Path, typer.Argument(help="Campaign HDF5 to write.")],
    trajectories: Annotated[int, typer.Option(help="Number of indentations.")] = 200,
    sensor_id: Annotated[int, typer.Option(help="Sensor id (its electrode parameters come from the seed).")] = 1,
    seed: Annotated[int, typer.Option(help="Seed of sensor, trajectories and noise.")] = 0,
    max_edge_mm: Annotated[float, typer.Option(help="Skin mesh edge length (mm).")] = 2.0,
) -> None:
    """Write a synthetic campaign (analytic dents + the physics electrode model; not FE) for trying learn."""
    from learn.synthetic import write_synthetic_campaign

    path = guarded(lambda: write_synthetic_campaign(out, trajectories, sensor_id, seed, max_edge_mm * 1e-3))
    err_console.print(f"wrote {path}")


@learn_app.command("fit-forward")
def fit_forward(
    file: Annotated[Path, typer.Argument(help="Campaign HDF5 with nodal_res, mesh and measured electrodes.")],
    out: Annotated[Path, typer.Option(help="Forward model file to write.")] = Path("forward.pt"),
    skin_thickness_mm: Annotated[float, typer.Option(help="Skin thickness of the FE that made the fields.")] = 1.57,
    seed: Annotated[int, typer.Option(help="Seed of split and initialisation.")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="Print the held-out scores as JSON.")] = False,
) -> None:
    """Fit the learned forward model (FE field -> this sensor's tared electrodes); report held-out RMSE."""
    from learn.forward import campaign_field_samples, fit_and_score

    guarded(lambda: data_files([file]))
    samples = guarded(lambda: campaign_field_samples(file, skin_thickness_mm * 1e-3))
    model, scores = guarded(lambda: fit_and_score(samples, seed=seed))
    record = {
        "file": str(file),
        "data_hash": samples.content_hash(),
        "seed": seed,
        "skin_thickness": skin_thickness_mm * 1e-3,
    }
    model.save(out, record | scores)
    err_console.print(f"wrote {out}")
    if as_json:
        print(json.dumps(scores))
    else:
        out_console.print(
            f"held-out RMSE {scores['rmse_counts']:.1f} counts "
            f"(mean predictor {scores['mean_predictor_rmse_counts']:.1f}) on {scores['n_test']} samples"
        )
