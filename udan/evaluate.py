"""``udan-eval``: paper-style score tables (rows obstacles, columns agents) for policies.

Every cell runs its episodes as one batch with a seed derived from (seed, agents, obstacles),
so two policies evaluated with the same ``--seed`` meet exactly the same layouts. MAgent tasks
have no obstacle rows: one row per number of agents, with its 95 % CI.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from udan.ablations import ABLATIONS, check_ablation
from udan.envs import EnvConfigError, env_names, make_vec
from udan.envs.errors import parse_range
from udan.leaders import check_leaders, format_leaders, leader_table
from udan.paths import FolderError, ensure_folder
from udan.policies import POLICIES, Policy
from udan.probe import check_probe, format_probe, probe
from udan.tags import check_tags, format_tags, tag_values


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
    goal_per_agent: float = 0.0
    """surround only: minus the steps an agent ends next to the target, averaged over agents
    and episodes (the paper's Table V "goal score", its "average loss score of each agent")."""
    line_walk: float = 0.0
    """magent/queue only: the cells an agent still had to walk to the nearest line when the
    episode ended (0 once lined up), averaged over agents and episodes: how near a fleet that
    scores the same −60 came."""
    scores: np.ndarray = field(default_factory=lambda: np.zeros(0), compare=False, repr=False)
    """Each episode's average agent score, in episode order (for paired comparisons)."""


def run_cell(
    env_name: str,
    policy: Policy,
    agents: int,
    obstacles: int,
    episodes: int,
    seed: int,
    options: dict | None = None,
) -> CellResult:
    """Play ``episodes`` episodes with exactly ``agents`` agents and ``obstacles`` obstacles
    (``options``: further task options, those a checkpoint was trained with)."""
    cell_seed = np.random.SeedSequence([seed, agents, obstacles])
    env = make_vec(
        env_name,
        batch=episodes,
        seed=cell_seed,
        agents=(agents, agents),
        obstacles=(obstacles, obstacles),
        **(options or {}),
    )
    env.reset()
    policy.reset(env)
    done = np.zeros(episodes, dtype=bool)
    while not done.all():
        _, _, done = env.step(policy.act(env))
    per_agent = env.episode_return.sum(axis=1) / agents
    goal = env.adjacent_steps.sum(axis=1) / -agents if env_name == "arena/surround" else 0.0
    walk = env.line_walk().sum(axis=1) / agents if env_name == "magent/queue" else 0.0
    return CellResult(
        agents,
        obstacles,
        episodes,
        float(per_agent.mean()),
        float(env.target_score.mean()),
        float(np.mean(goal)),
        float(np.mean(walk)),
        per_agent,
    )


#: Plays ``fn(*args)`` for each args tuple, results in order (:func:`udan.cluster.ray_map`).
CellRunner = Callable[[Callable, list[tuple]], list]


def evaluate(
    env_name: str,
    policy: Policy,
    agents: tuple[int, int],
    obstacles: tuple[int, int],
    episodes: int,
    seed: int,
    options: dict | None = None,
    runner: CellRunner | None = None,
) -> list[CellResult]:
    """Every cell of the agents x obstacles grid, played here one after the other, or by
    ``runner`` (Ray workers) for a checkpoint's policy: each cell depends only on its seed, so
    the numbers are the same. Reference policies draw from one generator from cell to cell, so
    they always play here, in order."""
    calls = [
        (env_name, policy, n, m, episodes, seed, options)
        for m in range(obstacles[0], obstacles[1] + 1)
        for n in range(agents[0], agents[1] + 1)
    ]
    if runner is None or not isinstance(policy, CheckpointPolicy):
        return [run_cell(*call) for call in calls]
    return runner(run_cell, calls)


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


def format_agents_table(results: list[CellResult], title: str) -> str:
    """Markdown table for tasks without obstacle rows: one row per agent count, the average
    agent score with the 95 % CI of its mean over episodes."""
    lines = [f"**{title}**", "", "| agents | score [95 % CI] | episodes |", "|---|---|---|"]
    for n in sorted({r.agents for r in results}):
        scores = pooled_scores(results, n)
        mean, half = mean_ci(scores)
        lines.append(f"| {n} | {mean:.2f} [{mean - half:.2f}, {mean + half:.2f}] | {scores.size} |")
    return "\n".join(lines)


def format_walk_table(results: list[CellResult], title: str) -> str:
    """Markdown table for queue: per agent count, the cells an agent still had to walk to the
    nearest line at the episode's end."""
    lines = [f"**{title}** (cells per agent at the episode's end; 0: lined up)", ""]
    lines += ["| agents | walk |", "|---|---|"]
    for n in sorted({r.agents for r in results}):
        walk = np.mean([r.line_walk for r in results if r.agents == n])
        lines.append(f"| {n} | {walk:.2f} |")
    return "\n".join(lines)


def write_csv(results: list[CellResult], path: Path) -> None:
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            [
                "agents",
                "obstacles",
                "episodes",
                "agent_score",
                "target_score",
                "goal_per_agent",
                "line_walk",
            ]
        )
        for r in results:
            writer.writerow(
                [
                    r.agents,
                    r.obstacles,
                    r.episodes,
                    f"{r.agent_score:.4f}",
                    f"{r.target_score:.4f}",
                    f"{r.goal_per_agent:.4f}",
                    f"{r.line_walk:.4f}",
                ]
            )


