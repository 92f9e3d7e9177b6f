"""Environment speed: environment steps per second of the vector env on the batched FE, against one env.

    python3 benchmarks/env_bench.py --device cpu|cuda --mesh-mm 2[,1,0.5] --num-envs 1,8,64 [--steps 20]
                                     [--same-episodes]

For each mesh (largest edge, mm) a vector env of each `--num-envs` size (`twin.envs.vector.TactileVectorEnv`:
all sub-environments' FE solved together by one `fe.batched_stepper.BatchedStepper` on the warp
`--device`) runs `--steps` vector steps of a pressing policy (mostly pressing, some sideways motion:
uniform in [-0.3, 0.3] x [-0.3, 0.3] x [-0.2, 1] of the action bounds, seeded) with autoreset, so the
count mixes free, contact and reset steps as training does. Sub-environment k plays its own episodes
(seed + k); with `--same-episodes` all play the baseline's episodes and actions, so the ratio measures
the batch's throughput on equal work, free of the episode mix. Before the timed runs, a stand-alone
environment (one FE system) runs the same number of steps on that mesh and device: the baseline
("vs 1 env" = env steps/s over the baseline's). "env steps/s" counts sub-environment steps; "FE share"
is the part of the wall time spent inside the FE batch call; "CPU (s)" is the process's CPU time (all
threads), which, unlike the wall time, does not grow when other jobs share the cores. "rounds/step" is the
device-independent cost: Newton rounds per vector step (one evaluation of every slot still solving and one
batched linear solve each: a vector step takes as many as its slowest sub-environment needs), and
"evals/env step" the slot evaluations of those rounds per sub-environment step (what the sub-environments
need on their own). A short untimed run first builds the model and compiles the kernels.

Needs only numpy, scipy, warp, trimesh (with rtree, which trimesh imports for the meshes' bounds tree)
and gymnasium beside the project (no mujoco, rerun, torch, rich or h5py): it runs on a bare GPU machine.
A device warp does not have is one line, exit 2.
"""

from __future__ import annotations

import argparse
import sys
import time

import gymnasium as gym
import numpy as np

import twin  # noqa: F401  (registers the environments)
from twin.envs.fe_batch import IndentationBatch, check_device

COLUMNS = (
    "mesh (mm)",
    "mode",
    "envs",
    "env steps",
    "wall (s)",
    "CPU (s)",
    "env steps/s",
    "vs 1 env",
    "FE share",
    "rounds/step",
    "evals/env step",
)


