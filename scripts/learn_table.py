"""One command for docs/learn.md's FE table: campaign (resumed if present), compact copies, paper's protocol.

    python3 scripts/learn_table.py --out out/learn_fe --points 2 --angled 2 --time-limit 1200
        # docs/learn.md's 2026-11-26 table: 112 trajectories (22 min on 2 shared cores), then the table
        # (GPU when torch sees one, else the CPU)
    python3 scripts/learn_table.py --out out/learn_fe --skip-campaign --scale-tail 0   # min-max rows

Steps: `scripts/make_learn_campaign.py --out OUT` (skipped with --skip-campaign, e.g. on a GPU machine
where only OUT_compact was carried), `--compact OUT_compact`, then `benchmarks/learn_bench.py --table 3
--campaign OUT_compact`, whose markdown table and JSON (OUT_compact/table.json) are the result.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(args: list[str]) -> None:
    """Run a repository script with this interpreter; stop with its exit status when it fails."""
    print("$ " + " ".join(args), flush=True)
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)
    done = subprocess.run([sys.executable, *args], cwd=ROOT, env={**os.environ, "PYTHONPATH": path})
    if done.returncode:
        sys.exit(done.returncode)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=Path("out/learn_fe"), help="campaign folder")
    ap.add_argument("--points", type=int, default=2, help="ventral points per indenter")
    ap.add_argument("--angled", type=int, default=2, help="30 deg paths per point")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--time-limit", type=float, default=None, help="campaign: stop starting trajectories (s)")
    ap.add_argument("--skip-campaign", action="store_true", help="use OUT_compact as it is")
    ap.add_argument("--models", default="pointnet,mlp,classical,mean")
    ap.add_argument("--device", default="auto", choices=("auto", "cpu", "cuda"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--scale-tail", type=float, default=None, help="networks' scaling (default: TrainConfig's)")
    ap.add_argument("--patience", type=int, default=10)
    ap.add_argument("--time-limit-network", type=float, default=300.0, help="s per network")
    args = ap.parse_args()
    compact = args.out.with_name(args.out.name + "_compact")
    if not args.skip_campaign:
        campaign = ["scripts/make_learn_campaign.py", "--out", str(args.out), "--workers", str(args.workers)]
        campaign += ["--points", str(args.points), "--angled", str(args.angled)]
        if args.time_limit is not None:
            campaign += ["--time-limit", str(args.time_limit)]
        run(campaign)
        run(["scripts/make_learn_campaign.py", "--out", str(args.out), "--compact", str(compact)])
    elif not sorted(compact.glob("biotac*.hdf5")):
        ap.exit(2, f"learn_table.py: error: --skip-campaign but no biotac*.hdf5 in {compact}\n")
    table = ["benchmarks/learn_bench.py", "--table", "3", "--campaign", str(compact), "--models", args.models]
    table += ["--device", args.device, "--threads", str(args.threads), "--patience", str(args.patience)]
    table += ["--time-limit", str(args.time_limit_network), "--json", str(compact / "table.json")]
    if args.scale_tail is not None:
        table += ["--scale-tail", str(args.scale_tail)]
    run(table)


if __name__ == "__main__":
    main()
