"""benchmarks/learn_bench.py runs where only torch, numpy, scipy and h5py are installed (the lent GPU
machine): a subprocess with warp, MuJoCo, trimesh and rerun made unimportable runs it end to end."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BLOCKED = ("warp", "mujoco", "trimesh", "rerun", "gymnasium", "typer")
RUNNER = """
import runpy, sys
for name in {blocked!r}:
    sys.modules[name] = None  # import of it raises ImportError
sys.argv = ["learn_bench.py", *sys.argv[1:]]
runpy.run_path("benchmarks/learn_bench.py", run_name="__main__")
"""


def test_learn_bench_runs_without_the_simulation_stack(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    args = ["--samples", "150", "--models", "mlp,pointnet", "--max-epochs", "2", "--threads", "1"]
    args += ["--device", "auto", "--data", str(tmp_path / "data"), "--json", str(out)]
    run = subprocess.run(
        [sys.executable, "-c", RUNNER.format(blocked=BLOCKED), *args],
        cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    report = json.loads(out.read_text())
    assert report["samples"] > 100
    for model in ("mlp", "pointnet"):
        entry = report["models"][model]
        assert entry["epochs"] == 2 and entry["stopped_by"] == "max epochs"
        assert 0.0 < entry["time_to_convergence_s"] <= entry["wall_s"]
        assert entry["inference_samples_per_s"] > 0.0
