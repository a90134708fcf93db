"""``roverswarm mission stress``: a swarm's redundancy under random rover failures.

Many episodes of a mission, each run twice per policy: as it is, and with ``failures`` distinct
rovers stopping for good, each at its own random step before the policy would have completed
that episode without them (a later failure changes nothing). The policy runs beside the
oracle, on the same starts and the same failing rovers, each failing at the same share of
that policy's own time to complete the episode (so the steps differ between policies).
"""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np

from roverswarm.env.mars import NEVER
from roverswarm.env.missions import Mission, load_mission
from roverswarm.errors import require
from roverswarm.limits import check_seed
from roverswarm.mission import load_policy, markdown_table, write_rows
from roverswarm.policies import ORACLE, Policy
from roverswarm.rollout import MissionStats, rollout
from roverswarm.runs import check_not_run, folder_lock
from roverswarm.storage import save_figure, write_text


def check_failures(failures: int, num_rovers: int) -> None:
    """``failures`` must leave at least one of ``num_rovers`` working."""
    require(num_rovers >= 2, f"mission stress needs at least 2 rovers (one fails, one keeps working), got {num_rovers}")
    require(
        1 <= failures < num_rovers,
        f"--failures must be in [1, {num_rovers - 1}] for {num_rovers} rovers (one must keep working), got {failures}",
    )


def random_failures(key: jax.Array, finish: np.ndarray, num_rovers: int, failures: int = 1) -> np.ndarray:
    """[E, N] fail steps: in episode e, ``failures`` distinct rovers, each drawn uniformly from
    those still working, fail at steps drawn uniformly in [0, finish[e]), before the mission
    would be complete (a later failure changes nothing; with finish[e] = 0, at step 0). The
    first failure comes from ``key`` itself, failure j > 0 from ``fold_in(fold_in(key, 2), j)``
    (``fold_in(key, 1)`` is one of the first failure's keys): one failure is drawn as it always was."""
    check_failures(failures, num_rovers)
    episodes = np.arange(len(finish))
    fail_step = np.full((len(finish), num_rovers), NEVER, np.int32)
    for j in range(failures):
        k_rover, k_when = jax.random.split(key if j == 0 else jax.random.fold_in(jax.random.fold_in(key, 2), j))
        pick = np.asarray(jax.random.randint(k_rover, (len(finish),), 0, num_rovers - j))
        working = fail_step == NEVER  # [E, N]
        rank = np.cumsum(working, axis=1)  # a working rover's place among them, from 1
        rover = np.argmax(working & (rank == pick[:, None] + 1), axis=1)
        when = np.asarray(jax.random.uniform(k_when, (len(finish),)))
        fail_step[episodes, rover] = np.floor(when * finish).astype(np.int32)
    return fail_step


def condition(failures: int) -> str:
    """The name of the failure rows: 'one rover fails', '2 rovers fail', ..."""
    return "one rover fails" if failures == 1 else f"{failures} rovers fail"


def stress_rows(
    policies: list[Policy], mission: Mission, episodes: int, seed: int, failures: int = 1
) -> tuple[list[dict[str, object]], dict]:
    """For each policy, ``episodes`` episodes without failure, then the same episodes (same
    starts and keys) with ``failures`` random rovers failing at random steps before that
    policy's episode was complete (or before its end, if it never was). Rovers and relative
    times are drawn once, shared by all policies. Returns the summary rows and, per policy,
    (the first failure's time as a fraction of the time to complete [E], success [E]) for the plot.

    Under JAX's partitionable threefry (the default from JAX 0.5) the failures' key
    ``fold_in(key, 1)`` is :func:`rollout`'s run key ``split(key)[1]``, whose splits are the
    episodes' keys. Only the random policy reads those (for its actions); the oracle and trained
    policies do not, and the layouts come from ``split(key)[0]``: the failures are independent
    of the layouts, and of every policy's actions but random's."""
    key = jax.random.PRNGKey(seed)
    rows, curves = [], {}
    for policy in policies:
        clean = MissionStats.of(rollout(policy, key, mission.params, episodes))
        finish = np.where(clean.success, clean.time_to_all, mission.params.max_steps)
        fail_step = random_failures(jax.random.fold_in(key, 1), finish, mission.params.num_rovers, failures)
        failed = MissionStats.of(rollout(policy, key, mission.params, episodes, fail_step=fail_step))
        for name, stats in (("no failure", clean), (condition(failures), failed)):
            rows.append({"policy": policy.name, "condition": name, **stats.summary()})
        curves[policy.name] = (fail_step.min(axis=1) / np.maximum(finish, 1), failed.success)
    return rows, curves


