"""The run folder: what a training run writes and how it is read back.

A run folder holds ``config.json`` (the :class:`~roverswarm.config.TrainConfig`),
``metrics.csv`` (one row per seed per ``log_every`` episodes), ``checkpoint.npz`` (the
trainer's state as plain arrays, never pickle), TensorBoard events in ``tb/`` and
``learning_curve.png``. :class:`Run` opens a folder and gives its config, metrics, networks
and policies, one way, for every command that reads a run.
"""

from __future__ import annotations

import contextlib
import csv
import functools
import os
import socket
from pathlib import Path
from typing import Any, Iterable, Iterator, Literal

import jax
import numpy as np

from roverswarm.config import TrainConfig, validate
from roverswarm.env.mars import EnvParams, count_text
from roverswarm.errors import UserError, require, unwritable, within
from roverswarm.learners import learner_family
from roverswarm.limits import batch_part, check_memory, networks_part, open_limited, read_config
from roverswarm.metrics import EPISODE_METRICS, reduce_metric
from roverswarm.policies import REFERENCE_POLICIES, Policy, mixed_policy, shielded, trained_policy
from roverswarm.storage import atomic_write, read_arrays, restore, save_figure, trained_episodes

CHECKPOINT = "checkpoint.npz"
CONFIG = "config.json"
METRICS = "metrics.csv"
CURVE = "learning_curve.png"
LOCK = ".lock"


@contextlib.contextmanager
def folder_lock(folder: Path) -> Iterator[None]:
    """Create ``folder`` if needed and hold ``folder/.lock`` while writing it: a second writer
    gets :class:`UserError` instead of mixing its files with the first's.

    The lock is ``fcntl.flock`` on the open file, held for the writer's life: taking it is
    atomic, and the kernel releases it when the process ends however it ends, so a stale
    ``.lock`` (a killed run) is simply taken over, by exactly one of several writers started
    together. The file holds the writer's process id and host, for the message; a ``.lock``
    naming a live process on this host that does not hold the flock (an older roverswarm)
    is respected too. A folder created here and left empty is removed again."""
    import fcntl

    created = not folder.exists()
    path, me = folder / LOCK, f"{os.getpid()} {socket.gethostname()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise UserError(f"output folder '{folder}' is a file (or lies inside one), not a folder") from None
    except OSError as error:  # read-only file system, no permission, ...
        raise UserError(f"output folder '{folder}' cannot be written ({unwritable(error)})") from error
    if not folder.is_dir():
        raise UserError(f"output folder '{folder}' is a file (or lies inside one), not a folder")
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
        except OSError as error:
            raise UserError(f"output folder '{folder}' cannot be written ({unwritable(error)})") from error
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise UserError(_held(folder, path, _lock_owner(path) or "(unknown)")) from None
        try:  # the file may have been removed and made anew by a writer that just finished: lock that one
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        owner = _lock_owner(path)
        if owner is not None and owner.split()[0] != str(os.getpid()):
            raise UserError(_held(folder, path, owner))
        os.ftruncate(fd, 0)
        os.pwrite(fd, me.encode(), 0)
    except BaseException:
        os.close(fd)
        raise
    try:
        yield
    finally:
        path.unlink(missing_ok=True)  # while still holding the flock: a waiting writer then makes a new file
        os.close(fd)
        if created and folder.exists() and not any(folder.iterdir()):
            folder.rmdir()


def holds_run(folder: Path) -> bool:
    """Whether ``folder`` holds a training run: its ``config.json`` and ``checkpoint.npz``."""
    return (folder / CONFIG).exists() and (folder / CHECKPOINT).exists()


def check_not_run(out: Path) -> None:
    """:class:`UserError` if the output folder ``out`` (``--out``) holds a training run, whose
    files (``metrics.csv``, ...) another command's outputs would overwrite or mix with."""
    require(
        not (out / CONFIG).exists(),  # with its checkpoint, or a run killed before its first
        f"--out: '{out}' holds a training run (its config.json), whose files these outputs "
        "would overwrite or mix with; give --out a folder of its own",
    )


def _held(folder: Path, path: Path, owner: str) -> str:
    return (
        f"'{folder}' is being written by process {owner} (its {LOCK}); wait for it to finish, choose "
        f"another --out, or delete '{path}' if that process is gone"
    )


def _lock_owner(path: Path) -> str | None:
    """'PID on HOST' of a lock's live writer; None if the lock is stale (its process is gone
    from this host, or its number now belongs to a program that is not Python: numbers are
    reused, after a reboot too) or vanished. A writer on another host is taken to be alive."""
    try:
        pid, host = path.read_text().split()
        number = int(pid)
    except FileNotFoundError:
        return None
    except ValueError:  # empty or garbage: nobody named (the flock says whether it is held)
        return None
    if host == socket.gethostname() and not _may_be_writer(number):
        return None
    return f"{pid} on {host}"