class CheckpointPolicy:
    """A trained checkpoint acting greedily, with per-slot memory (fresh for new agents).

    ``ablate`` names one of :data:`udan.ablations.ABLATIONS`; its random draws come from ``seed``.
    """

    def __init__(self, model, ablate: str | None = None, seed: int = 0) -> None:
        self.model, self.ablate, self.seed = model, ablate, seed
        self.actor = None

    def reset(self, env) -> None:
        from udan.learner import Actor

        rng = np.random.default_rng(self.seed)
        self.actor = Actor(self.model, env.batch, env.slots, self.ablate, rng)

    def act(self, env) -> np.ndarray:
        return self.actor.act(env.observe(), env.present, env.pos, env.joined)


#: Two-sided 95 % quantile of the normal distribution: cells have >= 30 paired episodes, where
#: the t quantile is within 2 % of it (100 episodes: 0.4 %).
Z95 = 1.959964


#: The two ablations that set the learned leader ranking against random leaders at one share
#: (half the agents), where the threshold lets (nearly) everyone lead: given both, ``--ablate``
#: also pairs them with each other.
SAME_SHARE = ("leaders=random-half", "leaders=top-half")


def mean_ci(values: np.ndarray) -> tuple[float, float]:
    """Mean of ``values`` and the half-width of its 95 % CI (NaN from one value: no spread to
    measure, and no numpy warning on the terminal)."""
    if values.size < 2:
        return float(values.mean()), float("nan")
    return float(values.mean()), float(Z95 * values.std(ddof=1) / np.sqrt(values.size))


def seeds_ci(values: list[float]) -> tuple[float, float]:
    """Mean of one score per training seed and the half-width of its 95 % CI: Student's t with
    n - 1 degrees of freedom, as a handful of training runs is far too few for the normal one."""
    from scipy import stats

    array = np.asarray(values, dtype=float)
    half = stats.t.ppf(0.975, array.size - 1) * array.std(ddof=1) / np.sqrt(array.size)
    return float(array.mean()), float(half)


def welch_ci(a: list[float], b: list[float]) -> tuple[float, float]:
    """Difference of two learners' means over their training seeds (a − b) and the half-width
    of its 95 % CI: Welch's t, with the Welch-Satterthwaite degrees of freedom, since two
    learners' seeds are independent runs, neither paired nor of equal spread."""
    from scipy import stats

    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    vx, vy = x.var(ddof=1) / x.size, y.var(ddof=1) / y.size
    difference = float(x.mean() - y.mean())
    if vx + vy == 0:  # every seed of both scored the same (queue's never-lined-up -60.00)
        return difference, 0.0
    dof = (vx + vy) ** 2 / (vx**2 / (x.size - 1) + vy**2 / (y.size - 1))
    return difference, float(stats.t.ppf(0.975, dof) * np.sqrt(vx + vy))