def _stress_png(curves: dict, rows: list[dict[str, object]], mission: Mission, failures: int, path: Path) -> None:
    """Success rate against when the (first) rover failed, as a fraction of the time the policy
    needs without failure, one line per policy, with its success without failure dashed."""
    from matplotlib.figure import Figure  # here: half a second that every other command skips

    figure = Figure(figsize=(7, 5), dpi=100)
    ax = figure.add_subplot()
    edges = np.linspace(0.0, 1.0, 11)
    centres = (edges[:-1] + edges[1:]) / 2
    for (name, (when, success)), color in zip(curves.items(), ("#1f77b4", "#ff7f0e", "#2ca02c")):
        which = np.clip(np.digitize(when, edges) - 1, 0, len(centres) - 1)
        rate = [success[which == b].mean() if np.any(which == b) else np.nan for b in range(len(centres))]
        ax.plot(centres, rate, marker="o", color=color, label=f"{name}: {condition(failures)}")
        baseline = next(r["success"] for r in rows if r["policy"] == name and r["condition"] == "no failure")
        ax.axhline(baseline, color=color, ls="--", lw=1, label=f"{name}: no failure")
    first = "the rover fails" if failures == 1 else "the first rover fails"
    ax.set_xlabel(f"when {first}, as a fraction of the time the swarm needs without failure")
    ax.set_ylabel("mission success (all POIs observed)")
    ax.set_ylim(-0.05, 1.05)
    under = "a rover failure" if failures == 1 else f"{failures} rover failures"
    ax.set_title(f"Mission '{mission.name}': redundancy under {under}")
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.15), ncol=2)
    figure.tight_layout()
    save_figure(figure, path)


def stress_mission(
    mission_path: str | Path,
    policy_spec: str,
    out: str | Path,
    episodes: int = 500,
    seed: int = 0,
    policy_seed: int = 0,
    shield: bool = False,
    failures: int = 1,
) -> list[dict[str, object]]:
    """``mission stress``: the policy beside the oracle, without and with ``failures`` random
    rover failures; writes stress.csv, stress.md and stress.png into ``out``. Returns the rows."""
    require(episodes >= 1, f"--episodes must be >= 1, got {episodes}")
    check_seed(seed)
    out = Path(out)
    with folder_lock(out):  # first: a bad --out is refused before the episodes run, and no one else writes there
        check_not_run(out)
        mission = load_mission(mission_path)
        check_failures(failures, mission.params.num_rovers)
        policy = load_policy(policy_spec, mission, policy_seed, shield, episodes)  # the oracle beside it needs no more
        policies = [policy] if policy.name == ORACLE.name else [policy, ORACLE]
        rows, curves = stress_rows(policies, mission, episodes, seed, failures)
        write_rows(rows, out / "stress.csv")
        header = [
            "policy",
            "condition",
            "success",
            "time to observe all (steps)",
            "POIs observed",
            "collisions",
            "trap contacts",
        ]
        body = [
            [
                r["policy"],
                r["condition"],
                f"{r['success']:.0%}",
                r["time_to_all"],
                r["pois_observed"],
                r["collisions"],
                r["trap_contacts"],
            ]
            for r in rows
        ]
        who = "one rover, drawn uniformly, stops" if failures == 1 else f"{failures} rovers, drawn uniformly, stop"
        each = "" if failures == 1 else ", each"
        write_text(
            out / "stress.md",
            f"# Mission '{mission.name}': {condition(failures)}\n\n{episodes} episodes per row, seed {seed}. "
            f"In the failure rows {who} for good{each} at a step drawn uniformly before the "
            "policy's own time to observe all POIs in that episode without failure (before the episode's end if it "
            "never does): a later failure would change nothing. Time to observe all is the mean over successful "
            "episodes.\n\n" + markdown_table(header, body),
        )
        _stress_png(curves, rows, mission, failures, out / "stress.png")
    return rows