def _actions(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform([-0.3, -0.3, -0.2], [0.3, 0.3, 1.0], (n, 3))


def single(env_id: str, steps: int, mesh_mm: float, seed: int, device: str) -> dict:
    """The baseline: one stand-alone environment (one FE system) for `steps` steps."""
    env = gym.make(env_id, mesh_mm=mesh_mm, device=device)
    fe = env.unwrapped.fe
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    _zero_counts(fe)
    start, cpu = time.perf_counter(), time.process_time()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(_actions(rng, 1)[0])
        if terminated or truncated:
            env.reset()
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    env.close()
    run = {"mode": "single", "num_envs": 1, "vector_steps": steps, "env_steps": steps, "wall_s": wall, "cpu_s": cpu}
    return run | _counts(fe)


def vectorised(
    env_id: str, num_envs: int, steps: int, mesh_mm: float, seed: int, device: str, same: bool = False
) -> dict:
    """A vector env of `num_envs` for `steps` vector steps (autoreset); `same`: every sub-environment plays
    the baseline's episodes and actions (the batch's throughput on equal work), else its own."""
    env = gym.make_vec(
        env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", mesh_mm=mesh_mm, device=device
    )
    fe = env.fe
    rng = np.random.default_rng(seed)
    env.reset(seed=[seed] * num_envs if same else seed)
    _zero_counts(fe)
    start, cpu = time.perf_counter(), time.process_time()
    for _ in range(steps):
        env.step(np.tile(_actions(rng, 1), (num_envs, 1)) if same else _actions(rng, num_envs))
    wall, cpu = time.perf_counter() - start, time.process_time() - cpu
    env.close()
    return {
        "mode": "vector, same" if same else "vector",
        "num_envs": num_envs,
        "vector_steps": steps,
        "env_steps": steps * num_envs,
        "wall_s": wall,
        "cpu_s": cpu,
    } | _counts(fe)


def _zero_counts(fe: IndentationBatch) -> None:
    """Start the FE batch's time and work counters afresh (after the untimed reset)."""
    fe.wall_s, fe.rounds, fe.system_evaluations = 0.0, 0, 0


def _counts(fe: IndentationBatch) -> dict:
    """The FE batch's time (s) and work (Newton rounds, slot evaluations) since `_zero_counts`."""
    return {"fe_s": fe.wall_s, "rounds": fe.rounds, "evaluations": fe.system_evaluations}


def table_row(mesh_mm: float, row: dict, baseline: dict) -> list[str]:
    """One markdown table row of a run, its speed also relative to the baseline's."""
    rate = row["env_steps"] / row["wall_s"]
    ratio = rate / (baseline["env_steps"] / baseline["wall_s"])
    return [
        f"{mesh_mm:g}",
        row["mode"],
        str(row["num_envs"]),
        str(row["env_steps"]),
        f"{row['wall_s']:.1f}",
        f"{row['cpu_s']:.1f}",
        f"{rate:.1f}",
        f"{ratio:.2f}",
        f"{row['fe_s'] / row['wall_s']:.0%}",
        f"{row['rounds'] / row['vector_steps']:.1f}",
        f"{row['evaluations'] / row['env_steps']:.1f}",
    ]


def _fail(message: str) -> None:
    """Bad input: one line on stderr, exit status 2."""
    print(f"env_bench: {message}", file=sys.stderr)
    sys.exit(2)


def _numbers(text: str, kind: type, name: str) -> list:
    try:
        values = [kind(v) for v in text.split(",")]
    except ValueError:
        values = []
    if not values or min(values) <= 0:
        _fail(f"{name} must be positive numbers separated by commas, got {text!r}")
    return values


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="BioTacPress-v0")
    parser.add_argument("--device", default="cpu", help="warp device of the FE: cpu, cuda, cuda:0, ...")
    parser.add_argument("--mesh-mm", default="2", help="mesh edge(s) in mm, comma separated (2, 1, 0.5)")
    parser.add_argument("--num-envs", default="1,4", help="vector env size(s), comma separated")
    parser.add_argument("--steps", type=int, default=20, help="vector steps per run")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--same-episodes", action="store_true", help="every sub-environment plays the baseline's episodes and actions"
    )
    args = parser.parse_args()
    meshes = _numbers(args.mesh_mm, float, "--mesh-mm")
    sizes = _numbers(args.num_envs, int, "--num-envs")
    if args.steps < 1:
        _fail("--steps must be at least 1")
    try:
        check_device(args.device)
    except ValueError as error:
        _fail(str(error))
    print(f"{args.env}, FE on warp device {args.device!r}, {args.steps} steps per run\n")
    print("| " + " | ".join(COLUMNS) + " |")
    print("|" + "---|" * len(COLUMNS))
    for mesh_mm in meshes:
        single(args.env, 3, mesh_mm, args.seed, args.device)  # untimed: model build, kernel compilation
        baseline = single(args.env, args.steps, mesh_mm, args.seed, args.device)
        run = (args.steps, mesh_mm, args.seed, args.device, args.same_episodes)
        rows = [baseline] + [vectorised(args.env, n, *run) for n in sizes]
        for row in rows:
            print("| " + " | ".join(table_row(mesh_mm, row, baseline)) + " |", flush=True)


if __name__ == "__main__":
    main()
