"""The paper's experiment grid, planned: its arms (algorithms, optimizer readings) and runs,
and the state of each run's folder.

Each (scenario, algorithm) run trains in its own folder ``OUT/runs/<scenario>/<algorithm>``
(:mod:`roverswarm.experiments.grid` trains them).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Literal, get_args

from roverswarm.config import TrainConfig, resumed_config, with_options
from roverswarm.env.scenarios import SCENARIOS
from roverswarm.errors import UserError, require
from roverswarm.limits import read_config
from roverswarm.presets import PRESETS
from roverswarm.runs import (
    CHECKPOINT,
    CONFIG,
    Run,
    budget_spent,
    check_rollout_memory,
    checkpointed_rows,
    logged_rows,
    training_seconds,
)

ALGORITHMS: dict[str, dict[str, str]] = {
    "ddpg": {"algo": "ddpg", "replay": "uniform"},
    "maddpg": {"algo": "maddpg", "replay": "uniform"},
    "maddpg-optimizer": {"algo": "maddpg", "replay": "ranked"},
    "ddpg-optimizer": {"algo": "ddpg", "replay": "ranked"},
    "mappo": {"preset": "mappo"},
    "ippo": {"preset": "ippo"},
}
"""The arms of the grid: the paper's three learners (DDPG, MADDPG, and MADDPG with the
experience sample optimizer) and DDPG with the optimizer at the grid's base settings, and two
on-policy learners beside them, each from its own preset (``preset``)."""

Algorithm = Literal["ddpg", "maddpg", "maddpg-optimizer", "ddpg-optimizer", "mappo", "ippo"]

PAPER_SCENARIOS = ("paper-2", "paper-3", "paper-4", "paper-5")
"""The paper's four swarms (its Table I's rows)."""

QUICK_SCENARIOS = ("paper-2", "paper-5")
"""The quick grid's (``--quick``): the smallest and the largest of the paper's swarms. Each run
compiles its own training and evaluation programs, which take most of a short grid's time
(docs/performance.md#the-readmes-first-command)."""

OPTIMIZERS = {"maddpg-optimizer": "maddpg", "ddpg-optimizer": "ddpg"}
"""The optimizer arms and the plain learner each is compared with on the same seeds (the
paper's Table I: MADDPG's)."""


def _flag(text: str) -> bool:
    require(text.lower() in ("true", "false"), f"must be true or false, got '{text}'")
    return text.lower() == "true"


OPTIMIZER_OPTIONS: dict[str, Callable[[str], object]] = {
    "reading": str,
    "alpha": float,
    "beta": float,
    "refresh_every": int,
    "importance_weights": _flag,
    "importance_exponent": float,
}
"""The options an optimizer arm (``--variants``) may set, the ranked replay's, and how each value is read."""


@dataclass(frozen=True, kw_only=True)
class Backend:
    """Where the runs of a grid or a sweep train (``reproduce``, ``sweep``)."""

    backend: Literal["local", "ray"] = "local"
    """`local`: runs on this machine (see --jobs); `ray`: one Ray task per run, retried if its
    worker dies; an interrupted run resumes in its task (docs/reproduce.md#on-ray)."""
    jobs: int | None = None
    """Local backend: runs trained side by side, each in its own process on its share of the
    CPUs (in the order given). Default: one at a time for runs under 5000 episodes, else as
    many as the CPUs, the memory the runs need and the runs left allow; 1 trains them one
    after another in this process."""
    address: str | None = None
    """Ray cluster address for --backend ray (default: start a local Ray instance)."""
    retries: int = 3
    """Ray: times a run is retried when its worker dies."""


def check_backend(config: Backend) -> None:
    """The backend options are in range and go together; else :class:`UserError` naming one."""
    require(config.retries >= 0, f"--retries must be >= 0, got {config.retries}")
    require(config.address is None or config.backend == "ray", "--address needs --backend ray")
    check_jobs(config.jobs)
    require(config.jobs is None or config.backend == "local", "--jobs is for --backend local (Ray places its tasks)")


@dataclass(frozen=True)
class ReproduceConfig(Backend):
    """The grid of the paper's section IV and where its results go."""

    out: Path = Path("results/paper")
    """Output folder: runs/, table1.md/.csv, fig8.png, fig9.png, report.md."""
    quick: bool = False
    """A small grid that finishes in minutes on a 2-core CPU: the smallest and the largest of
    the paper's swarms, 2 seeds, 2000 episodes per run, metrics every 500 episodes (the
    learners keep their preset's settings)."""
    scenarios: tuple[str, ...] | None = None
    """Scenario presets, one per swarm size N. Default: the paper's four, paper-2 to paper-5
    (paper-2 and paper-5 with --quick: compiling each run's programs is most of a short
    grid's time)."""
    algorithms: tuple[Algorithm, ...] = ("ddpg", "maddpg", "maddpg-optimizer")
    """Learners to compare (Table I needs maddpg and maddpg-optimizer, or ddpg and
    ddpg-optimizer). `ddpg-optimizer` adds DDPG with the optimizer, compared with `ddpg` (not a
    claim of the paper: the optimizer on a learner with local critics). `mappo` and `ippo` add
    an on-policy arm beside the paper's, trained from its own preset (docs/training.md)."""
    seeds: int | None = None
    """Seeds per run, vmapped together (default 5; 2 with --quick)."""
    episodes: int | None = None
    """Training episodes per seed (default the paper's 60000; 2000 with --quick); a multiple of
    1000 (500 with --quick), the episodes between metrics rows."""
    seed: int = 0
    """Base random seed of every run (the same seeds for every learner)."""
    preset: Literal["reference", "default", "swarm"] = "reference"
    """Settings of the paper's learners (DDPG, MADDPG, the optimizer): `reference`, the
    reference MADDPG code's (the paper states only its 2 x 64 networks); `default` or `swarm`
    (docs/training.md#presets)."""
    ensemble: int | None = None
    """Sub-policies per agent of the paper's learners (policy ensembles, section III.B; the
    paper's K = 3). Default: the preset's (1)."""
    infer_policies: bool = False
    """MADDPG arms (with and without the optimizer) learn approximations of the other agents'
    policies (section III.A); DDPG's critics see no other agent, so it trains as before."""
    reading: Literal["paper", "schaul"] | None = None
    """The optimizer's reading of the rank (docs/replay.md#readings). Default: the preset's (`paper`)."""
    alpha: float | None = None
    """The optimizer's alpha. Default: the preset's (1)."""
    beta: float | None = None
    """The optimizer's uniform share beta. Default: the preset's (0.1)."""
    refresh_every: int | None = None
    """Updates between the optimizer's re-rankings. Default: the preset's (250 for `reference`)."""
    variants: tuple[str, ...] = ()
    """Several optimizer arms against the one plain arm, on the same seeds: each
    `NAME` or `NAME:OPTION=VALUE,...` over the optimizer options above (reading, alpha, beta,
    refresh_every, importance_weights, importance_exponent), e.g. `paper` `sharp:alpha=3`
    `schaul:reading=schaul,alpha=0.7,beta=0,importance_weights=true,importance_exponent=0.5`.
    Arm NAME trains in runs/<scenario>/maddpg-optimizer-NAME (and ddpg-optimizer-NAME, if
    ddpg-optimizer is in --algorithms). Default: one arm per optimizer algorithm."""
    force: bool = False
    """Train every run again, even finished ones."""
    time_chunks: int | None = None
    """Chunks of every paper-learner arm timed back to back after training, per scenario (the
    benchmarks' method: full replay, chunks alternating) for the time column of Table I and
    Figure 8; 0 uses the runs' own chunk times, which other load on the machine can skew.
    Default: 3, or 0 for runs under 5000 episodes (--quick)."""
    eval_episodes: int | None = None
    """Deterministic evaluation episodes of every run's final policies, the same for every
    policy (default 1000; 200 with --quick)."""
    keep_programs: bool = False
    """Keep every run's compiled programs in memory until the command ends (released anyway
    past 20,000 memory mappings), as a grid of runs under 5000 episodes (--quick) always does:
    its runs would otherwise spend much of their time loading their programs again (the quick
    grid 2:01 kept against 2:28 released, peak memory 0.97 GB against 0.59 GB). A longer grid
    releases them after every run and evaluation unless this is given."""

    @property
    def grid_scenarios(self) -> tuple[str, ...]:
        if self.scenarios is not None:
            return self.scenarios
        return QUICK_SCENARIOS if self.quick else PAPER_SCENARIOS

    @property
    def grid_seeds(self) -> int:
        return self.seeds if self.seeds is not None else (2 if self.quick else 5)

    @property
    def grid_episodes(self) -> int:
        return self.episodes if self.episodes is not None else (2000 if self.quick else 60_000)

    @property
    def grid_time_chunks(self) -> int:
        if self.time_chunks is not None:
            return self.time_chunks
        return 0 if self.grid_episodes < SHORT_RUN else 3

    @property
    def grid_keep_programs(self) -> bool:
        return self.keep_programs or self.grid_episodes < SHORT_RUN

    @property
    def grid_eval_episodes(self) -> int:
        return self.eval_episodes if self.eval_episodes is not None else (200 if self.quick else 1000)


@dataclass(frozen=True)
class GridRun:
    """One cell of the grid."""

    scenario: str
    algorithm: str
    config: TrainConfig
    folder: Path

    @property
    def name(self) -> str:
        return f"{self.scenario} {self.algorithm}"


def parse_variant(text: str) -> tuple[str, dict[str, object]]:
    """``NAME`` or ``NAME:OPTION=VALUE,...`` -> (NAME, options), each value read as its
    option's type; :class:`UserError` names what is wrong."""
    name, _, rest = text.partition(":")
    require(
        re.fullmatch(r"[a-z0-9][a-z0-9_-]*", name) is not None,
        f"--variants: '{text}' must start with a name of lower-case letters, digits, '-' or '_'",
    )
    options: dict[str, object] = {}
    for item in filter(None, rest.split(",")):
        key, equals, value = item.partition("=")
        require(equals == "=", f"--variants: '{item}' in '{text}' must be OPTION=VALUE")
        require(key not in options, f"--variants: '{key}' is given twice in '{text}'")
        require(
            key in OPTIMIZER_OPTIONS,
            f"--variants: '{key}' in '{text}' is not an optimizer option; allowed: {', '.join(OPTIMIZER_OPTIONS)}",
        )
        try:
            options[key] = OPTIMIZER_OPTIONS[key](value)
        except (ValueError, UserError) as error:
            raise UserError(f"--variants: {key} in '{text}': {error}") from None
    return name, options


def optimizer_arms(config: ReproduceConfig, optimizer: str) -> dict[str, dict[str, object]]:
    """Every arm of the optimizer algorithm ``optimizer`` (a key of :data:`OPTIMIZERS`): its
    name and settings (the optimizer flags, then the variant's)."""
    flags = {k: getattr(config, k) for k in ("reading", "alpha", "beta", "refresh_every")}
    common = {**ALGORITHMS[optimizer], **{k: v for k, v in flags.items() if v is not None}}
    if not config.variants:
        return {optimizer: common}
    arms = {}
    for text in config.variants:
        name, options = parse_variant(text)
        require(f"{optimizer}-{name}" not in arms, f"--variants: the name '{name}' is given twice")
        arms[f"{optimizer}-{name}"] = {**common, **options}
    return arms


def optimizer_of(algorithm: str) -> str | None:
    """The optimizer algorithm (a key of :data:`OPTIMIZERS`) a grid arm runs, for the default
    arm and the ``--variants`` ones (``maddpg-optimizer-sharp`` -> ``maddpg-optimizer``);
    None for an arm without the optimizer."""
    return next((o for o in OPTIMIZERS if algorithm == o or algorithm.startswith(o + "-")), None)


def plan(config: ReproduceConfig, base: TrainConfig | None = None) -> list[GridRun]:
    """The runs of the grid, at the settings of ``base`` (default: ``config.preset``'s) with
    the grid's ensembles, inferred policies and optimizer arms, after checking the input. An
    arm naming a preset (MAPPO, IPPO) starts from that preset instead, with ``base``'s
    logging and checkpoint intervals."""
    base = PRESETS[config.preset] if base is None else base
    require(len(config.grid_scenarios) > 0, "--scenarios: give at least one scenario")
    for name in config.grid_scenarios:
        require(name in SCENARIOS, f"--scenarios: unknown scenario '{name}'; known: {', '.join(SCENARIOS)}")
    sizes = [SCENARIOS[name].params.num_rovers for name in config.grid_scenarios]
    require(len(set(sizes)) == len(sizes), "--scenarios: give each swarm size N once (the report compares by N)")
    require(len(config.algorithms) > 0, f"--algorithms: give at least one of {', '.join(get_args(Algorithm))}")
    require(len(set(config.algorithms)) == len(config.algorithms), "--algorithms: give each algorithm once")
    require(config.grid_seeds >= 1, f"--seeds must be >= 1, got {config.grid_seeds}")
    log_every = 500 if config.quick else base.log_every
    require(
        config.grid_episodes >= 1 and config.grid_episodes % log_every == 0,
        f"--episodes must be a positive multiple of {log_every} (the episodes between the grid's metrics rows"
        f"{'' if config.quick else '; 500 with --quick'}), got {config.grid_episodes}",
    )
    require(config.grid_time_chunks >= 0, f"--time-chunks must be >= 0, got {config.grid_time_chunks}")
    require(config.grid_eval_episodes >= 1, f"--eval-episodes must be >= 1, got {config.grid_eval_episodes}")
    check_backend(config)
    require(
        not config.variants or any(a in OPTIMIZERS for a in config.algorithms),
        f"--variants needs {' or '.join(OPTIMIZERS)} in --algorithms",
    )
    given = [
        f"--{k.replace('_', '-')}"
        for k in ("reading", "alpha", "beta", "refresh_every")
        if getattr(config, k) is not None
    ]
    require(
        not given or any(a in OPTIMIZERS for a in config.algorithms),
        f"{', '.join(given)} set the optimizer: give {' or '.join(OPTIMIZERS)} in --algorithms",
    )
    arms: dict[str, dict[str, object]] = {}
    for algorithm in config.algorithms:
        arms.update(
            optimizer_arms(config, algorithm) if algorithm in OPTIMIZERS else {algorithm: dict(ALGORITHMS[algorithm])}
        )
    learners = [settings for settings in arms.values() if "preset" not in settings]  # the paper's
    require(
        config.ensemble is None or bool(learners),
        "--ensemble is for the paper's learners (ddpg, maddpg and their optimizer arms); --algorithms has none",
    )
    require(
        not config.infer_policies or any(settings["algo"] == "maddpg" for settings in learners),
        "--infer-policies is for the MADDPG arms (maddpg, maddpg-optimizer); --algorithms has none",
    )
    paper = {} if config.ensemble is None else {"ensemble": config.ensemble}
    runs = []
    for scenario in config.grid_scenarios:
        for algorithm, settings in arms.items():
            settings = dict(settings)
            if "preset" not in settings:  # one of the paper's learners
                infer = config.infer_policies and settings["algo"] == "maddpg"
                settings.update(paper, **({"infer_policies": True} if infer else {}))
            start = PRESETS[settings.pop("preset")] if "preset" in settings else base
            train_config = with_options(
                start,
                dict(
                    settings,
                    scenario=scenario,
                    episodes=config.grid_episodes,
                    seeds=config.grid_seeds,
                    seed=config.seed,
                    log_every=log_every,
                    checkpoint_every=base.checkpoint_every,
                ),
            )
            runs.append(GridRun(scenario, algorithm, train_config, config.out / "runs" / scenario / algorithm))
    return runs


def run_rows(run: GridRun) -> list[dict[str, float]]:
    """The metrics rows of ``run``'s checkpoint (none before its first): ``metrics.csv`` may run
    a chunk ahead of it where training was killed between the two (an extension's rows past a
    finished run's end), and those episodes were never saved."""
    return checkpointed_rows(run.folder)[1] if (run.folder / CHECKPOINT).exists() else []


def status(run: GridRun) -> Literal["done", "partial", "new"]:
    """Whether ``run``'s folder holds its finished run (all its episodes, or its
    ``--budget-minutes`` spent), an interrupted one, or nothing. A run of fewer episodes or
    another budget, its settings otherwise the same, is one to extend: "partial" until it
    has trained the episodes asked (or spent the budget), as ``train --resume`` would extend it.

    A folder holding a run of other settings, or of more episodes, is an error (the user
    chooses: delete it, reproduce --force, or another --out), never silently overwritten."""
    if not (run.folder / CONFIG).exists():
        return "new"
    saved = read_config(run.folder / CONFIG)
    try:
        resumed_config(run.config, saved)  # the settings a resume may not change are the same
        longer = saved.episodes > run.config.episodes
        reason = f"{saved.episodes} episodes, more than {run.config.episodes}" if longer else ""
    except UserError as e:
        reason = str(e).removeprefix("--resume: ")
    rows = [] if reason else run_rows(run)  # none without a checkpoint
    trained = int(max((r["episodes"] for r in rows), default=0))
    if trained > run.config.episodes:
        reason = f"{trained} episodes trained, more than {run.config.episodes}: an extension stopped"
        reason += " before it saved its settings"
    if reason:
        raise UserError(
            f"'{run.folder}' holds a run with other settings ({reason}); delete that folder (reproduce --force "
            "deletes every run of its grid; sweep has no --force) or choose another --out"
        )
    if not (run.folder / CHECKPOINT).exists():
        return "new"
    finished = sum(1 for r in rows if r["episodes"] == run.config.episodes) == run.config.seeds
    return "done" if finished or budget_spent(run.config, training_seconds(rows)) else "partial"


def episodes_done(run: GridRun) -> int:
    """Episodes per seed ``run``'s checkpoint holds (what a resume starts from)."""
    return int(max((r["episodes"] for r in run_rows(run)), default=0))


def episodes_logged(run: GridRun) -> int:
    """Episodes per seed of ``run``'s last metrics row, checkpointed or not: a running job's
    progress, chunk by chunk."""
    return int(max((r["episodes"] for r in logged_rows(run.folder)), default=0))


# ----------------------------------------------------------------------------- jobs

SHORT_RUN = 5000
"""Episodes per seed below which runs train one after another: start-up and compilation
dominate such runs, and side by side they finished no sooner (benchmarks/reproduce_jobs.py:
the quick grid 0.94x with two jobs at 2000 episodes, 1.40x at 10,000)."""


def check_evaluations(runs: list[GridRun], episodes: int) -> None:
    """Refuse, before any run trains, an evaluation of ``episodes`` episodes per policy that
    will not fit in memory once the runs are trained (:func:`~roverswarm.runs.check_rollout_memory`,
    as ``evaluate`` checks it then: an error after all the training, naming --episodes)."""
    sets = f"--eval-episodes {episodes}"
    for run in runs:
        handle = Run.of(run.config, None)  # its config and environment (validated), no networks yet
        check_rollout_memory(handle, [handle.params], episodes, sets, f"evaluating run '{run.name}'")


def check_jobs(jobs: int | None) -> None:
    """A ``--jobs`` value is None (the default) or between 1 and the CPUs this process may use."""
    cpus = len(usable_cpus())
    require(
        jobs is None or 1 <= jobs <= cpus, f"--jobs must be in [1, {cpus}] (the CPUs this process may use), got {jobs}"
    )


def usable_cpus() -> list[int]:
    """The CPUs this process may use (all of them where the system cannot say, e.g. macOS)."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))
