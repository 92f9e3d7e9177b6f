"""Environment speed: environment steps per second, stand-alone and vectorised, on the coarse FE mesh.

    python3 benchmarks/env_bench.py [--env BioTacPress-v0] [--steps 40] [--num-envs 4,8] [--mesh-mm 2]

Every environment runs `--steps` steps of a pressing policy (mostly pressing, some sideways motion:
uniform in [-0.3, 0.3] x [-0.3, 0.3] x [-0.2, 1] of the action bounds, seeded) with autoreset, so the
count mixes free, contact and reset steps as training does. "env steps/s" counts sub-environment
steps; "FE share" is the part of the wall time spent inside the FE batch call. The vector env steps
its sub-environments through one `step_batch` call: by default a loop over per-slot CPU steppers
(expect the same env steps/s as stand-alone); with `--fe-device cpu|cuda:0` the batched warp FE
(`fe.batched_stepper`), whose cost per call grows slowly with the number of environments.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
from rich.console import Console
from rich.table import Table

import twin  # noqa: F401  (registers the environments)


def _actions(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform([-0.3, -0.3, -0.2], [0.3, 0.3, 1.0], (n, 3))


def single(env_id: str, steps: int, mesh_mm: float, seed: int, fe_device: str | None) -> dict:
    """One stand-alone environment for `steps` steps."""
    env = gym.make(env_id, mesh_mm=mesh_mm, fe_device=fe_device)
    fe = env.unwrapped.fe
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    fe.wall_s = 0.0
    start = time.perf_counter()
    for _ in range(steps):
        _, _, terminated, truncated, _ = env.step(_actions(rng, 1)[0])
        if terminated or truncated:
            env.reset()
    wall = time.perf_counter() - start
    env.close()
    return {"mode": "single", "num_envs": 1, "env_steps": steps, "wall_s": wall, "fe_s": fe.wall_s}


def vectorised(env_id: str, num_envs: int, steps: int, mesh_mm: float, seed: int, fe_device: str | None) -> dict:
    """A vector env of `num_envs` for `steps` vector steps (autoreset)."""
    env = gym.make_vec(
        env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", mesh_mm=mesh_mm, fe_device=fe_device
    )
    fe = env.fe
    rng = np.random.default_rng(seed)
    env.reset(seed=seed)
    fe.wall_s = 0.0
    start = time.perf_counter()
    for _ in range(steps):
        env.step(_actions(rng, num_envs))
    wall = time.perf_counter() - start
    env.close()
    return {"mode": "vector", "num_envs": num_envs, "env_steps": steps * num_envs, "wall_s": wall, "fe_s": fe.wall_s}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="BioTacPress-v0")
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--num-envs", default="4,8")
    parser.add_argument("--mesh-mm", type=float, default=2.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--fe-device", default=None, help="warp device of the batched FE (cpu, cuda:0); default: the CPU stepper loop"
    )
    args = parser.parse_args()
    run = (args.env, args.steps, args.mesh_mm, args.seed, args.fe_device)
    single(args.env, 3, args.mesh_mm, args.seed, args.fe_device)  # warm-up: model build, kernel compilation
    rows = [single(*run)]
    rows += [vectorised(args.env, int(n), *run[1:]) for n in args.num_envs.split(",")]
    table = Table(
        "mode",
        "envs",
        "env steps",
        "wall (s)",
        "env steps/s",
        "FE share",
        title=f"{args.env}, {args.mesh_mm} mm mesh, FE {args.fe_device or 'CPU stepper loop'}",
    )
    for r in rows:
        table.add_row(
            r["mode"],
            str(r["num_envs"]),
            str(r["env_steps"]),
            f"{r['wall_s']:.1f}",
            f"{r['env_steps'] / r['wall_s']:.1f}",
            f"{r['fe_s'] / r['wall_s']:.0%}",
        )
    Console().print(table)


if __name__ == "__main__":
    main()