def _may_be_writer(pid: int) -> bool:
    """Whether process ``pid`` of this host lives and may run roverswarm: its command line names
    Python or roverswarm where ``/proc`` shows it (elsewhere, living is enough)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, someone else's
        pass
    try:
        command = Path(f"/proc/{pid}/cmdline").read_bytes()
        return b"python" in command or b"roverswarm" in command
    except OSError:  # no /proc (macOS): living is enough; with /proc, the process just ended
        return not Path("/proc/self").exists()


def training_seconds(rows: list[dict[str, float]]) -> float:
    """Wall seconds a run has trained, over all its sessions: the sum of its metrics rows'
    ``wall_seconds`` (each chunk's time for all seeds, so one seed's rows)."""
    return sum(r["wall_seconds"] for r in rows if r["seed"] == 0)


def checkpointed_rows(folder: Path) -> tuple[int, list[dict[str, float]]]:
    """The episodes per seed ``folder``'s checkpoint has trained and the ``metrics.csv`` rows up
    to them (the file is written just before a checkpoint, so it may run one chunk ahead)."""
    done = trained_episodes(folder / CHECKPOINT)
    return done, [r for r in logged_rows(folder) if r["episodes"] <= done] if done else []


def logged_rows(folder: Path) -> list[dict[str, float]]:
    """The rows of ``folder``'s ``metrics.csv`` (none if it was never written)."""
    return read_metrics(folder / METRICS) if (folder / METRICS).exists() else []


def budget_spent(config: TrainConfig, seconds: float) -> bool:
    """Whether ``seconds`` of training use up the run's ``--budget-minutes`` (never without one)."""
    return config.budget_minutes > 0 and seconds >= 60 * config.budget_minutes


def metric_rows(
    config: TrainConfig, metrics: dict[str, np.ndarray], episodes: int, seconds: float
) -> list[dict[str, float]]:
    """One row per seed for a chunk: the episode totals (:data:`~roverswarm.metrics.EPISODE_METRICS`,
    every rover's reward after ``episode_reward``), the family's learner metrics and
    ``wall_seconds``, the chunk's time for all seeds together."""
    rows = []
    for s in range(config.seeds):
        row: dict[str, float] = {"seed": s, "episodes": episodes, "episode_reward": float(metrics["episode_reward"][s])}
        for i, r in enumerate(metrics["agent_rewards"][s]):
            row[f"agent_{i}_reward"] = float(r)
        for k in EPISODE_METRICS[1:]:
            row[k] = float(metrics[k][s])
        for k in learner_family(config.learner.algo).metric_names(config):
            row[k] = float(reduce_metric(k, metrics[k][s], None))
        row["wall_seconds"] = seconds
        rows.append(row)
    return rows


