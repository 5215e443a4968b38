"""``udan-eval``: paper-style score tables (rows obstacles, columns agents) for a policy.

Every cell runs its episodes as one batch with a seed derived from (seed, agents, obstacles),
so two policies evaluated with the same ``--seed`` meet exactly the same layouts.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from udan.envs import EnvConfigError, make_vec
from udan.envs.errors import parse_range
from udan.policies import POLICIES, Policy


@dataclass
class CellResult:
    """Scores of one (agents, obstacles) cell, averaged over its episodes."""

    agents: int
    obstacles: int
    episodes: int
    agent_score: float
    """Mean over episodes of the average agent's episode return."""
    target_score: float
    """surround only: the target's episode score (0 for find_water)."""


def run_cell(
    env_name: str, policy: Policy, agents: int, obstacles: int, episodes: int, seed: int
) -> CellResult:
    """Play ``episodes`` episodes with exactly ``agents`` agents and ``obstacles`` obstacles."""
    cell_seed = np.random.SeedSequence([seed, agents, obstacles])
    env = make_vec(
        env_name,
        batch=episodes,
        seed=cell_seed,
        agents=(agents, agents),
        obstacles=(obstacles, obstacles),
    )
    env.reset()
    policy.reset(env)
    done = np.zeros(episodes, dtype=bool)
    while not done.all():
        _, _, done = env.step(policy.act(env))
    per_agent = env.episode_return.sum(axis=1) / agents
    return CellResult(
        agents, obstacles, episodes, float(per_agent.mean()), float(env.target_score.mean())
    )


def evaluate(
    env_name: str,
    policy: Policy,
    agents: tuple[int, int],
    obstacles: tuple[int, int],
    episodes: int,
    seed: int,
) -> list[CellResult]:
    """Every cell of the agents x obstacles grid."""
    return [
        run_cell(env_name, policy, n, m, episodes, seed)
        for m in range(obstacles[0], obstacles[1] + 1)
        for n in range(agents[0], agents[1] + 1)
    ]


def format_table(results: list[CellResult], field: str, title: str) -> str:
    """Markdown table: one row per obstacle count, one column per agent count, plus the mean."""
    agents = sorted({r.agents for r in results})
    obstacles = sorted({r.obstacles for r in results})
    value = {(r.obstacles, r.agents): getattr(r, field) for r in results}
    lines = [
        f"**{title}**",
        "",
        "| obstacles \\ agents | " + " | ".join(map(str, agents)) + " | mean |",
        "|---" * (len(agents) + 2) + "|",
    ]
    for m in obstacles:
        row = [value[m, n] for n in agents]
        lines.append(f"| {m} | " + " | ".join(f"{v:.2f}" for v in row) + f" | {np.mean(row):.2f} |")
    lines.append(
        "| mean | "
        + " | ".join(f"{np.mean([value[m, n] for m in obstacles]):.2f}" for n in agents)
        + f" | {np.mean(list(value.values())):.2f} |"
    )
    return "\n".join(lines)


def write_csv(results: list[CellResult], path: Path) -> None:
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["agents", "obstacles", "episodes", "agent_score", "target_score"])
        for r in results:
            writer.writerow(
                [r.agents, r.obstacles, r.episodes, f"{r.agent_score:.4f}", f"{r.target_score:.4f}"]
            )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="udan-eval", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--policy", choices=sorted(POLICIES), required=True, help="reference policy to evaluate"
    )
    parser.add_argument("--env", default="arena/find_water", help="arena task to evaluate on")
    parser.add_argument("--agents", default="1-5", help="agent counts, e.g. 1-5 (columns)")
    parser.add_argument("--obstacles", default="0-9", help="obstacle counts, e.g. 0-9 (rows)")
    parser.add_argument("--episodes", type=int, default=100, help="episodes per cell")
    parser.add_argument("--seed", type=int, default=0, help="seed of the layouts and the policy")
    parser.add_argument("--csv", type=Path, help="also write the cells to this CSV file")
    args = parser.parse_args(argv)
    try:
        if args.episodes < 1:
            raise EnvConfigError(f"--episodes must be >= 1, got {args.episodes}")
        if not args.env.startswith("arena/"):
            raise EnvConfigError(f"reference policies exist for arena tasks only, not {args.env!r}")
        agents = parse_range(args.agents, "--agents")
        obstacles = parse_range(args.obstacles, "--obstacles")
        if args.csv is not None and not args.csv.parent.is_dir():
            raise EnvConfigError(f"--csv: folder {args.csv.parent} does not exist")
        started = time.perf_counter()
        results = evaluate(
            args.env,
            POLICIES[args.policy](seed=args.seed),
            agents,
            obstacles,
            args.episodes,
            args.seed,
        )
    except EnvConfigError as err:
        print(f"udan-eval: error: {err}", file=sys.stderr)
        return 2
    title = (
        f"{args.env}, policy {args.policy}: average agent score "
        f"({args.episodes} episodes per cell, seed {args.seed})"
    )
    print(format_table(results, "agent_score", title))
    if args.env == "arena/surround":
        print()
        print(
            format_table(results, "target_score", f"{args.env}, policy {args.policy}: target score")
        )
    print(f"\n{len(results)} cells in {time.perf_counter() - started:.1f} s")
    if args.csv is not None:
        write_csv(results, args.csv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