def pooled_scores(results: list[CellResult], agents: int) -> np.ndarray:
    """Per-episode scores of every cell with ``agents`` agents, in cell then episode order."""
    return np.concatenate([r.scores for r in results if r.agents == agents])


def format_paired(
    full: list[CellResult], ablated: dict[str, list[CellResult]], title: str, base: str = "full"
) -> str:
    """Markdown table per agent count (cells of every obstacle count pooled by episode): the
    ``base`` (the full model's) score, each ablation's (or other policy's), and the paired
    difference with its 95 % CI and as a share of the base score. With more than one agent count,
    a last row pools every episode: the communication criterion (a loss of >= 10 %, its CI
    excluding 0) is read there."""
    head = (
        f"| agents | {base} | " + " | ".join(f"{m} | Δ {m} [95 % CI] | Δ %" for m in ablated) + " |"
    )
    lines = [f"**{title}**", "", head, "|---" * (2 + 3 * len(ablated)) + "|"]
    counts = sorted({r.agents for r in full})
    rows = [(str(n), (n,)) for n in counts]
    if len(counts) > 1:
        rows.append((f"{counts[0]}-{counts[-1]} pooled", tuple(counts)))
    for label, ns in rows:
        base = np.concatenate([pooled_scores(full, n) for n in ns])
        cells = [f"{base.mean():.2f}"]
        for results in ablated.values():
            scores = np.concatenate([pooled_scores(results, n) for n in ns])
            mean, half = mean_ci(scores - base)  # paired: the same episodes in the same order
            share = f"{100 * mean / abs(base.mean()):+.0f} %" if base.mean() else "—"
            cells += [
                f"{scores.mean():.2f}",
                f"{mean:+.2f} [{mean - half:+.2f}, {mean + half:+.2f}]",
                share,
            ]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def format_bounds(results: list[CellResult], config, title: str) -> str:
    """hidden_goal: each agent count's score beside the no-message bound and the oracle's."""
    from udan.envs.hidden_goal import no_message_bound, oracle_score

    size = (config.height, config.width, config.max_steps)

    lines = [
        f"**{title}**",
        "",
        "| agents | score | no-message bound | oracle | above the bound |",
        "|---|---|---|---|---|",
    ]
    for n in sorted({r.agents for r in results}):
        mean, half = mean_ci(pooled_scores(results, n))
        bound, best = no_message_bound(*size, n), oracle_score(*size, n)
        lines.append(
            f"| {n} | {mean:.2f} ± {half:.2f} | {bound:.2f} | {best:.2f} | {mean - bound:+.2f} |"
        )
    return "\n".join(lines)


