"""Error breakdown by row property, the contact-row filter and the location study script (issue 19)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from learn.breakdown import by_group, force_bins
from learn.data import TactileData, with_min_force

ROOT = Path(__file__).resolve().parents[1]


def test_by_group_gives_hand_computed_means_medians_and_shares() -> None:
    errors = np.array([1.0, 1.0, 3.0, 5.0, 10.0])
    groups = np.array(["a", "a", "b", "b", "b"])
    table = by_group(errors, groups)
    assert table["a"] == {"n": 2, "row_share": 0.4, "mean": 1.0, "median": 1.0, "error_share": 2.0 / 20.0}
    assert table["b"]["mean"] == pytest.approx(6.0)
    assert table["b"]["median"] == 5.0
    assert table["b"]["error_share"] == pytest.approx(18.0 / 20.0)
    overall = sum(s["row_share"] * s["mean"] for s in table.values())
    assert overall == pytest.approx(errors.mean())


def test_by_group_refuses_mismatched_shapes() -> None:
    with pytest.raises(ValueError, match="same"):
        by_group(np.zeros(3), np.zeros(4))


def test_force_bins_use_the_vector_magnitude_and_half_open_bins() -> None:
    forces = np.array([[0.03, 0.04, 0.0], [0.18, 0.24, 0.0], [0.0, 0.0, 0.5], [3.0, 4.0, 0.0], [0.0, 0.0, 0.0999]])
    assert force_bins(forces).tolist() == ["0-0.1 N", "0.1-0.5 N", "0.5-1 N", "5-inf N", "0-0.1 N"]


def _rows(force: np.ndarray) -> TactileData:
    n = len(force)
    return TactileData(
        sensor="s",
        electrodes=np.arange(n * 19, dtype=float).reshape(n, 19),
        trajectory=np.arange(n),
        indenter=np.zeros(n, dtype=np.int64),
        indenter_names=("sphere",),
        contact_loc=np.arange(n * 3, dtype=float).reshape(n, 3),
        force=force,
    )


def test_with_min_force_keeps_exactly_the_rows_at_or_above_the_threshold() -> None:
    force = np.array([[0.0, 0.0, 0.1], [0.0, 0.0, 0.5], [0.0, 0.0, 0.49], [0.0, 2.0, 0.0]])
    kept = with_min_force(_rows(force), 0.5)
    assert kept.trajectory.tolist() == [1, 3]  # |F| = 0.5 is kept, 0.49 is not
    assert np.array_equal(kept.contact_loc, _rows(force).contact_loc[[1, 3]])
    with pytest.raises(ValueError, match="force"):
        with_min_force(TactileData("s", np.zeros((1, 19)), np.zeros(1, int), np.zeros(1, int), ("a",)), 0.5)


def test_study_tables_add_up_and_no_contact_rows_are_the_hardest(tmp_path) -> None:
    """On a synthetic campaign with no-contact rows appended (zero force, electrodes at rest + noise): every
    breakdown covers all test rows and reproduces the overall mean, and the weighted centroid, which has
    nothing to locate there, is worse on the < 0.1 N rows than on the rows in contact."""
    import h5py

    from learn.synthetic import write_synthetic_campaign

    path = write_synthetic_campaign(tmp_path / "biotac1.hdf5", 40, seed=2)
    rng = np.random.default_rng(0)
    with h5py.File(path, "r+") as f:
        n = len(f["force/data"])
        idle = rng.choice(n, size=n // 3, replace=False)
        for name, noise in (("force", 0.01), ("electrode_vals", 3.0), ("fe_force", 0.0)):
            values = f[f"{name}/data"][:]
            values[idle] = rng.normal(0.0, noise, (len(idle), values.shape[1]))
            f[f"{name}/data"][...] = values
    out = tmp_path / "study.json"
    subprocess.run(
        [sys.executable, str(ROOT / "scripts/location_error_study.py"), str(path), "--models", "mean,classical",
         "--json", str(out)],
        check=True, capture_output=True, text=True, cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": ""},
    )  # fmt: skip
    report = json.loads(out.read_text())
    for model, entry in report["models"].items():
        for name, table in entry["by"].items():
            assert sum(s["n"] for s in table.values()) == report["test_rows"], (model, name)
            overall = sum(s["row_share"] * s["mean"] for s in table.values())
            assert overall == pytest.approx(entry["mean_mm"]), (model, name)
    classical = report["models"]["classical"]["by"]["|F|"]
    in_contact = [s["mean"] for k, s in classical.items() if not k.startswith("0-")]
    assert classical["0-0.1 N"]["mean"] > 1.5 * max(in_contact)
    assert report["contact_rows_only"]["classical"]["mean_mm"] < report["models"]["classical"]["mean_mm"]


def test_min_force_drops_low_force_rows_after_an_unchanged_split(tmp_path) -> None:
    from learn.experiment import SplitSpec, evaluate_checkpoint, load_files, split_rows, train
    from learn.synthetic import write_synthetic_campaign

    path = write_synthetic_campaign(tmp_path / "biotac1.hdf5", 30, seed=4)
    parts = load_files([path])
    ((train_all, test_all),) = split_rows(parts, SplitSpec("contiguous"))
    ((train_rows, test_rows),) = split_rows(parts, SplitSpec("contiguous", min_force=0.5))
    strong = np.linalg.norm(parts[0].force, axis=1) >= 0.5
    assert 0 < strong.sum() < len(strong)  # the file has rows on both sides of the threshold
    assert np.array_equal(train_rows, train_all[strong[train_all]])
    assert np.array_equal(test_rows, test_all[strong[test_all]])
    checkpoint = train([path], "classical", SplitSpec("contiguous", min_force=0.5))
    assert checkpoint.metrics["combined"]["n_samples"] == len(test_rows)
    again = evaluate_checkpoint(checkpoint, [path], on="test")
    assert again["combined"] == checkpoint.metrics["combined"]
    assert evaluate_checkpoint(checkpoint, [path], on="all")["combined"]["n_samples"] == strong.sum()
