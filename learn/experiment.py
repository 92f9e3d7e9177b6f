"""The paper's protocol over files: load, split each file, fit on the training rows, score per sensor.

Per-file splits use the same rule and seed in every call, so a model pretrained on several sensors and
then fine-tuned on one never sees that sensor's test trajectories. Cross-sensor: train with split
"none" (every row trains) on one sensor, evaluate ``on="all"`` on another.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from learn.checkpoint import Checkpoint, Estimator, make_estimator
from learn.data import TactileData, concatenate, load
from learn.metrics import paper_metrics
from learn.splits import split
from learn.train import EpochRecord, NeuralEstimator, TrainConfig


@dataclass(frozen=True)
class SplitSpec:
    """name: a learn.splits name; test_fraction of trajectories/samples; seed of the split.
    min_force (N): after splitting, rows whose force magnitude is below it leave both sides (0: keep all).
    The rows below ~0.5 N include rows where the skin is not touched at all, whose contact location no
    electrode can show: at paper size they are 58 % of the rows and carry 60 % of the location error
    (docs/learn.md, "Why location is 2x the paper's")."""

    name: str = "contiguous"
    test_fraction: float = 0.2
    seed: int = 0
    min_force: float = 0.0


def load_files(paths: list[str | Path], node_ids: list[int] | None = None, node_seed: int = 0) -> list[TactileData]:
    """Load every file; sensors with the same name get their file stem appended."""
    parts = [load(p, node_ids=None if node_ids is None else np.asarray(node_ids), node_seed=node_seed) for p in paths]
    names = [p.sensor for p in parts]
    return [p if names.count(p.sensor) == 1 else replace(p, sensor=f"{p.sensor}:{Path(p.source).stem}") for p in parts]


def split_rows(parts: list[TactileData], spec: SplitSpec) -> list[tuple[np.ndarray, np.ndarray]]:
    """(train_rows, test_rows) of each part; split "none" trains on every row and tests on none. Rows with
    |force| < spec.min_force are then dropped from both (the split itself does not depend on it).

    Leave-one-indenter-out over several files: a file without that indenter trains on every row (the
    paper's BioTac 1 saw only the spheres); it is an error only when no file has it.
    """
    rows = _split_all_rows(parts, spec)
    if spec.min_force <= 0.0:
        return rows
    if any(p.force is None for p in parts):
        raise ValueError("min_force needs force targets in every file")
    kept = [np.linalg.norm(p.force, axis=1) >= spec.min_force for p in parts]
    return [(tr[k[tr]], te[k[te]]) for (tr, te), k in zip(rows, kept, strict=True)]


def _split_all_rows(parts: list[TactileData], spec: SplitSpec) -> list[tuple[np.ndarray, np.ndarray]]:
    everything = [(np.arange(len(p)), np.array([], dtype=np.int64)) for p in parts]
    if spec.name == "none":
        return everything
    if spec.name.startswith("indenter:"):
        name = spec.name.split(":", 1)[1]
        has = [name in p.indenter_names and np.any(p.indenter == p.indenter_names.index(name)) for p in parts]
        if not any(has):
            raise ValueError(f"no file has samples of indenter {name!r}")
        return [split(p, spec.name) if h else rows for p, h, rows in zip(parts, has, everything, strict=True)]
    return [split(p, spec.name, spec.test_fraction, spec.seed) for p in parts]


def evaluate(estimator: Estimator, parts: list[TactileData]) -> dict:
    """{"per_sensor": {sensor: metrics}, "combined": metrics} over the given (test) parts."""
    parts = [p for p in parts if len(p)]
    if not parts:
        return {"per_sensor": {}, "combined": {}}
    predictions = [estimator.predict(p) for p in parts]
    per_sensor = {p.sensor: paper_metrics(pred, p.targets()) for p, pred in zip(parts, predictions, strict=True)}
    keys = set.intersection(*(set(pred) for pred in predictions))
    if any(p.nodal is None for p in parts) or len({p.nodal.shape[1] for p in parts}) > 1:
        keys.discard("nodal")
    combined_pred = {k: np.concatenate([pred[k] for pred in predictions]) for k in keys}
    combined_true = concatenate(parts).targets()
    return {"per_sensor": per_sensor, "combined": paper_metrics(combined_pred, combined_true)}


def train(
    paths: list[str | Path],
    model: str,
    spec: SplitSpec = SplitSpec(),
    config: TrainConfig | None = None,
    init: Checkpoint | None = None,
    node_seed: int = 0,
    on_epoch: Callable[[EpochRecord], None] | None = None,
) -> Checkpoint:
    """Fit ``model`` on the training rows of every file and score it on their test rows.

    init: a pretrained network checkpoint to fine-tune (same model; its field nodes are reused).
    on_epoch: progress callback of the networks.
    """
    node_ids = init.training.get("node_ids") if init is not None else None
    parts = load_files(paths, node_ids, node_seed)
    rows = split_rows(parts, spec)
    training = concatenate([p.subset(tr) for p, (tr, _) in zip(parts, rows, strict=True)])
    if len(training) == 0:
        raise ValueError(f"split {spec.name!r} leaves no training rows")
    estimator = make_estimator(model, config)
    if init is not None:
        if init.model != model or not isinstance(init.estimator, NeuralEstimator):
            raise ValueError(f"cannot fine-tune a {model} from a {init.model} checkpoint")
        estimator.fit(training, init=init.estimator, on_epoch=on_epoch)
    elif isinstance(estimator, NeuralEstimator):
        estimator.fit(training, on_epoch=on_epoch)
    else:
        estimator.fit(training)
    tests = [p.subset(te) for p, (_, te) in zip(parts, rows, strict=True)]
    first_nodes = parts[0].node_ids
    record = {
        "files": [str(p) for p in paths],
        "sensors": [p.sensor for p in parts],
        "data_hashes": {p.sensor: p.content_hash() for p in parts},
        "split": spec.__dict__,
        "node_seed": node_seed,
        "node_ids": None if first_nodes is None else first_nodes.tolist(),
        "n_train": len(training),
        "fine_tuned_from": None if init is None else init.training.get("data_hashes"),
    }
    return Checkpoint(model, estimator, record, evaluate(estimator, tests))


def evaluate_checkpoint(checkpoint: Checkpoint, paths: list[str | Path], on: str = "test") -> dict:
    """Score a checkpoint on files: ``on="test"`` its split's test rows (same split rule and seed; the
    files' content must match what it was trained on), ``on="all"`` every row (unseen sensors)."""
    parts = load_files(paths, checkpoint.training.get("node_ids"), checkpoint.training.get("node_seed", 0))
    spec = SplitSpec(**checkpoint.training["split"])
    if on == "all":
        rows = split_rows(parts, replace(spec, name="none"))  # every row, less those under spec.min_force
        tests = [p.subset(tr) for p, (tr, _) in zip(parts, rows, strict=True)]
    elif on == "test":
        hashes = checkpoint.training.get("data_hashes", {})
        for p in parts:
            if hashes.get(p.sensor) not in (None, p.content_hash()):
                raise ValueError(f"{p.source}: its content differs from the {p.sensor} data this model was trained on")
        tests = [p.subset(te) for p, (_, te) in zip(parts, split_rows(parts, spec), strict=True)]
    else:
        raise ValueError(f"on must be 'test' or 'all', got {on!r}")
    return evaluate(checkpoint.estimator, tests)