def load_sources(
    args: argparse.Namespace,
) -> tuple[list[tuple[str, str, Policy]], dict, str | None]:
    """(label, env name, policy) for every checkpoint given and the ``--policy`` if any; the
    task options (episode length, map size) and the agent range the checkpoints were trained
    with (the first one's; None without a checkpoint)."""
    from udan.train import env_options

    sources, options, trained = [], [], []
    for path in args.checkpoints:
        import torch

        from udan.checkpoint import load_model

        torch.set_num_threads(1)  # small networks: on a busy 2-core machine more threads are slower
        model, ckpt = load_model(path)
        env_name = args.env or ckpt["env"]
        if env_name != ckpt["env"]:
            raise EnvConfigError(f"{path} was trained on {ckpt['env']}, not {env_name}")
        sources.append(
            (f"{ckpt['algo']} ({Path(path).parent.name})", env_name, CheckpointPolicy(model))
        )
        options.append(env_options(ckpt["config"]))
        trained.append(str(ckpt["config"]["agents"]))
    if args.policy:
        env_name = args.env or (sources[0][1] if sources else "arena/find_water")
        plays = {  # policy -> (task name prefixes it plays, how to say them)
            "oracle": (("arena/",), "arena tasks"),
            "chaser": (("magent/pursuit", "magent/tiger"), "magent/pursuit and magent/tiger"),
            "liner": (("magent/queue",), "magent/queue"),
        }
        prefixes, said = plays.get(args.policy, (("arena/", "magent/"), "every task"))
        if not env_name.startswith(prefixes):
            raise EnvConfigError(f"--policy {args.policy} plays {said}, not {env_name}")
        sources.append((args.policy, env_name, POLICIES[args.policy](seed=args.seed)))
    if not sources:
        raise EnvConfigError("nothing to evaluate: give checkpoints and/or --policy")
    if len({env for _, env, _ in sources}) > 1:
        raise EnvConfigError("all checkpoints must come from one env to share a table")
    if any(o != options[0] for o in options):
        raise EnvConfigError("all checkpoints must share episode length and map size")
    return sources, options[0] if options else {}, trained[0] if trained else None