def write_csv(path: Path, rows: Iterable[dict], columns: list[str] | None = None) -> None:
    """``rows`` (dicts with the same keys; ``columns``, default the first row's, ``rows`` then a
    list) as a CSV file, written atomically (temp file + rename) row by row as they come."""

    def write(f) -> None:
        writer = csv.DictWriter(f, fieldnames=columns or list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

    atomic_write(path, write)


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table of the ``header`` cells and ``rows`` (a cell may hold several, joined by " | ")."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * sum(h.count("|") + 1 for h in header)]
    return "\n".join(lines + ["| " + " | ".join(row) + " |" for row in rows]) + "\n"


COUNT_COLUMNS = ("seed", "episodes")
"""Integer columns of ``metrics.csv``; kept integers when a resumed run rewrites the file."""


READ_COLUMNS = (*COUNT_COLUMNS, "wall_seconds")
"""Columns of ``metrics.csv`` that resuming, extending and the sweeps' timings read."""


def read_metrics(path: Path) -> list[dict[str, float]]:
    """The rows of a ``metrics.csv``: ``seed`` and ``episodes`` as ints, the rest as floats;
    :class:`UserError` if the file is damaged (or lacks one of :data:`READ_COLUMNS`)."""
    try:
        with open_limited(path, "metrics.csv") as f:
            reader = csv.DictReader(f)
            missing = [c for c in READ_COLUMNS if c not in (reader.fieldnames or ())]
            if missing:
                raise ValueError(f"no column {missing[0]!r}")
            return [{k: int(float(v)) if k in COUNT_COLUMNS else float(v) for k, v in row.items()} for row in reader]
    except UserError:  # past its size limit
        raise
    except (ValueError, TypeError, UnicodeDecodeError, csv.Error) as error:
        raise UserError(f"'{path}' is damaged ({error}); it is not a roverswarm metrics file") from error


def plot_learning_curve(
    rows: list[dict[str, float]],
    path: Path,
    title: str,
    x: str = "episodes",
    y: str = "episode_reward",
    ylabel: str = "mean episode reward",
) -> None:
    """Mean episode reward per 1000 episodes (or column ``y`` against ``x``): one thin line per
    seed and their mean."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    seeds = sorted({int(r["seed"]) for r in rows})
    curves = []
    for s in seeds:
        xs = [r[x] for r in rows if int(r["seed"]) == s]
        ys = [r[y] for r in rows if int(r["seed"]) == s]
        ax.plot(xs, ys, lw=0.8, alpha=0.5, label=f"seed {s}")
        curves.append(ys)
    length = min(len(c) for c in curves)
    ax.plot(xs[:length], np.mean([c[:length] for c in curves], axis=0), color="black", lw=2, label="mean")
    ax.set_xlabel(x)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path)


SubPolicies = Literal["random", "each"]
Partners = Literal["own", "other-seeds"]


def partner_seeds(seed: int, num_agents: int, seeds: int) -> np.ndarray:
    """[N] the seed each agent's actor comes from under ``other-seeds``: ``(seed + i) mod S``."""
    return (seed + np.arange(num_agents)) % seeds


_seed_of = jax.jit(lambda tree, index: jax.tree.map(lambda x: x[index], tree))
"""Seed ``index`` of every leaf [S, ...] of ``tree``: one compiled program, where indexing leaf by
leaf compiled one per leaf shape."""


class Run:
    """A finished or interrupted run in ``folder``: its config, metrics, networks and policies.

    The networks are the last checkpoint's; :class:`UserError` if the folder holds no run."""

    def __init__(self, folder: str | os.PathLike):
        self.folder = Path(folder)
        require(holds_run(self.folder), f"'{self.folder}' holds no trained run (config.json and checkpoint.npz)")
        self.config: TrainConfig = read_config(self.folder / CONFIG)
        with within(f"the run in '{self.folder}': its config.json"):  # a setting this version refuses
            self.params: EnvParams = validate(self.config)
        check_memory([networks_part(self.config, self.params)], f"the run in '{self.folder}'")

    @classmethod
    def of(cls, config: TrainConfig, learner: Any, folder: str | os.PathLike = "(in memory)") -> Run:
        """A run held in memory (e.g. a :class:`~roverswarm.trainer.Result`'s config and networks)."""
        run = cls.__new__(cls)
        run.folder, run.config, run.params = Path(folder), config, validate(config)
        run.__dict__["learner"] = learner
        return run

    def metrics(self) -> list[dict[str, float]]:
        """The rows of ``metrics.csv`` (none if it was never written)."""
        return logged_rows(self.folder)

    @functools.cached_property
    def learner(self) -> Any:
        """Every seed's networks [S, ...] from the checkpoint (read once)."""
        family = learner_family(self.config.learner.algo)
        # the template's shapes only (eval_shape): building fresh networks to overwrite them took seconds
        template = jax.eval_shape(lambda: family.learners(family.configure(self.config, self.params), self.params))
        return restore(template, read_arrays(self.folder / CHECKPOINT, "learner/"), prefix="learner/")

    @property
    def any_size(self) -> bool:
        """Whether this run's policies drive any number of rovers (an entity network)."""
        family = learner_family(self.config.learner.algo)
        return family.view(family.acting(self.config)) is not None

    def policy(self, seed: int = 0) -> Policy:
        """Seed ``seed``'s deterministic policy (with ensembles, a sub-policy per agent and episode)."""
        require(
            0 <= seed < self.config.seeds,
            f"--policy-seed must be in [0, {self.config.seeds}) for '{self.folder}', got {seed}",
        )
        ensemble = ", random sub-policies" if self.config.learner.ensemble > 1 else ""
        name = f"{self.config.learner.algo} ({self.folder.name}, seed {seed}{ensemble})"
        return self._policy(seed, name, seed=seed)

    def _policy(self, index: int, name: str, sub_policy: int | None = None, seed: int = 0) -> Policy:
        """Seed ``index``'s policy (its networks and observation normaliser); with ensembles,
        sub-policy ``sub_policy`` for every agent, or random ones drawn with ``seed``."""
        actor, norm = _seed_of(learner_family(self.config.learner.algo).weights(self.learner), index)
        return trained_policy(self.config, actor, name, sub_policy, seed, obs_norm=norm)

    def policies(
        self, sub_policies: SubPolicies = "random", seed: int = 0, partners: Partners = "own", rovers: int | None = None
    ) -> list[Policy]:
        """Every seed's trained policy; with ensembles, a random sub-policy per agent and episode
        as in training (``random``), or every sub-policy k of all agents in turn (``each``).
        With ``partners="other-seeds"`` agent i of seed s's swarm is seed ``(s + i) mod S``'s
        agent i (:func:`partner_seeds`, :func:`~roverswarm.policies.mixed_policy`): a test of how
        well a policy copes with partners it was not trained with; ``rovers``: the swarm's size
        (an any-size run's, evaluated at another size; default the run's own)."""
        config = self.config
        require(sub_policies in ("random", "each"), f"--sub-policies must be 'random' or 'each', got '{sub_policies}'")
        require(partners in ("own", "other-seeds"), f"--partners must be 'own' or 'other-seeds', got '{partners}'")
        require(
            partners == "own" or config.seeds >= 2,
            f"--partners other-seeds needs a run trained with --seeds >= 2, this one has {config.seeds}",
        )
        algo, ensemble = config.learner.algo, config.learner.ensemble
        require(
            sub_policies == "random" or ensemble > 1,
            f"--sub-policies each needs a run trained with --ensemble K > 1 (each agent's K sub-policies in turn); "
            f"the run in '{self.folder}' has one policy per agent",
        )
        sub = [None] if ensemble == 1 or sub_policies == "random" else list(range(ensemble))
        policies = []
        for s in range(config.seeds):
            sources = (
                partner_seeds(s, rovers or self.params.num_rovers, config.seeds) if partners == "other-seeds" else None
            )
            name = f"{algo} seed {s}" if sources is None else f"{algo} agents of seeds {'/'.join(map(str, sources))}"
            for k in sub:
                full = name + ("" if ensemble == 1 else ", random sub-policies" if k is None else f", sub-policy {k}")
                if sources is None:
                    policies.append(self._policy(s, full, k, seed))
                else:
                    policies.append(mixed_policy(full, [self._policy(int(i), full, k, seed) for i in sources]))
        return policies


def load_policy(
    spec: str,
    params: EnvParams,
    target: str,
    seed: int = 0,
    hint: str = "",
    shield: bool = False,
    episodes: int = 1,
    sets: str = "",
) -> Policy:
    """``oracle``, ``random``, or seed ``seed`` of the trained run in folder ``spec``, checked
    against ``params``'s numbers of rovers, POIs and traps (the positions may differ) and, before
    its networks are read, against memory for ``episodes`` episodes at once on ``params``
    (:func:`check_rollout_memory`; ``sets``, default ``target``, names what sets their size); with
    ``shield``, behind the safety layer (:func:`~roverswarm.policies.shielded`). ``target``
    names ``params`` in the error, ``hint`` ends it."""
    run = None
    if spec not in REFERENCE_POLICIES:
        require(
            Path(spec).is_dir(),
            f"--policy: expected 'oracle', 'random' or a run folder of `roverswarm train`, got '{spec}'",
        )
        run = Run(spec)
        check_fits(run, params, target, hint)
    check_rollout_memory(run, [params], episodes, sets or target, f"running '{spec}' on {target}")
    policy = REFERENCE_POLICIES[spec] if run is None else run.policy(seed)
    return shielded(policy) if shield else policy


def check_rollout_memory(run: Run | None, sizes: list[EnvParams], episodes: int, sets: str, what: str) -> None:
    """:func:`~roverswarm.limits.check_memory` of ``episodes`` episodes at once of ``run``'s policies
    (None: random or the oracle, no networks) on the largest environment of ``sizes``, before any
    rollout: the networks as the run holds them (its own shapes, whatever size they drive) and
    the batch (:func:`~roverswarm.limits.batch_part`; ``sets`` names what sets its size, ``what``
    the work refused)."""
    width = 0 if run is None else sum(run.config.learner.hidden)
    batch = max((batch_part(params, episodes, width, sets) for params in sizes), key=lambda part: part.bytes)
    check_memory(([] if run is None else [networks_part(run.config, run.params)]) + [batch], what)


def check_fits(run: Run, params: EnvParams, target: str, hint: str = "", flag: str = "--policy") -> None:
    """:class:`UserError` unless ``run``'s policies can drive ``params``: any size for an
    any-size run, else the same numbers of rovers, POIs and traps (``target`` names ``params``,
    ``flag`` the option that asked for it)."""
    trained = run.params
    require(
        run.any_size
        or (trained.num_rovers, trained.num_pois, trained.num_traps)
        == (params.num_rovers, params.num_pois, params.num_traps),
        f"{flag}: '{run.folder}' was trained for {count_text(trained)} ({run.config.env_name()}); {target} has "
        f"{count_text(params)}.{' ' + hint if hint else ''}",
    )
