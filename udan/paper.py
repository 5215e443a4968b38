"""``udan-paper``: the paper's §V tables and figures regenerated from the committed models into one
markdown file (``make paper`` writes ``docs/results.md``), each beside the paper's own numbers.

- Table V and Fig. 7 (``arena/surround``): UDAN per obstacles x agents, the agent score and the
  goal score per agent, beside Table V; every policy's score by N (UDAN trained on 1-5 agents,
  the baselines at N = 3, as in the paper).
- Table VI and Fig. 8 (``arena/find_water``): the same, beside Table VI.
- The positive control (``arena/hidden_goal``, not in the paper): UDAN against the proven
  no-message bound, its no-message twin and IQL, and what shuffled messages cost.
- Table II and Fig. 5 (MAgent pursuit, tiger, queue): a model's row where one is committed, and
  "not trained yet" where none is: a number that was not measured is never written. A learner
  trained with more seeds keeps each further seed in a ``seed<k>/`` folder inside its own; the
  scenario then gets a table across seeds (each seed's score, a CI over seeds, each UDAN against
  each baseline played on the same task, what shuffled messages cost each UDAN seed); a try
  trained on a map of its own has its seeds played on its map and on the paper's.

Models are found by folder under ``--models`` (:data:`FIG7`, :data:`FIG8`, :data:`CONTROL`,
:data:`MAGENT`); each evaluation is seeded as ``udan-eval`` seeds it (the same layouts for every
policy), so the same models give the same file, byte for byte.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from udan.envs import EnvConfigError, make_vec
from udan.envs.errors import parse_range
from udan.evaluate import (
    CellResult,
    CheckpointPolicy,
    evaluate,
    format_paired,
    learning_curves,
    mean_ci,
    pooled_scores,
    seeds_ci,
    welch_ci,
)
from udan.paths import FolderError, ensure_folder
from udan.policies import POLICIES

# ------------------------------------------------------------------ the paper's numbers
#: Table V, upper half: average agent score, rows obstacles ("Wall nums") 0-9, columns N = 1-4.
#: The extracted table has a constant 0 column after the wall count (carried no number) and
#: four score columns; they are N = 1-4 because the text's remarks hold only so: "the score when
#: the number of agents is four is higher than when the number is three" at few obstacles
#: (28.677 > 26.937) and lower at seven or eight (25.147 < 26.798).
TABLE_V_AGENT: dict[int, tuple[float, ...]] = {
    0: (29.329, 28.277, 26.937, 28.677),
    1: (30.077, 29.502, 27.844, 29.727),
    2: (30.279, 29.620, 28.025, 28.959),
    3: (30.101, 29.434, 27.841, 28.182),
    4: (29.634, 29.128, 27.756, 26.640),
    5: (29.305, 29.004, 27.288, 26.164),
    6: (29.095, 28.069, 27.207, 25.370),
    7: (28.585, 27.770, 26.798, 25.147),
    8: (27.691, 27.377, 26.565, 24.527),
    9: (28.194, 27.530, 26.238, 25.080),
}
#: Table V, lower half: "goal score", "the average loss score of each agent".
TABLE_V_GOAL: dict[int, tuple[float, ...]] = {
    0: (-36.838, -35.369, -34.354, -34.289),
    1: (-36.873, -36.045, -34.806, -34.907),
    2: (-38.788, -37.626, -35.659, -36.771),
    3: (-37.999, -37.547, -36.698, -36.281),
    4: (-38.390, -37.578, -35.942, -34.514),
    5: (-37.238, -36.996, -35.842, -33.820),
    6: (-37.364, -36.697, -34.796, -32.854),
    7: (-36.974, -35.799, -34.545, -32.430),
    8: (-35.447, -35.290, -34.319, -32.231),
    9: (-37.737, -35.367, -34.150, -32.514),
}
#: Table VI: average agent score on find-water, rows obstacles 0-14, columns N = 1-5.
TABLE_VI: dict[int, tuple[float, ...]] = {
    0: (42.0, 41.5, 41.954, 42.220, 41.749),
    1: (42.0, 41.413, 41.850, 41.990, 41.548),
    2: (41.904, 41.404, 41.760, 41.828, 41.569),
    3: (41.922, 41.47, 41.532, 41.539, 41.532),
    4: (41.647, 41.25, 41.365, 41.45, 41.132),
    5: (41.68, 41.30, 41.085, 41.137, 40.710),
    6: (41.137, 40.962, 40.872, 40.466, 40.426),
    7: (41.68, 38.627, 40.908, 40.43, 39.875),
    8: (40.865, 39.71, 40.071, 39.03, 39.708),
    9: (40.0, 40.127, 38.960, 39.038, 38.364),
    10: (40.490, 39.343, 39.933, 36.53, 38.145),
    11: (37.865, 38.0, 35.648, 36.615, 37.180),
    12: (38.491, 37.27, 35.660, 35.135, 36.345),
    13: (37.314, 35.598, 37.679, 34.647, 35.944),
    14: (32.588, 32.63, 32.549, 30.656, 32.992),
}
#: Table II (cooperative pursuit): average reward per agent, tested at N drawn in 8-20; the key
#: is the number of agents the algorithm was trained with.
TABLE_II: dict[str, dict[str, float]] = {
    "udan": {"8-20": 71.0},
    "iql": {"10": 8.5, "15": 7.91, "20": 6.26},
    "coma": {"10": -0.71, "15": -0.68, "20": -0.73},
    "vdn": {"10": 7.5, "15": 14.32, "20": 3.03},
    "qmix": {"10": 43.98, "15": 46.18, "20": 34.35},
}

# ------------------------------------------------------------------ which model is where
#: (label, folder under --models) of the policies of Fig. 7: UDAN on 1-5 agents, baselines at 3.
FIG7 = (
    ("UDAN", "surround"),
    ("QMIX", "baselines/surround_qmix"),
    ("VDN", "baselines/surround_vdn"),
    ("IQL (the paper's DQN)", "baselines/surround_iql"),
    ("COMA", "baselines/surround_coma"),
)
#: The same for Fig. 8 (find-water).
FIG8 = (
    ("UDAN", "find_water"),
    ("UDAN, the paper's min-max leader target", "find_water/minmax"),
    ("QMIX", "baselines/find_water_qmix"),
    ("VDN", "baselines/find_water_vdn"),
    ("IQL (the paper's DQN)", "baselines/find_water_iql"),
    ("COMA", "baselines/find_water_coma"),
)
#: The positive control and its two controls.
CONTROL = (
    ("UDAN", "hidden_goal"),
    ("UDAN, the paper's min-max leader target", "hidden_goal/minmax"),
    ("UDAN, no messages", "hidden_goal/no_messages"),
    ("IQL", "hidden_goal/iql"),
)
#: Tries beside a MAgent scenario's models, each a deviation its card documents: (label,
#: folder, the paper's algorithm key in TABLE_II). One trained on another map is played on its
#: own and on the paper's.
MAGENT_TRIES = {
    "pursuit": (
        ("UDAN, 30×30 map, slow ε, sheep curriculum (a deviation)", "magent_pursuit/map30", "udan"),
        (
            "UDAN, the same, its mixer started as a sum (a deviation)",
            "magent_pursuit/map30_sum",
            "udan",
        ),
        (
            "UDAN, the same, its mixer started as a sum, trained at N = 15 (a deviation)",
            "magent_pursuit/map30_sum15",
            "udan",
        ),
        (
            "QMIX, 30×30 map, slow ε, sheep curriculum (a deviation)",
            "baselines/magent_pursuit_qmix/map30",
            "qmix",
        ),
        (
            "VDN, 30×30 map, slow ε, sheep curriculum (a deviation)",
            "baselines/magent_pursuit_vdn/map30",
            "vdn",
        ),
        (
            "IQL, 30×30 map, slow ε, sheep curriculum (a deviation)",
            "baselines/magent_pursuit_iql/map30",
            "iql",
        ),
        *(
            (
                f"IQL, the same, trained at N = {n} (a deviation)",
                f"baselines/magent_pursuit_iql/map30_n{n}",
                "iql",
            )
            for n in (10, 20)
        ),
    ),
    "queue": (
        ("UDAN, small fleets in training (a deviation)", "magent_queue/agents2_20", "udan"),
        *(
            (f"{label}, {shaping} (a deviation)", f"{folder}/{subfolder}", algo)
            for subfolder, shaping in (
                ("shaped", "shaped toward the nearest line"),
                ("shaped_2m", "the same, the full 2·10⁶ steps"),
            )
            for label, folder, algo in (
                ("UDAN", "magent_queue", "udan"),
                ("QMIX", "baselines/magent_queue_qmix", "qmix"),
                ("VDN", "baselines/magent_queue_vdn", "vdn"),
            )
        ),
    ),
}
#: MAgent scenario -> (label, folder, the paper's algorithm key in TABLE_II) of its models.
MAGENT = {
    scenario: tuple(
        (label, folder.format(scenario), algo)
        for label, folder, algo in (
            ("UDAN", "magent_{}", "udan"),
            ("QMIX", "baselines/magent_{}_qmix", "qmix"),
            ("VDN", "baselines/magent_{}_vdn", "vdn"),
            ("IQL (the paper's DQN)", "baselines/magent_{}_iql", "iql"),
            ("COMA", "baselines/magent_{}_coma", "coma"),
        )
    )
    + MAGENT_TRIES.get(scenario, ())
    for scenario in ("pursuit", "tiger", "queue")
}
#: Each scenario's scripted reference row beside its UDAN (``udan-eval --policy NAME``): policy
#: and label.
SCRIPTED = {
    "pursuit": ("chaser", "scripted chaser (no learning, no messages)"),
    "tiger": ("chaser", "scripted chaser (no learning, no messages)"),
    "queue": ("liner", "scripted liner (no learning, no messages)"),
}
#: Every folder udan-paper reads a model from.
FOLDERS = tuple(
    entry[1] for entries in (FIG7, FIG8, CONTROL, *MAGENT.values()) for entry in entries
)
NOT_TRAINED = "not trained yet"


@dataclass
class Loaded:
    """A committed model, loaded: its network, checkpoint and where it came from."""

    label: str
    folder: str
    model: object
    checkpoint: dict
    sha256: str

    @property
    def trained_agents(self) -> str:
        return str(self.checkpoint["config"]["agents"])

    def options(self) -> dict:
        """The task options it was trained with (episode length, map size)."""
        from udan.train import env_options

        return env_options(self.checkpoint["config"])


def load_models(models: Path, entries) -> dict[str, Loaded | None]:
    """label -> the loaded model of each (label, folder, ...) entry, None where the folder holds
    no checkpoint."""
    from udan.checkpoint import load_model

    loaded: dict[str, Loaded | None] = {}
    for label, folder, *_ in entries:
        path = models / folder / "checkpoint.pt"
        if not path.is_file():
            loaded[label] = None
            continue
        model, ckpt = load_model(path)
        sha = hashlib.sha256(path.read_bytes()).hexdigest()
        loaded[label] = Loaded(label, folder, model, ckpt, sha)
    return loaded


# ------------------------------------------------------------------ tables
def _by_agents(results: list[CellResult], field: str = "agent_score") -> dict[int, float]:
    """Mean over obstacle rows of ``field``, per number of agents."""
    agents = sorted({r.agents for r in results})
    return {
        n: float(np.mean([getattr(r, field) for r in results if r.agents == n])) for n in agents
    }


def _paper_by_agents(table: dict[int, tuple[float, ...]], obstacles: range) -> dict[int, float]:
    """The paper's per-N means over the same obstacle rows as ours."""
    rows = [table[m] for m in obstacles if m in table]
    return {n + 1: float(np.mean([row[n] for row in rows])) for n in range(len(rows[0]))}


