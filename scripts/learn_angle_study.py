"""Why is the force-angle error large? Measure each hypothesis on a campaign (docs/learn.md, issue 19).

On the combined contiguous split (20 % of each file's trajectories held out) of the campaign files
biotac*.hdf5 in a folder (FE-simulated, scripts/make_learn_campaign.py, or synthetic, `twin learn synth`):

- angle error by true force magnitude (is it the low-force rows, whose direction is noise?);
- the *zero-shear* predictor: the force along the inward skin normal at the trajectory's sampled point
  (perfect location, no shear): the floor of any model whose inputs do not show shear;
- 1 - cos beside the angle (what "angular cosine error" could also mean);
- networks with the paper's min-max scaling against quantile scaling of inputs and targets and
  force-direction and force-magnitude loss terms (`--variants`, TrainConfig's scale_tail, angle_weight,
  magnitude_weight).

    python3 scripts/learn_angle_study.py out/learn_fe --json angle_study.json [--network mlp]

Angles in rad, forces in N, locations in mm; the biotac frame. Prints one JSON object.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import h5py  # noqa: E402
import numpy as np  # noqa: E402

from assets.biotac import make_biotac, vertex_normals  # noqa: E402
from learn.baselines import Classical, MeanPredictor  # noqa: E402
from learn.data import TactileData, concatenate  # noqa: E402
from learn.experiment import SplitSpec, load_files, split_rows  # noqa: E402
from learn.metrics import ANGLE_MIN_FORCE, location_errors  # noqa: E402
from learn.report import add_model, emit  # noqa: E402
from learn.train import NeuralEstimator, TrainConfig  # noqa: E402

FORCE_BINS = (0.0, 0.5, 1.0, 2.0, 5.0, np.inf)
"""Edges (N) of the true-force-magnitude bins of the angle table."""


def angle_and_cosine(predicted: np.ndarray, true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N,) angle (rad) between the rows of two (N, 3) force arrays, and 1 - its cosine."""
    norms = np.linalg.norm(predicted, axis=1) * np.linalg.norm(true, axis=1)
    cos = np.clip(np.einsum("ij,ij->i", predicted, true) / np.maximum(norms, 1e-12), -1.0, 1.0)
    return np.arccos(cos), 1.0 - cos


def trajectory_points(path: Path) -> dict[int, np.ndarray]:
    """{trajectory id: sampled skin point (3,) m} from a campaign file's `trajectories` group."""
    with h5py.File(path, "r") as f:
        ids, points = f["trajectories/trajectory_id"][:], f["trajectories/point"][:]
    return {int(i): p for i, p in zip(ids, points, strict=True)}


def zero_shear_forces(at: np.ndarray, mesh_edge: float) -> np.ndarray:
    """(N, 3) N: unit forces along the inward normal of the nominal skin at its vertex nearest to each
    point of ``at`` (N, 3) m: what a model that sees no shear can best predict."""
    skin = make_biotac(mesh_edge).skin
    normals = vertex_normals(skin.vertices, skin.triangles)
    nearest = np.argmin(((at[:, None, :] - skin.vertices[None]) ** 2).sum(axis=2), axis=1)
    return -normals[nearest]


def sampled_points(data: TactileData, path: Path) -> np.ndarray:
    """(N, 3) m: each row's trajectory's sampled skin point."""
    points = trajectory_points(path)
    return np.array([points[int(t)] for t in data.trajectory])


def force_report(predicted: np.ndarray, true: np.ndarray) -> dict:
    """Angle (rad) and 1 - cos over |F_true| >= ANGLE_MIN_FORCE, and by force bin; magnitude error (N)."""
    mag = np.linalg.norm(true, axis=1)
    angle, one_minus_cos = angle_and_cosine(predicted, true)
    keep = mag >= ANGLE_MIN_FORCE
    bins = {}
    for lo, hi in zip(FORCE_BINS[:-1], FORCE_BINS[1:], strict=True):
        rows = (mag >= lo) & (mag < hi)
        if rows.any():
            bins[f"{lo:g}-{hi:g} N"] = {
                "n": int(rows.sum()),
                "angle_mean": round(float(angle[rows].mean()), 3),
                "angle_median": round(float(np.median(angle[rows])), 3),
            }
    magnitude = np.abs(np.linalg.norm(predicted, axis=1) - mag)
    return {
        "angle_mean": round(float(angle[keep].mean()), 3),
        "angle_median": round(float(np.median(angle[keep])), 3),
        "one_minus_cos_mean": round(float(one_minus_cos[keep].mean()), 3),
        "angle_mean_all_rows": round(float(angle.mean()), 3),
        "force_magnitude_median_N": round(float(np.median(magnitude)), 3),
        "by_force": bins,
    }


