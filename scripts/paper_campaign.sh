#!/bin/bash
# The paper's campaign on GPUs (issue 18): every sensor's campaign on its own GPU (round robin over the GPUs
# given), then `twin dataset info` and `twin validate` per sensor on the GPU that ran it.
#
#   scripts/paper_campaign.sh OUT [GPUS] [WORKERS_PER_SENSOR]
#       OUT      folder: OUT/s1/biotac1.hdf5, ... , OUT/info1.json, OUT/validate1/ (validation.json, PNGs)
#       GPUS     comma-separated warp devices (default cuda:0); sensors 2 and 3 (~390 trajectories each) first
#       WORKERS  CPU worker processes per running campaign (default: cores / number of GPUs)
#
# A killed run resumes: `twin campaign run` keeps its parts, and a sensor whose file exists is only validated.
set -u
OUT=${1:?usage: scripts/paper_campaign.sh OUT [GPUS] [WORKERS_PER_SENSOR]}
IFS=, read -r -a GPUS <<< "${2:-cuda:0}"
WORKERS=${3:-$(( $(nproc) / ${#GPUS[@]} ))}
mkdir -p "$OUT"

sensor() {  # sensor id, device: campaign (resumed once if it stops), dataset info, validate
  local s=$1 device=$2 file="$OUT/s$1/biotac$1.hdf5"
  [ -f "$file" ] || python3 -m twin campaign run --sensors "$s" --device "$device" --workers "$WORKERS" --out "$OUT/s$s" \
    || python3 -m twin campaign run --sensors "$s" --device "$device" --workers "$WORKERS" --out "$OUT/s$s" || return
  python3 -m twin dataset info "$file" --json > "$OUT/info$s.json"
  python3 -m twin validate "$file" --device "$device" --out "$OUT/validate$s" --json > "$OUT/validate$s.json"
}

order=(2 3 1)
for g in "${!GPUS[@]}"; do
  (for k in "${!order[@]}"; do
     [ $(( k % ${#GPUS[@]} )) -eq "$g" ] && sensor "${order[$k]}" "${GPUS[$g]}"
   done) > "$OUT/gpu$g.log" 2>&1 &
done
wait
for s in 1 2 3; do [ -f "$OUT/info$s.json" ] && python3 -c "
import json, sys
d = json.load(open(sys.argv[1]))
print(f\"sensor {sys.argv[2]}: {d['trajectories']['total']} trajectories ({d['trajectories']['complete']} complete), {d['rows']} rows\")" \
  "$OUT/info$s.json" "$s"; done
