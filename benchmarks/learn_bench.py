"""Speed of learn/: training time to the best epoch on a ~30k-sample campaign, and inference samples/s.

The timing campaign is synthetic (learn.synthetic: analytic dents read by the physics electrode model,
2 mm skin mesh); it is written once to --data and reused. Only torch, numpy, scipy and h5py are needed:
no warp, MuJoCo, trimesh or rerun, so a GPU machine with the campaign folder carried over runs it.
--table runs the paper's protocol on synthetic sensors, or on the campaign files biotac*.hdf5 of
--campaign (e.g. the FE-simulated one of scripts/make_learn_campaign.py). Every model trains on the
contiguous 80/20 split with early stopping (patience epochs without validation improvement) or the
time limit, whichever comes first. "Time to convergence" is the wall time up to the best validation
epoch; "converged" says whether early stopping (not the time limit) ended the run. On a GPU each
network is also timed for --baseline-epochs epochs on the CPU (--baseline-threads threads) in the same
process: "speedup_vs_cpu_baseline" is that s/epoch over the GPU's.

    python benchmarks/learn_bench.py --device cpu --threads 2 --time-limit 900
    python benchmarks/learn_bench.py --device cuda --batch-size 128
    python benchmarks/learn_bench.py --table 3 --samples 10000   # the paper's table (GPU when present)
    python benchmarks/learn_bench.py --table 3 --campaign runs/learn_fe_compact

On a GPU machine without this project installed (docs/learn.md, "Speed"): write the campaign here
(`python benchmarks/learn_bench.py --write-only`), carry out/learn_bench over, and there run
`PYTHONPATH=. python3 benchmarks/learn_bench.py --device cuda --threads 4`.

Prints one JSON object (and writes it to --json when given).
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from pathlib import Path

import torch

from learn.data import load
from learn.experiment import SplitSpec, evaluate_checkpoint, train
from learn.report import add_model, emit
from learn.synthetic import write_synthetic_campaign
from learn.train import NETWORKS, TrainConfig, resolve_device

ROWS_PER_TRAJECTORY = 13.5
"""Mean rows of a synthetic trajectory (depths 0.5-2 mm in 0.1 mm steps, plus the first contact)."""


def campaign(folder: Path, samples: int, seed: int, sensor_id: int = 1) -> Path:
    """The synthetic campaign of about ``samples`` rows in ``folder`` (written if missing)."""
    path = folder / f"bench_{samples}_{seed}" / f"biotac{sensor_id}.hdf5"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        write_synthetic_campaign(path, math.ceil(samples / ROWS_PER_TRAJECTORY), sensor_id=sensor_id, seed=seed)
        print(f"wrote {path} in {time.perf_counter() - start:.0f} s", flush=True)
    return path


def cpu_name() -> str:
    """The processor's model name (Linux), else the platform's word for it."""
    cpuinfo = Path("/proc/cpuinfo")
    if cpuinfo.exists():
        for line in cpuinfo.read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "cpu"


def inference_rate(estimator, data, device: str, repeats: int = 3) -> float:
    """Best-of-``repeats`` samples/s of ``predict`` over the whole data set (host transfers included)."""
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        estimator.predict(data, device=device)
        if device == "cuda":
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - start)
    return len(data) / best


def cpu_baseline(path: Path, model: str, config: TrainConfig, epochs: int, threads: int) -> float:
    """Seconds per epoch of ``model`` trained for ``epochs`` epochs on the CPU with ``threads`` threads."""
    cpu = TrainConfig(**{**config.__dict__, "device": "cpu", "threads": threads, "max_epochs": epochs})
    ckpt = train([path], model, SplitSpec("contiguous", 0.2, config.seed), cpu)
    torch.set_num_threads(config.threads)
    return ckpt.estimator.history[-1].seconds / len(ckpt.estimator.history)


def paper_table(paths: list[Path], models: list[str], config: TrainConfig, held_out_indenter: str) -> list[dict]:
    """The paper's protocol on several sensors: per-sensor and combined contiguous, non-contiguous
    (leaky), leave one indenter out, cross-sensor (last two sensors both ways), pretrain on all then
    fine-tune on the last (networks). One row per (model, split, training files)."""
    rows = []

    clock = [time.perf_counter()]

    def add(model: str, split: str, trained_on: str, result: dict) -> None:
        wall = time.perf_counter() - clock[0]
        rows.append({"model": model, "split": split, "trained_on": trained_on, "wall_s": round(wall, 1), **result})
        print(
            json.dumps(rows[-1]["combined"] | {"model": model, "split": split, "on": trained_on, "s": round(wall, 1)}),
            flush=True,
        )
        clock[0] = time.perf_counter()

    names = [p.stem for p in paths]
    for model in models:
        cfg = TrainConfig(**{**config.__dict__, "network": model if model in NETWORKS else "pointnet"})
        for path, name in zip(paths, names, strict=True):
            add(model, "contiguous", name, train([path], model, SplitSpec("contiguous"), cfg).metrics)
        combined = train(paths, model, SplitSpec("contiguous"), cfg)
        add(model, "contiguous", "all", combined.metrics)
        add(model, "noncontiguous", "all", train(paths, model, SplitSpec("noncontiguous"), cfg).metrics)
        held = SplitSpec(f"indenter:{held_out_indenter}")
        add(model, f"leave out {held_out_indenter}", "all", train(paths, model, held, cfg).metrics)
        for source, target in ((-2, -1), (-1, -2)):
            alone = train([paths[source]], model, SplitSpec("none"), cfg)
            unseen = evaluate_checkpoint(alone, [paths[target]], "all")
            add(model, f"cross-sensor -> {names[target]}", names[source], unseen)
        if model in NETWORKS:
            tuned = train([paths[-1]], model, SplitSpec("contiguous"), cfg, init=combined)
            add(model, "pretrain all + fine-tune", names[-1], tuned.metrics)
    return rows


COLUMNS = (
    "contact_loc_mean_mm",
    "contact_loc_median_mm",
    "force_magnitude_median_N",
    "force_angle_mean_rad",
    "force_angle_median_rad",
    "nodal_mean_mm",
)


def markdown(rows: list[dict]) -> str:
    """The table rows as markdown: one line per (model, split, trained on, scored sensor)."""
    lines = ["| model | split | trained on | scored on | " + " | ".join(COLUMNS) + " |"]
    lines.append("|" + "---|" * (4 + len(COLUMNS)))
    for row in rows:
        scored = list(row["per_sensor"].items()) + (
            [("combined", row["combined"])] if len(row["per_sensor"]) > 1 else []
        )
        for sensor, metrics in scored:
            cells = [f"{metrics[c]:.2f}" if c in metrics else "-" for c in COLUMNS]
            lines.append(
                f"| {row['model']} | {row['split']} | {row['trained_on']} | {sensor} | " + " | ".join(cells) + " |"
            )
    return "\n".join(lines)


def _train_config(args: argparse.Namespace, **overrides: str) -> TrainConfig:
    """The training settings the command line asks for (plus `overrides`)."""
    return TrainConfig(
        max_epochs=args.max_epochs,
        batch_size=args.batch_size,
        learning_rate=args.learning_rate,
        patience=args.patience,
        time_limit_s=args.time_limit,
        seed=args.seed,
        threads=args.threads,
        device=args.device,
        scale_tail=args.scale_tail,
        angle_weight=args.angle_weight,
        **overrides,
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=30000)
    parser.add_argument("--models", default="pointnet,mlp,classical,mean")
    parser.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"), help="auto: cuda if present")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch-size", type=int, default=128)
    parser.add_argument("--learning-rate", type=float, default=1e-3)
    parser.add_argument("--patience", type=int, default=10)
    parser.add_argument("--max-epochs", type=int, default=300)
    parser.add_argument("--time-limit", type=float, default=900.0, help="seconds per network")
    parser.add_argument("--data", type=Path, default=Path("out/learn_bench"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scale-tail", type=float, default=TrainConfig.scale_tail, help="quantile scaling tail")
    parser.add_argument("--angle-weight", type=float, default=TrainConfig.angle_weight, help="force-direction loss")
    parser.add_argument("--baseline-epochs", type=int, default=2, help="CPU epochs timed beside a GPU run")
    parser.add_argument("--baseline-threads", type=int, default=2)
    parser.add_argument("--write-only", action="store_true", help="write the synthetic campaign and stop")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--table", type=int, default=0, help="run the paper's protocol on this many sensors")
    parser.add_argument("--held-out-indenter", default="ring")
    parser.add_argument(
        "--campaign", type=Path, default=None, help="--table on this folder's biotac*.hdf5 instead of synthetic"
    )
    args = parser.parse_args()
    args.device = resolve_device(args.device)

    torch.set_num_threads(args.threads)
    if args.table:
        if args.campaign is not None:
            paths = sorted(args.campaign.glob("biotac*.hdf5"))[: args.table]
            for p in paths:
                d = load(p)
                print(f"{p}: {len(d)} samples, {len(set(d.trajectory.tolist()))} trajectories", flush=True)
        else:
            paths = [campaign(args.data, args.samples, args.seed + k, k + 1) for k in range(args.table)]
        config = _train_config(args)
        rows = paper_table(paths, args.models.split(","), config, args.held_out_indenter)
        print(markdown(rows))
        if args.json is not None:
            args.json.write_text(json.dumps(rows, indent=1))
        return
    path = campaign(args.data, args.samples, args.seed)
    if args.write_only:
        return
    data = load(path)
    report: dict = {
        "samples": len(data),
        "trajectories": int(len(set(data.trajectory.tolist()))),
        "device": torch.cuda.get_device_name() if args.device == "cuda" else cpu_name(),
        "threads": args.threads,
        "torch": torch.__version__,
        "data": "synthetic (learn.synthetic), contiguous 80/20 split",
        "models": {},
    }
    for model in args.models.split(","):
        config = _train_config(args, network=model if model in NETWORKS else "pointnet")
        start = time.perf_counter()
        ckpt = train([path], model, SplitSpec("contiguous", 0.2, args.seed), config)
        entry: dict = {"wall_s": time.perf_counter() - start, "metrics": ckpt.metrics["combined"]}
        history = getattr(ckpt.estimator, "history", None)
        if history:
            best = min(history, key=lambda h: h.val_loss)
            entry.update(
                epochs=len(history),
                best_epoch=best.epoch,
                time_to_convergence_s=best.seconds,
                seconds_per_epoch=history[-1].seconds / len(history),
                converged=len(history) < args.max_epochs and history[-1].seconds <= args.time_limit,
                stopped_by="patience"
                if len(history) < args.max_epochs and history[-1].seconds <= args.time_limit
                else ("time limit" if history[-1].seconds > args.time_limit else "max epochs"),
                history=[[h.epoch, round(h.val_loss, 6), round(h.seconds, 1)] for h in history],
                inference_samples_per_s=inference_rate(ckpt.estimator, data, args.device),
            )
            if args.device == "cuda" and args.baseline_epochs > 0:
                base = cpu_baseline(path, model, config, args.baseline_epochs, args.baseline_threads)
                entry.update(
                    cpu_baseline_seconds_per_epoch=base,
                    cpu_baseline_threads=args.baseline_threads,
                    speedup_vs_cpu_baseline=base / entry["seconds_per_epoch"],
                )
        add_model(report, model, entry)
    emit(report, args.json)


if __name__ == "__main__":
    main()
