"""Train a linear press policy on BioTacPress-v0 with the cross-entropy method; plot its learning curve.

The policy sees only the environment's observation (tared electrodes and PDC, commanded tip in the
target frame, target force) through seven features and outputs clip(W phi, -1, 1), W (3, 7) sparse
(`MASK`: sideways increments from the sideways offsets, the press increment from PDC, electrodes, target
force and depth). Each CEM iteration evaluates `--population` candidate W (the first is the current
mean) on the same `--episodes` episodes, all candidates x episodes as the sub-environments of one vector
env (so each step is one batched FE call), and refits the Gaussian over W to the best `--elites`. A
random policy (uniform actions) on held-out seeds is the baseline; the final mean W is evaluated on the
same held-out seeds.

    python3 scripts/train_press_policy.py --out docs/img/press_training.png [--device cuda] [--mesh-mm 2]

Cost: about (population x episodes + validation) x iterations x max_steps FE increments on the coarse
mesh (a few minutes on two CPU cores with the defaults).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path

import gymnasium as gym
import numpy as np
from matplotlib.figure import Figure

import twin  # noqa: F401  (registers the environments)
from twin.envs.fe_batch import check_device

N_FEATURES = 7
MASK = np.array(
    [
        [0, 0, 0, 1, 0, 0, 1],  # t1 increment: from the tip's t1 offset
        [0, 0, 0, 0, 1, 0, 1],  # t2 increment: from the tip's t2 offset
        [1, 1, 1, 0, 0, 1, 1],  # press increment: from PDC, electrodes, target force, press depth
    ],
    dtype=bool,
)
"""The weights CEM searches (9 of 3 x 7); the others are 0."""
Policy = Callable[[dict[str, np.ndarray]], np.ndarray]


def features(obs: dict[str, np.ndarray]) -> np.ndarray:
    """(N, 7) features of a batch of observations: PDC and mean electrode (hundreds of counts), target
    force (N), commanded tip in the target frame (mm), a constant."""
    n = len(obs["pdc"])
    return np.column_stack(
        [
            obs["pdc"][:, 0] / 100.0,
            obs["electrodes"].mean(axis=1) / 100.0,
            obs["target_force"][:, 0],
            obs["tip"],
            np.ones(n),
        ]
    )


def linear_policies(weights: np.ndarray) -> Policy:
    """Sub-environment k acts with clip(weights[k] @ phi, -1, 1); weights (N, 3, 7)."""
    return lambda obs: np.clip(np.einsum("kaf,kf->ka", weights, features(obs)), -1.0, 1.0)


def random_policy(rng: np.random.Generator, n: int) -> Policy:
    """Uniform actions in [-1, 1]^3."""
    return lambda obs: rng.uniform(-1.0, 1.0, (n, 3))


def episode_returns(env: gym.vector.VectorEnv, policy: Policy, seeds: list[int], max_steps: int) -> np.ndarray:
    """One episode per sub-environment (sub-environment k on seeds[k]); the return of each up to its end."""
    obs, _ = env.reset(seed=seeds)
    returns = np.zeros(env.num_envs)
    running = np.ones(env.num_envs, dtype=bool)
    for _ in range(max_steps):
        obs, reward, terminated, truncated, _ = env.step(policy(obs))
        returns += np.where(running, reward, 0.0)
        running &= ~(terminated | truncated)
        if not running.any():
            break
    return returns


def train(args: argparse.Namespace) -> dict:
    """Run CEM and the baseline; returns the curve and the evaluation numbers.

    Each iteration the vector env holds population x episodes training sub-environments (every candidate
    on the same fresh episodes, so candidates are ranked on equal terms; candidate 0 is the current mean)
    and `--validation` more that play the current mean on fixed validation episodes: the curve.
    """
    rng = np.random.default_rng(args.seed)
    n_train = args.population * args.episodes
    env = gym.make_vec(
        "BioTacPress-v0",
        num_envs=n_train + args.validation,
        vectorization_mode="vector_entry_point",
        max_steps=args.max_steps,
        mesh_mm=args.mesh_mm,
        device=args.device,
    )
    validation_seeds = [10**5 + k for k in range(args.validation)]
    mean = np.zeros((3, N_FEATURES))
    std = np.where(MASK, args.init_std, 0.0)
    curve = []
    for iteration in range(args.iterations + 1):
        start = time.perf_counter()
        weights = mean + std * rng.standard_normal((args.population, 3, N_FEATURES))
        weights[0] = mean
        played = np.concatenate([np.repeat(weights, args.episodes, 0), np.repeat(mean[None], args.validation, 0)])
        seeds = [1000 * (iteration + 1) + e for _ in range(args.population) for e in range(args.episodes)]
        per_episode = episode_returns(env, linear_policies(played), seeds + validation_seeds, args.max_steps)
        returns = per_episode[:n_train].reshape(args.population, args.episodes).mean(axis=1)
        validation = float(per_episode[n_train:].mean())
        curve.append({"iteration": iteration, "validation": validation, "population": float(returns.mean())})
        print(
            f"iteration {iteration}: mean policy on validation {validation:.2f}, population {returns.mean():.2f} "
            f"({time.perf_counter() - start:.0f} s)",
            flush=True,
        )
        if iteration == args.iterations:  # the last pass only measures the final mean
            break
        elite = weights[np.argsort(returns)[-args.elites :]]
        mean, std = elite.mean(axis=0), np.where(MASK, elite.std(axis=0) + args.min_std, 0.0)
    held_out = [10**6 + k for k in range(env.num_envs)]
    trained = episode_returns(env, linear_policies(np.repeat(mean[None], env.num_envs, 0)), held_out, args.max_steps)
    baseline = episode_returns(env, random_policy(rng, env.num_envs), held_out, args.max_steps)
    env.close()
    return {
        "curve": curve,
        "trained": {"mean": float(trained.mean()), "std": float(trained.std()), "episodes": len(trained)},
        "random": {"mean": float(baseline.mean()), "std": float(baseline.std()), "episodes": len(baseline)},
        "weights": mean.tolist(),
        "settings": {k: str(v) for k, v in vars(args).items() if k not in ("out", "json")},
    }


def plot(result: dict, out: Path) -> None:
    """The learning curve with the random baseline and the final evaluation."""
    fig = Figure(figsize=(6.0, 3.8), layout="constrained")
    ax = fig.add_subplot()
    iterations = [c["iteration"] for c in result["curve"]]
    ax.plot(iterations, [c["validation"] for c in result["curve"]], "o-", label="mean policy, validation episodes")
    ax.plot(
        iterations, [c["population"] for c in result["curve"]], "s--", alpha=0.5, label="population, training episodes"
    )
    for name, colour in (("random", "tab:red"), ("trained", "tab:green")):
        stats = result[name]
        ax.axhline(stats["mean"], color=colour, label=f"{name} policy, held-out seeds ({stats['mean']:.1f})")
        ax.axhspan(stats["mean"] - stats["std"], stats["mean"] + stats["std"], color=colour, alpha=0.12)
    ax.set(xlabel="CEM iteration", ylabel="episode return", title="BioTacPress-v0, linear policy (coarse FE mesh)")
    ax.legend(fontsize=7, loc="lower right")
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/img/press_training.png"))
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--population", type=int, default=10)
    parser.add_argument("--episodes", type=int, default=2, help="Episodes per candidate and iteration.")
    parser.add_argument("--validation", type=int, default=4, help="Fixed episodes the mean policy plays.")
    parser.add_argument("--elites", type=int, default=3)
    parser.add_argument("--max-steps", type=int, default=10)
    parser.add_argument("--init-std", type=float, default=0.5)
    parser.add_argument("--min-std", type=float, default=0.1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--mesh-mm", type=float, default=2.0, help="FE mesh edge (mm).")
    parser.add_argument("--device", default="cpu", help="Warp device of the batched FE (cpu, cuda, cuda:0, ...).")
    parser.add_argument("--json", type=Path, default=None, help="Also write the numbers to this JSON file.")
    args = parser.parse_args()
    if not 0 < args.elites <= args.population or args.iterations < 1 or args.episodes < 1:
        parser.error("need 0 < elites <= population, iterations >= 1 and episodes >= 1")
    try:
        check_device(args.device)
    except ValueError as error:
        parser.exit(2, f"train_press_policy: {error}\n")
    result = train(args)
    plot(result, args.out)
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: result[k] for k in ("trained", "random")}))


if __name__ == "__main__":
    main()
