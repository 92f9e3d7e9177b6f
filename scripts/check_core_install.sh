#!/usr/bin/env bash
# The core install on a fresh venv (issue 22): `pip install .` with no extras holds no torch, no MKL, no
# nvidia-* and no pypardiso, and runs `twin campaign run --quick` (its smallest form: one sensor, one indenter)
# and `twin demo`. Not part of the test suite (minutes, and it downloads the core's wheels).
#
# Usage: scripts/check_core_install.sh [WORK_DIR]   (default: a new temporary folder; kept for inspection)
# Prints each step's wall time, the package count and the result; exits 1 on the first failure.
set -euo pipefail

repo="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
work="${1:-$(mktemp -d -t biotac-core-XXXXXX)}"
mkdir -p "$work"
python="${PYTHON:-python3}"

step() {  # step NAME COMMAND...: run COMMAND, print its wall time (s), stop on failure
    local name="$1" start end
    shift
    start=$(date +%s)
    if ! "$@" >"$work/$name.log" 2>&1; then
        echo "FAIL $name (log: $work/$name.log)"
        tail -20 "$work/$name.log"
        exit 1
    fi
    end=$(date +%s)
    echo "ok   $name: $((end - start)) s"
}

echo "work folder: $work"
step venv "$python" -m venv "$work/venv"
step install "$work/venv/bin/pip" install "$repo"

"$work/venv/bin/pip" list --format=freeze >"$work/packages.txt"
echo "packages: $(wc -l <"$work/packages.txt") (list: $work/packages.txt)"
echo "venv size: $(du -sh "$work/venv" | cut -f1)"
forbidden=$(grep -i -E '^(torch|mkl|intel-openmp|tbb|pypardiso|nvidia-[^=]*)==' "$work/packages.txt" || true)
if [ -n "$forbidden" ]; then
    echo "FAIL the core install pulled:"
    echo "$forbidden"
    exit 1
fi
echo "ok   no torch, mkl, nvidia-* or pypardiso"

cd "$work"  # away from the source tree: the installed package is what runs
step campaign "$work/venv/bin/twin" campaign run --quick --sensors 2 --indenters sphere_medium --out "$work/quick"
step compare "$work/venv/bin/twin" compare "$work/quick/biotac2.hdf5" --out "$work/quick/report"
step demo "$work/venv/bin/twin" demo --out "$work/demo"
grep -i -E "hidden|verdict|revealed" "$work/demo.log" | tail -5 || true
if grep -q "CUDA driver" "$work"/*.log; then
    echo "note: a CUDA warning was printed on this machine (see the logs)"
fi
echo "ok   core install: $work"