def _fmt(value: float | None, sign: bool = False) -> str:
    if value is None:
        return "—"
    return f"{value:+.2f}" if sign else f"{value:.2f}"


def _paper(value: float | None) -> str:
    """A number of the paper's tables as it prints it."""
    return "—" if value is None else f"{value:g}"


def side_by_side(
    results: list[CellResult], paper: dict[int, tuple[float, ...]], field: str, title: str
) -> str:
    """Rows obstacles, per N our value beside the paper's (— where the paper has none), a mean
    row over the obstacle rows."""
    agents = sorted({r.agents for r in results})
    obstacles = sorted({r.obstacles for r in results})
    ours = {(r.obstacles, r.agents): getattr(r, field) for r in results}

    def theirs(m: int, n: int) -> float | None:
        row = paper.get(m)
        return row[n - 1] if row is not None and n <= len(row) else None

    head = " | ".join(f"N={n} ours | N={n} paper" for n in agents)
    lines = [f"**{title}**", "", f"| obstacles | {head} |", "|---" * (1 + 2 * len(agents)) + "|"]
    for m in obstacles:
        cells = [f"{_fmt(ours[m, n])} | {_paper(theirs(m, n))}" for n in agents]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    means = []
    for n in agents:
        paper_values = [theirs(m, n) for m in obstacles]
        paper_mean = None if None in paper_values else float(np.mean(paper_values))
        means.append(f"**{_fmt(np.mean([ours[m, n] for m in obstacles]))}** | {_fmt(paper_mean)}")
    lines.append("| mean | " + " | ".join(means) + " |")
    return "\n".join(lines)


