"""Why is the contact-location error twice the paper's? Break it down by row property (docs/learn.md, issue 19).

On the combined contiguous split (20 % of each file's trajectories held out, seed 0, as `twin learn train`)
of campaign row files (e.g. runs/paper12/r1.h5 r2.h5 r3.h5), fits the mean predictor, the classical
weighted centroid and (``--models``) the plain MLP or PointNet++ on CPU, and prints each one's location
error (mm) broken down by:

- true force magnitude |F| (F/T, tared and filtered): is location unobservable where contact barely
  started or never happened (< 0.1 N is F/T noise)?
- FE contact: whether the simulated skin carried any contact force at that row (simulation-only truth);
- indenter, trajectory kind (normal / 30-degree angled), loading / unloading / retracted (the last row,
  1 mm off the skin), region of the sampled skin point (tip x > 0, side |y| > 4 mm, ventral), sensor;

then the same models trained and scored only on rows with |F| >= ``--min-force`` (0.5 N, the paper's
F/T-noise threshold), and the label spread (distance of the test labels to their mean).

``--true-labels`` (simulated files only: re-runs the plant, twin.label_truth) also prints how far each
label (the tip through the *estimated* registration, as on the real testbed) is from the true tip, per
sensor and arm, and reruns the contact-rows models with the true tip as the label.

    PYTHONPATH=. python3 scripts/location_error_study.py r1.h5 r2.h5 r3.h5 --models mean,classical,mlp \
        --trajectories 120 --time-limit 300 --json location_study.json

``--trajectories K`` keeps K trajectories per file (seeded) for fast CPU runs: say so with any figure.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import h5py  # noqa: E402
import numpy as np  # noqa: E402

from learn.breakdown import by_group, force_bins  # noqa: E402
from learn.checkpoint import make_estimator  # noqa: E402
from learn.data import TactileData, concatenate, with_min_force  # noqa: E402
from learn.experiment import SplitSpec, load_files, split_rows  # noqa: E402
from learn.metrics import location_errors  # noqa: E402
from learn.train import TrainConfig  # noqa: E402

SIDE_Y = 4e-3
"""|y| (m) of a sampled skin point beyond which it counts as the side of the finger."""


def row_properties(path: Path, data: TactileData) -> dict[str, np.ndarray]:
    """(N,) labels per row of a campaign file loaded whole into ``data``: FE contact, phase, trajectory kind,
    region of the sampled point, indenter, sensor."""
    with h5py.File(path, "r") as f:
        fe_force = np.linalg.norm(f["fe_force/data"][:], axis=1) if "fe_force" in f else None
        depth = f["depth/data"][:]
        phase = f["phase/data"][:] if "phase" in f else np.zeros(len(depth), dtype=np.int64)
        ids, angle, point = (f[f"trajectories/{k}"][:] for k in ("trajectory_id", "angle", "point"))
        arm = f["trajectories/arm"][:] if "trajectories/arm" in f else np.full(len(ids), -1)
    by_id = {int(i): k for k, i in enumerate(ids)}
    k = np.array([by_id[int(t)] for t in data.trajectory])
    state = np.where(depth < 0.0, "retracted (1 mm off)", np.where(phase == 1, "unloading", "loading"))
    p = point[k]
    region = np.where(p[:, 0] > 0.0, "tip (x > 0)", np.where(np.abs(p[:, 1]) > SIDE_Y, "side (|y| > 4 mm)", "ventral"))
    out = {
        "state": state,
        "trajectory": np.where(angle[k] > 1e-3, "angled 30 deg", "normal"),
        "region": region,
        "indenter": np.array([data.indenter_names[i] for i in data.indenter]),
        "sensor": np.full(len(data), data.sensor),
        "arm": np.array(["unknown", "left", "right"])[arm[k] + 1],
    }
    if fe_force is not None:
        out["FE contact force"] = np.where(fe_force > 0.0, "> 0 (contact)", "0 (no contact)")
    return out


def keep_trajectories(data: TactileData, count: int, seed: int) -> np.ndarray:
    """Row indices of ``count`` trajectories drawn (seeded) from ``data`` (all rows if it has fewer)."""
    ids = np.unique(data.trajectory)
    if count >= len(ids):
        return np.arange(len(data))
    chosen = np.random.default_rng(seed).choice(ids, size=count, replace=False)
    return np.flatnonzero(np.isin(data.trajectory, chosen))


def fit_predict(
    model: str, train: TactileData, test: TactileData, args: argparse.Namespace
) -> tuple[np.ndarray, float]:
    """Location errors (mm) of ``model`` fitted on ``train`` over ``test``'s rows, and the wall time (s)."""
    config = TrainConfig(
        network=model if model in ("mlp", "pointnet") else "mlp",
        targets=("contact_loc", "force"),
        patience=args.patience,
        threads=args.threads,
        device="cpu",
        time_limit_s=args.time_limit,
    )
    start = time.perf_counter()
    estimator = make_estimator(model, config).fit(train)
    errors = location_errors(estimator.predict(test)["contact_loc"], test.contact_loc) * 1e3
    return errors, time.perf_counter() - start


def print_table(title: str, table: dict[str, dict[str, float]]) -> None:
    print(f"  {title}")
    for group, s in table.items():
        print(
            f"    {group:28s} n {s['n']:6d}  rows {100 * s['row_share']:5.1f} %  mean {s['mean']:6.2f}"
            f"  median {s['median']:6.2f}  share of error {100 * s['error_share']:5.1f} %"
        )


