"""Plot the per-round trace of batched FE runs (`fe_bench.py --batch N --json run.json`): systems iterated per
round and wall time per round (ms) against the run's time (s), one line per file.

    python benchmarks/plot_fe_trace.py run1.json [run2.json ...] --out trace.png [--labels a,b]
"""

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def load_trace(path: Path) -> tuple[np.ndarray, np.ndarray, int]:
    """Round end times (s), systems iterated per round and slots of the continuous run in an fe_bench JSON."""
    data = json.loads(path.read_text())
    if not isinstance(data, dict) or "trace" not in data:
        raise ValueError(f"{path} has no per-round trace: write it with fe_bench.py --batch N --json FILE")
    trace = data["trace"]
    return np.asarray(trace["round_end_s"]), np.asarray(trace["round_systems"]), int(data["rows"][-1]["slots"])


def plot(paths: list[Path], labels: list[str], out: Path) -> None:
    """Two panels sharing the time axis: busy systems (share of the slots) and ms per round."""
    fig, (busy, cost) = plt.subplots(2, 1, sharex=True, figsize=(8, 6))
    for path, label in zip(paths, labels, strict=True):
        end, systems, slots = load_trace(path)
        busy.plot(end, systems / slots, label=f"{label} ({slots} slots)")
        cost.plot(end, 1e3 * np.diff(end, prepend=0.0), lw=0.6, label=label)
    busy.set_ylabel("systems iterated / slots")
    busy.set_ylim(0, 1.05)
    busy.legend()
    cost.set_ylabel("ms per round")
    cost.set_yscale("log")
    cost.set_xlabel("time since the start of the run (s)")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="fe_bench --json files")
    parser.add_argument("--out", type=Path, required=True, help="image file (.png)")
    parser.add_argument("--labels", default=None, help="comma-separated, one per run (default: file names)")
    args = parser.parse_args()
    labels = args.labels.split(",") if args.labels else [p.stem for p in args.runs]
    if len(labels) != len(args.runs):
        parser.error(f"{len(labels)} labels for {len(args.runs)} runs")
    plot(args.runs, labels, args.out)


if __name__ == "__main__":
    main()