def network_variants(args: argparse.Namespace) -> dict[str, TrainConfig]:
    """The network settings compared: the paper's min-max scaling, quantile scaling, + direction loss."""
    base = TrainConfig(
        network=args.network,
        targets=tuple(args.targets.split(",")),
        patience=args.patience,
        max_epochs=args.max_epochs,
        threads=args.threads,
        device=args.device,
        time_limit_s=args.time_limit,
        scale_tail=0.0,
        angle_weight=0.0,
        magnitude_weight=0.0,
    )
    variants = {f"{args.network} min-max": base}
    for spec in args.variants.split(","):
        tail, angle, magnitude = (float(v) for v in spec.split(":"))
        name = f"{args.network} tail {tail:g}, angle loss {angle:g}, magnitude loss {magnitude:g}"
        changes = {"scale_tail": tail, "angle_weight": angle, "magnitude_weight": magnitude}
        variants[name] = TrainConfig(**{**base.__dict__, **changes})
    return variants


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("folder", type=Path, help="folder of campaign files biotac*.hdf5")
    ap.add_argument("--network", default="mlp", choices=("mlp", "pointnet"))
    ap.add_argument(
        "--variants",
        default="0.01:0:0,0:0.3:0,0:0.3:0.3",
        help="networks besides the paper's min-max one: scale_tail:angle_weight:magnitude_weight,...",
    )
    ap.add_argument("--targets", default="contact_loc,force,nodal", help="network targets (comma-separated)")
    ap.add_argument("--patience", type=int, default=10)
    ap.add_argument("--max-epochs", type=int, default=300)
    ap.add_argument("--time-limit", type=float, default=300.0, help="s per network")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu", choices=("cpu", "cuda"))
    ap.add_argument("--mesh-mm", type=float, default=1.0, help="nominal skin mesh for the normals")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    paths = sorted(args.folder.glob("biotac*.hdf5"))
    if not paths:
        ap.exit(2, f"learn_angle_study.py: error: no biotac*.hdf5 in {args.folder}\n")
    parts = load_files(paths)
    rows = split_rows(parts, SplitSpec("contiguous"))
    train = concatenate([p.subset(tr) for p, (tr, _) in zip(parts, rows, strict=True)])
    test = concatenate([p.subset(te) for p, (_, te) in zip(parts, rows, strict=True)])
    tests = [p.subset(te) for p, (_, te) in zip(parts, rows, strict=True)]
    edge = args.mesh_mm * 1e-3
    at = np.concatenate([sampled_points(t, path) for t, path in zip(tests, paths, strict=True)])
    zero_shear = zero_shear_forces(at, edge)
    mag = np.linalg.norm(test.force, axis=1)
    report: dict = {
        "files": [str(p) for p in paths],
        "train_rows": len(train),
        "test_rows": len(test),
        "test_force_quantiles_N": dict(
            zip(
                ("10", "50", "90", "99", "max"),
                np.quantile(mag, [0.1, 0.5, 0.9, 0.99, 1.0]).round(2).tolist(),
                strict=True,
            )
        ),
        "models": {"zero-shear (true point's inward normal)": force_report(zero_shear, test.force)},
    }
    for name, model in (("mean", MeanPredictor()), ("classical", Classical())):
        report["models"][name] = force_report(model.fit(train).predict(test)["force"], test.force)
    for name, config in network_variants(args).items():
        start = time.perf_counter()
        net = NeuralEstimator(config).fit(train)
        predicted = net.predict(test)
        entry = force_report(predicted["force"], test.force)
        if "contact_loc" in predicted:
            errors = location_errors(predicted["contact_loc"], test.contact_loc)
            entry["contact_loc_mean_mm"] = round(float(errors.mean() * 1e3), 2)
        entry["epochs"], entry["wall_s"] = len(net.history), round(time.perf_counter() - start, 1)
        add_model(report, name, entry)
        if "contact_loc" in predicted:
            at_predicted = zero_shear_forces(predicted["contact_loc"], edge)
            report["models"][f"zero-shear at the {name} location"] = force_report(at_predicted, test.force)
    emit(report, args.json)


if __name__ == "__main__":
    main()