def verdict_table(results: list[CellResult], paper: dict[int, float], title: str) -> str:
    """Per N: our mean with its 95 % CI over episodes (every obstacle row pooled), the paper's,
    the difference, and whether ours is at or above it (the paper gives no spread to test
    against: "below, within the CI" says only that our interval reaches its number)."""
    lines = [
        f"**{title}**",
        "",
        "| N | ours [95 % CI] | paper | ours − paper | verdict |",
        "|---|---|---|---|---|",
    ]
    for n, ours in _by_agents(results).items():
        mean, half = mean_ci(pooled_scores(results, n))
        theirs = paper.get(n)
        if theirs is None:
            cells = [_fmt(None), _fmt(None), f"the paper has no N = {n} column"]
        else:
            verdict = (
                "at or above"
                if ours >= theirs
                else "below, within the CI"
                if mean + half >= theirs
                else "below"
            )
            cells = [f"{theirs:.2f}", f"{ours - theirs:+.2f}", verdict]
        lines.append(
            f"| {n} | {ours:.2f} [{mean - half:.2f}, {mean + half:.2f}] | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(lines)


def by_agents_table(
    tables: dict[str, list[CellResult] | None],
    trained: dict[str, str],
    agents: range,
    title: str,
    field: str = "agent_score",
) -> str:
    """One row per policy: its mean over obstacle rows at each N (Figs. 7-8 as numbers)."""
    lines = [
        f"**{title}**",
        "",
        "| policy | trained on N | " + " | ".join(f"N={n}" for n in agents) + " | spread |",
        "|---" * (3 + len(agents)) + "|",
    ]
    for label, results in tables.items():
        if results is None:
            lines.append(f"| {label} | — | " + " | ".join([NOT_TRAINED] * len(agents)) + " | — |")
            continue
        values = _by_agents(results, field)
        row = [f"{values[n]:.2f}" for n in agents]
        spread = max(values.values()) - min(values.values())
        lines.append(f"| {label} | {trained[label]} | " + " | ".join(row) + f" | {spread:.2f} |")
    return "\n".join(lines)


# ------------------------------------------------------------------ figures
def plot_by_agents(
    panels: list[tuple[str, dict[str, list[CellResult] | None], str, dict[int, float]]],
    title: str,
    path: Path,
) -> None:
    """One panel per (y label, policy tables, field, the paper's UDAN per N): a line per policy,
    the paper's UDAN dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4), squeeze=False)
    for ax, (ylabel, tables, field, paper) in zip(axes[0], panels, strict=True):
        for label, results in tables.items():
            if results is not None:
                values = _by_agents(results, field)
                ax.plot(list(values), list(values.values()), marker="o", label=label)
        ax.plot(list(paper), list(paper.values()), "k--", marker="x", label="paper, UDAN")
        ax.set_xticks(sorted({r.agents for t in tables.values() if t for r in t} | set(paper)))
        ax.set_xlabel("agents")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)


# ------------------------------------------------------------------ sections
@dataclass
class Settings:
    """What every evaluation of one ``udan-paper`` run shares."""

    models: Path
    """Folder of the committed models (the checkout's ``models/``)."""
    figures: Path
    """Folder the figures are written to."""
    link: str
    """How the markdown file refers to that folder."""
    episodes: int
    """Episodes per (agents, obstacles) cell of the arena tasks."""
    magent_episodes: int
    """Episodes per number of agents on the MAgent scenarios (300 steps of up to 20 agents)."""
    seed: int
    """Seed of layouts and policies (udan-eval's)."""
    played: dict = dataclasses.field(default_factory=dict)
    """Evaluations already run, by model folder and arguments: one is played once per file."""


def _play(
    loaded: Loaded | None,
    env: str,
    agents,
    obstacles,
    settings: Settings,
    ablate=None,
    episodes=0,
    task_of: Loaded | None = None,
) -> list[CellResult] | None:
    """``loaded``'s evaluation as udan-eval seeds it (None without a model), on the task options
    it was trained with or on those of ``task_of``; seeded, so the same arguments give the same
    results and a second call returns the first's."""
    if loaded is None:
        return None
    episodes = episodes or settings.episodes
    options = (task_of or loaded).options()
    key = (loaded.folder, env, tuple(agents), tuple(obstacles), ablate, episodes, str(options))
    if key not in settings.played:
        policy = CheckpointPolicy(loaded.model, ablate, settings.seed)
        settings.played[key] = evaluate(
            env, policy, agents, obstacles, episodes, settings.seed, options
        )
    return settings.played[key]


def _shuffle_table(
    udan: Loaded,
    full: list[CellResult],
    env: str,
    agents,
    obstacles,
    settings: Settings,
    name: str,
    episodes: int = 0,
) -> str:
    """What shuffled messages cost ``udan``, paired on the episodes of its ``full`` results."""
    shuffled = _play(udan, env, agents, obstacles, settings, "messages=shuffle", episodes)
    title = f"{name}: UDAN with shuffled messages, paired on the same episodes"
    return format_paired(full, {"messages=shuffle": shuffled}, title)


def _curves(
    models: Path, entries, png: Path | None, panel: Callable[[Path], str] = lambda run: ""
) -> str | None:
    """The learning-curve table of the entries whose folder keeps its ``progress.csv``; the
    figure has a panel per distinct ``panel(run folder)``."""
    runs = [
        models / folder for _, folder, *_ in entries if (models / folder / "progress.csv").is_file()
    ]
    if not runs:
        return None
    return learning_curves(
        runs, png, panel, lambda run: str(run.relative_to(models)).removeprefix("baselines/")
    )


def arena_section(
    settings: Settings,
    *,
    env: str,
    entries,
    agents: tuple[int, int],
    obstacles: tuple[int, int],
    table: str,
    figure: str,
    paper_agent: dict[int, tuple[float, ...]],
    paper_goal: dict[int, tuple[float, ...]] | None,
    stem: str,
    floor: tuple[int, float] | None = None,
) -> tuple[str, list[Loaded]]:
    """Table V or VI with Fig. 7 or 8: UDAN beside the paper, every policy by N, the shuffled
    messages' cost, the learning curves; ``floor`` (most obstacles, score): the project's target
    for UDAN's mean over every N and the obstacle rows up to that many."""
    loaded = load_models(settings.models, entries)
    tables = {label: _play(m, env, agents, obstacles, settings) for label, m in loaded.items()}
    rows = range(obstacles[0], obstacles[1] + 1)
    columns = range(agents[0], agents[1] + 1)
    paper_means = _paper_by_agents(paper_agent, rows)
    out = [f"## {table} and {figure}: `{env}`", ""]
    udan = tables["UDAN"]
    if udan is None:
        out += [f"UDAN: {NOT_TRAINED} (no `{entries[0][1]}/checkpoint.pt`).", ""]
    else:
        out += [
            side_by_side(udan, paper_agent, "agent_score", f"{table}: average agent score"),
            "",
            verdict_table(
                udan,
                paper_means,
                f"{table}, by N (mean over obstacles {rows.start}-{rows.stop - 1})",
            ),
            "",
        ]
        if floor is not None:
            most, score = floor
            mean = float(np.mean([r.agent_score for r in udan if r.obstacles <= most]))
            met = "met" if mean >= score else "NOT met"
            out += [
                f"UDAN's mean over N = {columns.start}-{columns.stop - 1} and obstacles "
                f"{rows.start}-{most}: **{mean:.2f}** (the project's target ≥ {score:g}: {met}).",
                "",
            ]
        if paper_goal is not None:
            out += [
                side_by_side(udan, paper_goal, "goal_per_agent", f"{table}: goal score per agent"),
                "",
                "The goal score is minus the steps an agent ends next to the target, averaged "
                "over agents (docs/environments.md says why this is the paper's reading).",
                "",
            ]
        if loaded["UDAN"].model.spec.communicates:
            out += [
                _shuffle_table(loaded["UDAN"], udan, env, agents, obstacles, settings, table),
                "",
            ]
    trained = {label: m.trained_agents for label, m in loaded.items() if m is not None}
    out += [
        by_agents_table(tables, trained, columns, f"{figure}: average agent score by N"),
        "",
    ]
    panels = [("average agent score", tables, "agent_score", paper_means)]
    if paper_goal is not None:
        out += [
            by_agents_table(
                tables, trained, columns, f"{figure}: goal score per agent by N", "goal_per_agent"
            ),
            "",
        ]
        panels.append(
            ("goal score per agent", tables, "goal_per_agent", _paper_by_agents(paper_goal, rows))
        )
    png = settings.figures / f"{stem}.png"
    plot_by_agents(
        panels, f"{env}: {figure} (mean over obstacles {rows.start}-{rows.stop - 1})", png
    )
    out += [f"![{figure}]({settings.link}/{png.name})", ""]
    curves = _curves(settings.models, entries, settings.figures / f"{stem}_curves.png")
    if curves:
        out += [
            "Learning curves (training return, the committed runs' `progress.csv`):",
            "",
            curves,
            "",
            f"![learning curves]({settings.link}/{stem}_curves.png)",
            "",
        ]
    return "\n".join(out), [m for m in loaded.values() if m is not None]


def control_section(settings: Settings) -> tuple[str, list[Loaded]]:
    """hidden_goal: scores beside the proven no-message bound and the oracle, the controls, and
    the shuffled messages' cost."""
    from udan.envs.hidden_goal import no_message_bound, oracle_score

    env, agents, obstacles = "arena/hidden_goal", (2, 8), (0, 0)
    loaded = load_models(settings.models, CONTROL)
    out = ["## The positive control: `arena/hidden_goal` (not in the paper)", ""]
    if loaded["UDAN"] is None:
        return "\n".join([*out, f"UDAN: {NOT_TRAINED}.", ""]), []
    tables = {label: _play(m, env, agents, obstacles, settings) for label, m in loaded.items()}
    config = make_vec(env, batch=1, agents=agents[1], obstacles=0).config
    size = (config.height, config.width, config.max_steps)
    columns = range(agents[0], agents[1] + 1)
    lines = [
        "| N | " + " | ".join(map(str, columns)) + " |",
        "|---" * (1 + len(columns)) + "|",
    ]
    for label, results in tables.items():
        values = (
            [NOT_TRAINED] * len(columns)
            if results is None
            else [f"{v:.2f}" for v in _by_agents(results).values()]
        )
        lines.append(f"| {label} | " + " | ".join(values) + " |")
    lines.append(
        "| proven no-message bound | "
        + " | ".join(f"{no_message_bound(*size, n):.2f}" for n in columns)
        + " |"
    )
    lines.append(
        "| oracle (exact) | " + " | ".join(f"{oracle_score(*size, n):.2f}" for n in columns) + " |"
    )
    out += [
        "No agent can solve it alone; an agent that cannot hear the others scores at most the "
        "bound (docs/environments.md).",
        "",
        *lines,
        "",
        _shuffle_table(
            loaded["UDAN"], tables["UDAN"], env, agents, obstacles, settings, "hidden_goal"
        ),
        "",
    ]
    return "\n".join(out), [m for m in loaded.values() if m is not None]


def _scores(results: list[CellResult]) -> np.ndarray:
    """Every episode's score of ``results``, pooled over its cells."""
    return np.concatenate([r.scores for r in results])


def _pooled(results: list[CellResult]) -> str:
    """Every episode's score of ``results`` pooled: "mean [95 % CI]"."""
    mean, half = mean_ci(_scores(results))
    return f"{mean:.2f} [{mean - half:.2f}, {mean + half:.2f}]"


def _walk_row(label: str, results: list[CellResult]) -> str:
    return f"| {label} | {np.mean([r.line_walk for r in results]):.2f} |"


def _task(loaded: Loaded) -> str:
    """The task a MAgent model was trained on, in words: "100×100 map, 300 steps"."""
    env, agents = loaded.checkpoint["env"], loaded.trained_agents
    config = make_vec(env, batch=1, agents=agents, **loaded.options()).config
    return f"{config.map_size}×{config.map_size} map, {config.max_steps} steps"


def _seeds(models: Path, label: str, folder: str) -> list[Loaded]:
    """The models of ``folder``'s other training seeds, each in a ``seed<k>/`` folder of its own
    (the folder itself holds the first)."""
    found = sorted(
        (models / folder).glob("seed*/checkpoint.pt"), key=lambda p: int(p.parent.name[4:])
    )
    entries = [(f"{label}, {p.parent.name}", f"{folder}/{p.parent.name}") for p in found]
    return list(load_models(models, entries).values())


def _seed_row(label: str, seeds: list[int], scores: list[float], sign: bool = False) -> str:
    """One row of the seeds table: every seed's score and their mean with its t-based CI."""
    fmt = "{:+.2f}" if sign else "{:.2f}"
    each = ", ".join(fmt.format(v) for v in scores)
    return (
        f"| {label} | {', '.join(map(str, seeds))} | {each} | {_interval(*seeds_ci(scores), fmt)} |"
    )


def _interval(mean: float, half: float, fmt: str) -> str:
    """``mean [low, high]`` in ``fmt``."""
    return f"{fmt.format(mean)} [{fmt.format(mean - half)}, {fmt.format(mean + half)}]"


@dataclass
class Seeds:
    """One learner's training seeds played on one task: a row group of the table across seeds."""

    algo: str
    """The paper's algorithm key (``"udan"`` for UDAN)."""
    task_of: Loaded | None
    """Whose task every seed is played on (None: the seeds' own)."""
    runs: list[tuple[Loaded, list[CellResult]]]
    """Each seed's model and its results, the first seed first."""

    def task(self) -> str:
        """The task the seeds were played on, comparable between learners."""
        return str((self.task_of or self.runs[0][0]).options())


def _seeds_table(scenario: str, per_seed: dict[str, Seeds], settings: Settings) -> str:
    """Every learner trained with more than one seed: each seed's pooled score, their mean with
    a CI across seeds (the spread between training runs, which one run's episode CI does not
    show), each UDAN's mean minus each such baseline's played on the same task (Welch's t: the
    runs are independent), and what shuffled messages cost each UDAN seed (paired on its
    episodes)."""
    lines = [
        f"**{scenario}: across training seeds** (each seed's score pooled over every N and "
        "episode above, every seed on the same episodes; the 95 % CI is Student's t over seeds, "
        "and Welch's t for a difference of two learners' means)",
        "",
        "| policy | training seeds | score per seed | mean over seeds [95 % CI] |",
        "|---|---|---|---|",
    ]
    means = {
        label: (
            [m.checkpoint["config"]["seed"] for m, _ in learner.runs],
            [_scores(r).mean() for _, r in learner.runs],
        )
        for label, learner in per_seed.items()
        if len(learner.runs) > 1
    }
    for label, (seeds, scores) in means.items():
        lines.append(_seed_row(label, seeds, scores))
    udans = [label for label in means if per_seed[label].algo == "udan"]
    for udan in udans:
        ours, mine = means[udan]
        for label, (seeds, scores) in means.items():
            other = per_seed[label]
            if other.algo != "udan" and other.task() == per_seed[udan].task():
                both = f"{', '.join(map(str, ours))} − {', '.join(map(str, seeds))}"
                difference = _interval(*welch_ci(mine, scores), "{:+.2f}")
                lines.append(f"| {udan} − {label} (Welch's t) | {both} | — | {difference} |")
    for udan in udans:
        learner = per_seed[udan]
        if not learner.runs[0][0].model.spec.communicates:
            continue
        costs = []
        for model, results in learner.runs:
            agents = (min(r.agents for r in results), max(r.agents for r in results))
            shuffled = _play(
                model,
                model.checkpoint["env"],
                agents,
                (0, 0),
                settings,
                "messages=shuffle",
                settings.magent_episodes,
                learner.task_of,
            )
            costs.append(_scores(shuffled).mean() - _scores(results).mean())
        lines.append(_seed_row(f"{udan}, Δ messages=shuffle (paired)", means[udan][0], costs, True))
    return "\n".join(lines)


def magent_section(settings: Settings) -> tuple[str, list[Loaded]]:
    """Table II (pursuit) and Fig. 5 (pursuit, queue, tiger): each committed model evaluated over
    the fleet sizes its scenario's UDAN was trained on; the paper's numbers beside them; and
    what shuffled messages cost each UDAN, paired on the same episodes (the communication
    criterion is read in that table's pooled row); across training seeds where a learner has
    more than one."""
    out = [
        "## Table II and Fig. 5: MAgent pursuit, tiger and queue",
        "",
        "Models are looked for in `magent_<scenario>/` (UDAN) and "
        "`baselines/magent_<scenario>_<algo>/`.",
        "",
        "| scenario | policy | trained on N | tested on N | ours [95 % CI] | paper (Table II) |",
        "|---|---|---|---|---|---|",
    ]
    everything, curves, shuffles, seed_tables, walks = [], [], [], [], []
    for scenario, entries in MAGENT.items():
        loaded = load_models(settings.models, entries)
        udan = loaded["UDAN"]
        per_seed: dict[str, Seeds] = {}
        seed_curves: list[tuple[str, str]] = []
        other_tasks: list[Loaded] = []  # tries on task options of their own (a smaller map)
        for (label, folder, algo), model in zip(entries, loaded.values(), strict=True):
            paper = TABLE_II.get(algo, {}) if scenario == "pursuit" else {}
            theirs = ", ".join(f"{v:g} (trained on {n})" for n, v in paper.items())
            theirs = theirs or "curves only (Fig. 5)"
            if model is None:
                out.append(f"| {scenario} | {label} | — | — | {NOT_TRAINED} | {theirs} |")
                continue
            everything.append(model)
            tested = (udan or model).trained_agents
            env, agents = model.checkpoint["env"], parse_range(tested, "agents")
            episodes = settings.magent_episodes
            results = _play(model, env, agents, (0, 0), settings, episodes=episodes)
            elsewhere = udan is not None and model.options() != udan.options()
            here = f"— (the paper's task: {_task(udan)})" if elsewhere else theirs
            out.append(
                f"| {scenario} | {label} | {model.trained_agents} | {tested} | "
                f"{_pooled(results)} | {here} |"
            )
            if scenario == "queue":
                walks.append(_walk_row(label, results))
            seeds = _seeds(settings.models, label, folder)
            for task_of in (None, udan) if elsewhere else (None,):
                played = [
                    (one, _play(one, env, agents, (0, 0), settings, None, episodes, task_of))
                    for one in (model, *seeds)
                ]
                row = label if task_of is None else f"{label}, played on the paper's {_task(udan)}"
                per_seed[row] = Seeds(algo, task_of, played)
            if elsewhere:
                other_tasks.append(model)
                out.append(
                    f"| {scenario} | {row} | {model.trained_agents} | {tested} | "
                    f"{_pooled(per_seed[row].runs[0][1])} | {theirs} |"
                )
            if model.model.spec.communicates:
                name = scenario if model is udan else f"{scenario} (`{folder}`)"
                shuffle = _shuffle_table(
                    model, results, env, agents, (0, 0), settings, name, episodes
                )
                shuffles += ["", shuffle]
            everything += seeds
            seed_curves += [(label, other.folder) for other in seeds]
        tasks: dict[str, Loaded] = {}  # one row per task: the UDAN's, then the tries'
        for task in [udan, *other_tasks] if udan is not None else []:
            tasks.setdefault(str(task.options()), task)
        for task in tasks.values():
            policy, label = SCRIPTED[scenario]
            if task is not udan:
                label = f"{label}, on the {_task(task)}"
            results = evaluate(
                f"magent/{scenario}",
                POLICIES[policy](settings.seed),
                parse_range(udan.trained_agents, "agents"),
                (0, 0),
                settings.magent_episodes,
                settings.seed,
                task.options(),
            )
            out.append(
                f"| {scenario} | {label} | — | {udan.trained_agents} | {_pooled(results)} | — |"
            )
            if scenario == "queue":
                walks.append(_walk_row(label, results))
        curves += [e for e in entries if loaded[e[0]] is not None] + seed_curves
        if any(len(learner.runs) > 1 for learner in per_seed.values()):
            seed_tables += ["", _seeds_table(scenario, per_seed, settings)]
    scenario = {
        settings.models / folder: f"magent/{name}"
        for name, entries in MAGENT.items()
        for _, folder, *_ in entries
    }
    table = _curves(
        settings.models,
        curves,
        settings.figures / "fig5_curves.png",
        lambda run: scenario.get(run) or scenario[run.parent],  # a seed<k>/ under its first
    )
    if walks:
        out += [
            "",
            "**queue: how near the fleet came to a line** (cells an agent still had to walk to "
            "the nearest line when the episode ended, mean over N; 0: lined up)",
            "",
            "| policy | walk |",
            "|---|---|",
            *walks,
        ]
    out += shuffles + seed_tables
    out += [
        "",
        "Fig. 5 (learning curves): "
        + (
            f"\n\n{table}\n\n![Fig. 5]({settings.link}/fig5_curves.png)"
            if table
            else NOT_TRAINED + "."
        ),
        "",
    ]
    return "\n".join(out), everything


def build(settings: Settings, command: str) -> str:
    """The whole results file."""
    surround, used = arena_section(
        settings,
        env="arena/surround",
        entries=FIG7,
        agents=(1, 5),
        obstacles=(0, 9),
        table="Table V",
        figure="Fig. 7",
        paper_agent=TABLE_V_AGENT,
        paper_goal=TABLE_V_GOAL,
        stem="fig7_surround",
    )
    find_water, more = arena_section(
        settings,
        env="arena/find_water",
        entries=FIG8,
        agents=(1, 5),
        obstacles=(0, 14),
        table="Table VI",
        figure="Fig. 8",
        paper_agent=TABLE_VI,
        paper_goal=None,
        stem="fig8_find_water",
        floor=(9, 41.0),
    )
    control, controls = control_section(settings)
    magent, magents = magent_section(settings)
    models = [*used, *more, *controls, *magents]
    listing = ["| model | checkpoint sha256 |", "|---|---|"] + [
        f"| `models/{m.folder}` ({m.checkpoint['algo']}) | `{m.sha256[:16]}` |" for m in models
    ]
    head = [
        "# Results: the paper's tables and figures, regenerated",
        "",
        f"Written by `{command}` from the committed models; do not edit by hand. "
        f"{settings.episodes} episodes per cell of the arena tasks, "
        f"{settings.magent_episodes} per N on MAgent, seed {settings.seed}: every policy meets "
        "the same layouts. Each model's card (`models/.../README.md`) says how it was trained.",
        "",
        *listing,
        "",
    ]
    return "\n".join([*head, surround, find_water, control, magent]).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    import udan.models

    parser = argparse.ArgumentParser(prog="udan-paper", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--models",
        type=Path,
        default=Path(udan.models.__file__).parent,
        help="folder of the committed models (default: the checkout's models/)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/results.md"),
        help="the markdown file; its figures go to a folder beside it named after it "
        "(default: docs/results.md, figures in docs/results/)",
    )
    parser.add_argument("--episodes", type=int, default=100, help="episodes per arena cell")
    parser.add_argument(
        "--magent-episodes", type=int, default=10, help="episodes per N on MAgent scenarios"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of layouts and policies")
    args = parser.parse_args(argv)
    from udan.checkpoint import CheckpointError

    started = time.perf_counter()
    try:
        if args.episodes < 2 or args.magent_episodes < 2:
            raise EnvConfigError(
                "--episodes and --magent-episodes must be >= 2 (a shuffled message comes from "
                "another episode)"
            )
        if not any((args.models / folder / "checkpoint.pt").is_file() for folder in FOLDERS):
            raise EnvConfigError(
                f"--models: no checkpoint.pt under {args.models} in any of "
                "the folders udan-paper reads"
            )
        if args.out.is_dir():
            raise FolderError(f"--out: {args.out} is a folder, not a file")
        figures = ensure_folder(args.out.parent / args.out.stem, "--out")
        import torch

        torch.set_num_threads(1)
        settings = Settings(
            args.models, figures, args.out.stem, args.episodes, args.magent_episodes, args.seed
        )
        command = "udan-paper" + "".join(
            f" --{k.replace('_', '-')} {v}"
            for k, v in (
                ("episodes", args.episodes),
                ("magent_episodes", args.magent_episodes),
                ("seed", args.seed),
            )
            if v != parser.get_default(k)
        )
        text = build(settings, command)
        args.out.write_text(text)
    except (EnvConfigError, CheckpointError, FolderError) as err:
        print(f"udan-paper: error: {err}", file=sys.stderr)
        return 2
    print(f"{args.out} and {figures}/ written in {time.perf_counter() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