def plot_heatmap(results: list[CellResult], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    agents = sorted({r.agents for r in results})
    obstacles = sorted({r.obstacles for r in results})
    grid = np.array(
        [
            [
                next(r.agent_score for r in results if r.agents == n and r.obstacles == m)
                for n in agents
            ]
            for m in obstacles
        ]
    )
    fig, ax = plt.subplots(figsize=(1.2 * len(agents) + 2, 0.45 * len(obstacles) + 1.5))
    im = ax.imshow(grid, cmap="viridis", aspect="auto")
    ax.set_xticks(range(len(agents)), agents)
    ax.set_yticks(range(len(obstacles)), obstacles)
    ax.set_xlabel("agents")
    ax.set_ylabel("obstacles")
    for (i, j), v in np.ndenumerate(grid):
        ax.text(j, i, f"{v:.1f}", ha="center", va="center", color="w", fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.colorbar(im, ax=ax, label="average agent score")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_comparison(tables: dict[str, list[CellResult]], env_name: str, path: Path) -> None:
    """The paper's Figs. 7-8: score by number of agents, one line per policy."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for label, results in tables.items():
        agents = sorted({r.agents for r in results})
        ax.plot(
            agents,
            [np.mean([r.agent_score for r in results if r.agents == n]) for n in agents],
            marker="o",
            label=label,
        )
    ax.set_xticks(sorted({r.agents for results in tables.values() for r in results}))
    ax.set_xlabel("agents")
    ax.set_ylabel("average agent score (mean over obstacles)")
    ax.set_title(env_name)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _probed_model(args: argparse.Namespace, sources: list):
    """The one checkpoint's model that ``--ablate`` / ``--probe`` / ``--leaders`` / ``--tags``
    act on (None without them); refuses what cannot be ablated, probed or inspected."""
    if not args.ablate and not args.probe and not args.leaders and not args.tags:
        return None
    policies = [policy for _, _, policy in sources if isinstance(policy, CheckpointPolicy)]
    if len(sources) != 1 or len(policies) != 1:
        raise EnvConfigError(
            "--ablate/--probe/--leaders/--tags take exactly one checkpoint and no --policy"
        )
    spec = policies[0].model.spec
    try:
        for mode in args.ablate:
            check_ablation(mode, spec.algo, spec.communicates, args.episodes)
    except ValueError as err:
        raise EnvConfigError(str(err)) from None
    if args.probe:
        check_probe(spec, sources[0][1], args.episodes)
    if args.leaders:
        check_leaders(spec)
    if args.tags:
        check_tags(spec, sources[0][1])
    return policies[0].model


def learning_curves(
    runs: list[Path],
    path: Path | None,
    panel: Callable[[Path], str] = lambda run: "",
    name: Callable[[Path], str] = lambda run: run.name,
) -> str:
    """Each run's training return against environment steps (its ``progress.csv``), plotted to
    ``path``, one panel per distinct ``panel(run)`` (the paper's Fig. 5 has one per scenario, as
    their returns differ by orders of magnitude) and labelled ``name(run)``; returns a markdown
    table of the last two tenths of each run, to tell whether the curve has levelled off."""
    curves = {}
    for run in runs:
        file = run / "progress.csv"
        if not file.is_file():
            raise EnvConfigError(f"--curves: {run} has no progress.csv (not a run folder)")
        with file.open() as f:
            rows = [(int(r["steps"]), float(r["return"])) for r in csv.DictReader(f)]
        if len(rows) < 2:
            raise EnvConfigError(f"--curves: {run} has only {len(rows)} row(s) of progress")
        curves[run] = np.array(rows)
    lines = [
        "| run | steps | return, 8th-9th tenth | return, last tenth | change |",
        "|---|---|---|---|---|",
    ]
    for run, rows in curves.items():
        tenth = max(len(rows) // 10, 1)
        before, last = rows[-2 * tenth : -tenth, 1].mean(), rows[-tenth:, 1].mean()
        lines.append(
            f"| {name(run)} | {int(rows[-1, 0]):,} | {before:.2f} | {last:.2f} | "
            f"{last - before:+.2f} |"
        )
    if path is not None:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        titles = list(dict.fromkeys(panel(run) for run in curves))
        fig, axes = plt.subplots(1, len(titles), figsize=(6 * len(titles), 4), squeeze=False)
        for ax, title in zip(axes[0], titles, strict=True):
            for run, rows in curves.items():
                if panel(run) == title:
                    ax.plot(rows[:, 0], rows[:, 1], label=name(run), lw=1)
            ax.set_title(title)
            ax.set_xlabel("environment steps")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=8)
        axes[0, 0].set_ylabel("training return\n(mean of the last 200 episodes, with exploration)")
        fig.tight_layout()
        fig.savefig(path, dpi=100)
        plt.close(fig)
    return "\n".join(lines)


@contextmanager
def _cell_runner(args: argparse.Namespace) -> Iterator[CellRunner | None]:
    """The cells' runner: Ray workers with ``--workers``/``--address`` (Ray started or joined
    for the evaluation, and shut down after it), else None (the cells play here)."""
    if not args.workers and not args.address:
        yield None
        return
    from udan.cluster import ray_map, ray_session

    with ray_session(args.workers, args.address):
        yield ray_map


def _slug(label: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in label).strip("_")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="udan-eval", description=__doc__.splitlines()[0])
    parser.add_argument("checkpoints", nargs="*", help="checkpoint.pt files to evaluate")
    parser.add_argument(
        "--policy", choices=sorted(POLICIES), help="also evaluate a reference policy"
    )
    parser.add_argument("--env", help="task (default: the checkpoints' env, or find_water)")
    parser.add_argument(
        "--agents",
        help="agent counts, e.g. 1-5 (columns; default: arena 1-5, else the checkpoint's range, "
        "or the scenario's)",
    )
    parser.add_argument(
        "--obstacles", help="obstacle counts, e.g. 0-9 (rows; default: arena 0-9, MAgent 0)"
    )
    parser.add_argument(
        "--prey-alertness",
        type=float,
        help="magent/pursuit: the chance a sheep that sees a wolf flees rather than wanders "
        "(default 1, the task; lower, the sheep of a --prey-curriculum training)",
    )
    parser.add_argument(
        "--map-size",
        type=int,
        help="MAgent tasks: play on a map of this side (default: the checkpoints'; 0: the "
        "scenario's own, the paper's), e.g. a model trained on a smaller map on the paper's",
    )
    parser.add_argument("--episodes", type=int, default=100, help="episodes per cell")
    parser.add_argument("--seed", type=int, default=0, help="seed of the layouts and the policy")
    parser.add_argument("--csv", type=Path, help="write the cells to this CSV (one source only)")
    parser.add_argument(
        "--out", type=Path, help="folder for CSVs, heatmap PNGs and the comparison plot"
    )
    parser.add_argument(
        "--ablate",
        type=lambda text: [m.strip() for m in text.split(",") if m.strip()],
        default=[],
        metavar="MODE[,MODE...]",
        help="also play the checkpoint with each ablation, paired on the same episodes: "
        + "; ".join(f"{name}: {what}" for name, what in ABLATIONS.items()),
    )
    parser.add_argument(
        "--curves",
        nargs="+",
        type=Path,
        default=[],
        metavar="RUN",
        help="plot these run folders' learning curves (to --out/curves.png) and tabulate their end",
    )
    parser.add_argument(
        "--probe",
        action="store_true",
        help="arena/hidden_goal: a linear probe of the goal in the messages (udan.probe)",
    )
    parser.add_argument(
        "--leaders",
        action="store_true",
        help="UDAN: who leads against what the messages would change, and the groups each agent "
        "is in and how far its message reaches (udan.leaders)",
    )
    parser.add_argument(
        "--tags",
        action="store_true",
        help="MAgent pursuit and tiger: random wolves' attacks that paid against those that did "
        "not, as the checkpoint values them, and what its mixer passes back to each agent's Q "
        "(udan.tags)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        help="play the cells of checkpoints on this many Ray workers, a local Ray (0: here, one "
        "after the other); the numbers are the same (pip install 'udan-edge[scale]')",
    )
    parser.add_argument(
        "--address",
        default="",
        help="play the cells on this Ray cluster instead: ray://HOST:PORT, HOST:PORT or auto",
    )
    args = parser.parse_args(argv)
    from udan.checkpoint import CheckpointError
    from udan.cluster import ScaleError

    try:
        if args.episodes < 1:
            raise EnvConfigError(f"--episodes must be >= 1, got {args.episodes}")
        if args.workers < 0:
            raise EnvConfigError(f"--workers must be >= 0, got {args.workers}")
        if args.env is not None and args.env not in env_names():
            raise EnvConfigError(f"unknown env {args.env!r}; known: {', '.join(env_names())}")
        for folder, what in ((args.csv and args.csv.parent, "--csv"), (args.out, "--out")):
            if folder is not None:
                ensure_folder(folder, what)
        curves = ""
        if args.curves:
            curves = learning_curves(args.curves, args.out and args.out / "curves.png")
            if not args.checkpoints and not args.policy:
                print(curves)
                return 0
        sources, options, trained = load_sources(args)
        env_name = sources[0][1]
        arena = env_name.startswith("arena/")
        if args.prey_alertness is not None:
            if env_name != "magent/pursuit":
                raise EnvConfigError(f"--prey-alertness is for magent/pursuit, not {env_name}")
            options = {**options, "prey_alertness": args.prey_alertness}
        if args.map_size is not None:
            if arena:
                raise EnvConfigError(f"--map-size is for MAgent tasks, not {env_name}")
            options = {key: v for key, v in options.items() if key != "map_size"}
            options |= {"map_size": args.map_size} if args.map_size else {}
        if not arena and trained is None and not args.agents:  # a reference policy alone
            trained = make_vec(env_name, batch=1, **options).config.agents  # the scenario's
        agents = parse_range(args.agents or ("1-5" if arena else trained), "--agents")
        obstacles = parse_range(args.obstacles or ("0-9" if arena else "0"), "--obstacles")
        fits = make_vec(env_name, batch=1, agents=agents, obstacles=obstacles, **options).config
        if args.policy == "liner" and obstacles != (0, 0):
            raise EnvConfigError("--policy liner lines up along a wall: it needs --obstacles 0")
        if args.csv is not None and len(sources) > 1:
            raise EnvConfigError("--csv takes one source; use --out for several")
        probed = _probed_model(args, sources)
        started = time.perf_counter()
        with _cell_runner(args) as runner:
            cells = (agents, obstacles, args.episodes, args.seed, options, runner)
            tables = {label: evaluate(env, policy, *cells) for label, env, policy in sources}
            ablated = {
                mode: evaluate(env_name, CheckpointPolicy(probed, mode, args.seed), *cells)
                for mode in args.ablate
            }
        probes = probe(probed, agents, args.episodes, args.seed) if args.probe else []
        leaders = (
            leader_table(probed, env_name, agents, obstacles, args.episodes, args.seed, **options)
            if args.leaders
            else []
        )
        tags = (
            tag_values(probed, env_name, agents, args.episodes, args.seed, **options)
            if args.tags
            else []
        )
    except (EnvConfigError, CheckpointError, FolderError, ScaleError) as err:
        print(f"udan-eval: error: {err}", file=sys.stderr)
        return 2
    reports = [curves] if curves else []  # markdown tables written to --out/report.md
    task = "" if args.prey_alertness is None else f", sheep alertness {args.prey_alertness:g}"
    task += "" if args.map_size is None else f", {fits.map_size}×{fits.map_size} map"
    for label, results in tables.items():
        title = (
            f"{env_name}, {label}: average agent score "
            f"({args.episodes} episodes per cell, seed {args.seed}{task})"
        )
        print(
            format_table(results, "agent_score", title)
            if arena
            else format_agents_table(results, title)
        )
        if env_name == "arena/surround":
            print()
            print(format_table(results, "target_score", f"{env_name}, {label}: target score"))
            print()
            title = f"{env_name}, {label}: goal score per agent (the paper's Table V, lower half)"
            print(format_table(results, "goal_per_agent", title))
        if env_name == "magent/queue":
            print()
            print(format_walk_table(results, f"{env_name}, {label}: walk to the nearest line"))
        print()
        if env_name == "arena/hidden_goal":
            config = make_vec(env_name, batch=1, agents=agents[1], obstacles=0).config
            reports.append(format_bounds(results, config, f"{env_name}, {label}: bounds"))
        if args.out is not None:
            write_csv(results, args.out / f"{_slug(label)}.csv")
            if arena:
                plot_heatmap(results, title, args.out / f"{_slug(label)}.png")
    if len(tables) > 1:
        first, *others = tables
        title = (
            f"{env_name}: each policy against {first}, paired on the same {args.episodes} "
            "episodes per cell"
        )
        reports.append(
            format_paired(tables[first], {o: tables[o] for o in others}, title, base=first)
        )
    if ablated:
        label = sources[0][0]
        title = (
            f"{env_name}, {label}: ablations, paired on the same {args.episodes} episodes per cell"
        )
        reports.append(format_paired(tables[label], ablated, title))
    if all(mode in ablated for mode in SAME_SHARE):
        base, other = SAME_SHARE
        title = (
            f"{env_name}, {sources[0][0]}: the scorer's top half against random leaders at the "
            f"same share, paired on the same {args.episodes} episodes per cell"
        )
        reports.append(format_paired(ablated[base], {other: ablated[other]}, title, base=base))
    if probes:
        reports.append(
            format_probe(probes, f"{env_name}, {sources[0][0]}: linear probe of the goal's cell")
        )
    if leaders:
        title = f"{env_name}, {sources[0][0]}: leaders against ΔQ (eq. 4) at group formations"
        reports.append(format_leaders(leaders, title))
    if tags:
        title = (
            f"{env_name}, {sources[0][0]}: what it makes of random attacks "
            f"({args.episodes} episodes per N{task})"
        )
        reports.append(format_tags(tags, title))
    for report in reports:
        print(report, end="\n\n")
    if reports and args.out is not None:
        (args.out / "report.md").write_text("\n\n".join(reports) + "\n")
    if args.csv is not None:
        write_csv(next(iter(tables.values())), args.csv)
    if args.out is not None and len(tables) > 1:
        plot_comparison(tables, env_name, args.out / "comparison.png")
    print(f"{sum(map(len, tables.values()))} cells in {time.perf_counter() - started:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
