#!/bin/bash
# docs/learn.md's paper-size table (issue 19): every split the paper reports, on the three sensors' campaign
# files, all trainings at once on one device (a GPU when torch sees one), then the table.
#
#   scripts/paper_learn_table.sh OUT S1.hdf5 S2.hdf5 S3.hdf5 [TARGETS]
#       OUT      folder: learn_<run>.json per training, eval_unseen_sensor.json, <run>.log, table.md
#       S1..S3   the sensors' files (campaign HDF5 or their row copies); S3 is the unseen sensor
#       TARGETS  --targets of `twin learn train` (default contact_loc,force,nodal; contact_loc,force for row
#                copies without the nodal fields)
#
# Runs: PointNet++ / MLP / classical pair / mean on the contiguous split, PointNet++ non-contiguous, PointNet++
# trained on S1 + S2 and scored on every row of S3, PointNet++ with the ring held out. LEARN_S (default 420)
# caps each training's seconds; THREADS (default 3) torch CPU threads per training.
set -u
OUT=${1:?usage: scripts/paper_learn_table.sh OUT S1.hdf5 S2.hdf5 S3.hdf5 [TARGETS]}
S1=${2:?S1}; S2=${3:?S2}; S3=${4:?S3}; TARGETS=${5:-contact_loc,force,nodal}
mkdir -p "$OUT"
ALL=("$S1" "$S2" "$S3")
NET=(--targets "$TARGETS" --patience 15 --time-limit "${LEARN_S:-420}" --threads "${THREADS:-3}" --device auto --json)

train() {  # run name, then `twin learn train` arguments; JSON to OUT/learn_<name>.json, wall time to OUT/events
  local name=$1 t0; shift; t0=$(date +%s)
  python3 -m twin learn train "$@" --out "$OUT/$name.pt" > "$OUT/learn_$name.json" 2> "$OUT/$name.log"
  echo "$name rc=$? wall=$(( $(date +%s) - t0 )) s" >> "$OUT/events"
}

train pointnet_contiguous "${ALL[@]}" --model pointnet --split contiguous "${NET[@]}" &
train mlp_contiguous "${ALL[@]}" --model mlp --split contiguous "${NET[@]}" &
train pointnet_noncontiguous "${ALL[@]}" --model pointnet --split noncontiguous "${NET[@]}" &
train pointnet_unseen_ring "${ALL[@]}" --model pointnet --split indenter:ring "${NET[@]}" &
(train pointnet_sensors12 "$S1" "$S2" --model pointnet --split contiguous "${NET[@]}"
 python3 -m twin learn eval "$OUT/pointnet_sensors12.pt" --data "$S3" --on all --json \
   > "$OUT/eval_unseen_sensor.json" 2>> "$OUT/pointnet_sensors12.log") &
(train classical_contiguous "${ALL[@]}" --model classical --split contiguous --targets "$TARGETS" --json
 train mean_contiguous "${ALL[@]}" --model mean --split contiguous --targets "$TARGETS" --json) &
wait
cat "$OUT/events"

python3 - "$OUT" <<'EOF' | tee "$OUT/table.md"
"""The markdown table of every run's per-sensor and combined scores."""
import json
import sys
from pathlib import Path

out = Path(sys.argv[1])
runs = sorted(out.glob("learn_*.json")) + [out / "eval_unseen_sensor.json"]
print("| run | set | location mean / median (mm) | force magnitude median (N) | force angle mean (rad) | rows |")
print("|---|---|---|---|---|---|")
for path in runs:
    if not path.is_file() or not path.stat().st_size:
        print(f"| {path.stem} | failed: see its log | | | | |")
        continue
    result = json.loads(path.read_text())
    result = result[0] if isinstance(result, list) else result
    for name, m in {**result["per_sensor"], "combined": result["combined"]}.items():
        print(f"| {path.stem.removeprefix('learn_')} | {name} | {m['contact_loc_mean_mm']:.2f} / "
              f"{m['contact_loc_median_mm']:.2f} | {m['force_magnitude_median_N']:.3f} | "
              f"{m['force_angle_mean_rad']:.3f} | {m['n_samples']:.0f} |")
EOF