def contact_rerun(model: str, train: TactileData, test: TactileData, groups: dict, args: argparse.Namespace) -> dict:
    """``model`` trained and scored on the rows with |F| >= args.min_force only, with its breakdown."""
    keep = np.linalg.norm(test.force, axis=1) >= args.min_force
    train_contact, test_contact = with_min_force(train, args.min_force), test.subset(keep)
    errors, wall = fit_predict(model, train_contact, test_contact, args)
    return {
        "mean_mm": float(errors.mean()),
        "median_mm": float(np.median(errors)),
        "train_rows": len(train_contact),
        "test_rows": len(test_contact),
        "wall_s": round(wall, 1),
        "by": {name: by_group(errors, labels[keep]) for name, labels in groups.items()},
    }


def print_entry(title: str, entry: dict) -> None:
    print(f"\n{title}: mean {entry['mean_mm']:.2f} / median {entry['median_mm']:.2f} mm ({entry['wall_s']:.0f} s)")
    for name, table in entry["by"].items():
        print_table(name, table)
    sys.stdout.flush()


def split_sets(parts: list[TactileData], props: list[dict]) -> tuple[TactileData, TactileData, dict]:
    """Combined contiguous split: (train, test, {property: (N_test,) labels})."""
    rows = split_rows(parts, SplitSpec("contiguous"))
    train = concatenate([p.subset(tr) for p, (tr, _) in zip(parts, rows, strict=True)])
    test = concatenate([p.subset(te) for p, (_, te) in zip(parts, rows, strict=True)])
    groups = {k: np.concatenate([p[k][te] for p, (_, te) in zip(props, rows, strict=True)]) for k in props[0]}
    return train, test, {"|F|": force_bins(test.force), **groups}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("files", type=Path, nargs="+", help="campaign row files (one per sensor)")
    ap.add_argument("--models", default="mean,classical", help="comma-separated: mean, classical, mlp, pointnet")
    ap.add_argument("--min-force", type=float, default=0.5, help="N: threshold of the contact-rows-only rerun")
    ap.add_argument("--trajectories", type=int, default=0, help="keep this many trajectories per file (0: all)")
    ap.add_argument("--patience", type=int, default=15)
    ap.add_argument("--time-limit", type=float, default=600.0, help="s per network")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--true-labels", action="store_true", help="also with the plant's true tips as labels")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    parts = load_files(args.files)
    props = [row_properties(path, p) for path, p in zip(args.files, parts, strict=True)]
    if args.trajectories:
        kept = [keep_trajectories(p, args.trajectories, seed=0) for p in parts]
        parts = [p.subset(k) for p, k in zip(parts, kept, strict=True)]
        props = [{name: v[k] for name, v in p.items()} for p, k in zip(props, kept, strict=True)]
    train, test, groups = split_sets(parts, props)
    spread = np.linalg.norm(test.contact_loc - test.contact_loc.mean(axis=0), axis=1) * 1e3
    report: dict = {
        "files": [str(p) for p in args.files],
        "trajectories_per_file": args.trajectories or "all",
        "train_rows": len(train),
        "test_rows": len(test),
        "test_label_distance_to_mean_mm": {"mean": float(spread.mean()), "median": float(np.median(spread))},
        "models": {},
        "contact_rows_only": {},
    }
    print(
        f"train rows {len(train)}, test rows {len(test)}; test labels' distance to their mean: "
        f"mean {spread.mean():.2f} mm, median {np.median(spread):.2f} mm"
    )
    true_parts = None
    if args.true_labels:
        from twin.label_truth import true_tip_locations

        tips = [true_tip_locations(path) for path in args.files]
        if args.trajectories:
            tips = [t[k] for t, k in zip(tips, kept, strict=True)]
        true_parts = [replace(p, contact_loc=t) for p, t in zip(parts, tips, strict=True)]
        _, true_test, _ = split_sets(true_parts, props)
        offset = location_errors(test.contact_loc, true_test.contact_loc) * 1e3
        report["label_minus_true_tip_mm"] = {name: by_group(offset, groups[name]) for name in ("sensor", "arm")}
        print(f"label - true tip (mm): mean {offset.mean():.2f}, median {np.median(offset):.2f}")
        for name in ("sensor", "arm"):
            print_table(name, report["label_minus_true_tip_mm"][name])
    for model in args.models.split(","):
        errors, wall = fit_predict(model, train, test, args)
        contact = np.linalg.norm(test.force, axis=1) >= args.min_force
        entry = {
            "mean_mm": float(errors.mean()),
            "median_mm": float(np.median(errors)),
            "wall_s": round(wall, 1),
            "scored_on_contact_rows": {
                "mean_mm": float(errors[contact].mean()),
                "median_mm": float(np.median(errors[contact])),
            },
            "by": {name: by_group(errors, labels) for name, labels in groups.items()},
        }
        report["models"][model] = entry
        print_entry(f"{model}, all test rows", entry)
        print(
            f"{model} scored on |F| >= {args.min_force:g} N rows only: "
            f"{entry['scored_on_contact_rows']['mean_mm']:.2f} / {entry['scored_on_contact_rows']['median_mm']:.2f} mm"
        )
        report["contact_rows_only"][model] = contact_rerun(model, train, test, groups, args)
        print_entry(
            f"{model}, trained and scored on |F| >= {args.min_force:g} N rows", report["contact_rows_only"][model]
        )
        if true_parts is not None:
            true_train, true_test, _ = split_sets(true_parts, props)
            report.setdefault("contact_rows_only_true_labels", {})[model] = entry_true = contact_rerun(
                model, true_train, true_test, groups, args
            )
            print_entry(f"{model}, |F| >= {args.min_force:g} N rows, true tips as labels", entry_true)
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
