"""One policy for every swarm size: train the `anysize` preset once, judge it at every size.

    python docs/results/any-size/any_size.py --run runs/anysize              # train (or resume), then evaluate
    python docs/results/any-size/any_size.py --run runs/anysize --evaluate   # evaluate the run as it stands
    python docs/results/any-size/any_size.py --run runs/anysize --stress-only  # only its mission stress
    python docs/results/any-size/any_size.py --run runs/anysize --evaluate --shield \
        --out docs/results/any-size/any-size-shield  # behind the safety layer (rows of their own)
    python docs/results/any-size/any_size.py --run runs/anysize-shield --shield --episodes 60000 \
        --out docs/results/any-size/any-size-shield-trained  # trained behind it
    python docs/results/any-size/any_size.py --specialists runs/specialists  # one network per size, then the figure
    python docs/results/any-size/any_size.py --run runs/ddpg-anysize --algo ddpg --episodes 60000  # off-policy
    python docs/results/any-size/any_size.py --run runs/anysize-margin --trap-shaping 2 --trap-margin 0.1 \
        --hidden 128 128 128 128 --out /tmp/margin  # a margin round the traps (not run at 5 seeds: its
        # twenty-first round's rows are 2-seed probes, probe.py, docs/results/any-size/README.md)

Trains ``roverswarm train --preset anysize --seeds 5`` (MAPPO over each rover's nearest
entities on paper-2..10, a size drawn per episode; with ``--algo ddpg`` or ``maddpg`` the
off-policy family across the same sizes, the ``anysize-ddpg`` preset) into ``--run`` (resumed if there; Ctrl-C saves),
then evaluates every seed's deterministic policy at N = 2..10 (the sizes it trained on) and at
12, 16, 20 and 32 (sizes it never saw), 1000 episodes per policy on the same layouts, beside
random and the oracle. Writes ``any-size.csv`` / ``.md`` (the sweep tables' columns: every seed's
score, the means of POIs observed, collisions and trap contacts, the oracle's trap contacts)
and ``any-size.png``: the score against N beside the best per-size rows of the scale sweeps
(``docs/results/swarm/score-vs-n.csv``) and the earlier anysize runs (``any-size-v1.csv`` .. ``-v4.csv``).
Last, ``mission stress`` of ``examples/mission.yaml`` for every seed, with and without one
random rover failure, beside the oracle: ``any-size-stress.csv``.

``--specialists FOLDER`` trains the same network on one size each (``paper-N`` for N in
:data:`SPECIALIST_SIZES`, no size mixing; ``--specialist-episodes``, 20,000 by default: about
what the one policy sees of each of its 9 sizes in 200,000), 5 seeds each, the learning rates
annealed over those episodes as the preset's are over its own (so a run is not extended to
more: give each episode count a folder of its own), evaluates each at its own size and writes
its rows into ``any-size-specialists.csv`` (keeping those of other episode counts); the
figure then shows them beside the one policy. The committed specialists trained with
constant learning rates (20,000 episodes, then extended to 60,000).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from roverswarm import train
from roverswarm.config import TrainConfig, with_options
from roverswarm.env.entities import POI_ORDERS
from roverswarm.evaluate import evaluate_run
from roverswarm.experiments.sweep import figure, markdown, read_table
from roverswarm.finetune import RECORD as FINETUNED
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.limits import read_config
from roverswarm.presets import PRESETS
from roverswarm.runs import CONFIG, METRICS, read_metrics, training_seconds, write_csv
from roverswarm.storage import atomic_write

HERE = Path(__file__).resolve().parent
SIZES = (2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 16, 20, 32)
BASELINES = {"swarm (60k)", "swarm-ddpg (60k)", "mappo (40k)"}
"""The best per-size rows of today (one network per size), from the scale sweeps."""
EARLIER = (*(HERE / f"any-size-v{k}.csv" for k in (1, 2, 3, 4)), HERE / "any-size-matched.csv")
"""The earlier anysize runs' rows, kept beside the new: the first (20,000 episodes, no POI lead,
no curriculum), the second (60,000 episodes, 2 x 64 networks, no sample balance), the third
(200,000 episodes, constant learning rates), the fourth (250,000 episodes, annealed; no
claim lead, a value of the rover's own view) and the matched view's first (80,000 episodes,
the greedy matching before its crossing routes were swapped apart)."""
PRESET = HERE / "any-size-uncrossed.csv"
"""The preset's 5-seed run without the safety layer, beside every other table's figure."""
SHIELDED = {
    "the preset behind the safety layer": HERE / "any-size-shield.csv",
    "trained behind the safety layer (60k)": HERE / "any-size-shield-trained.csv",
    "trained behind it with failures (60k)": HERE / "any-size-shield-fail.csv",
    "failures, episodes end when complete, behind it": HERE / "any-size-stop-fail-shield.csv",
}
"""The tables behind the safety layer: the preset's run evaluated behind it, the runs trained
behind it (without and with rover failures), and the run trained with failures and episodes
that end when complete, evaluated behind it. The trap contacts figure (:data:`CONTACTS`,
redrawn when any of them is written) sets every one that exists beside :data:`PRESET` and the
oracle."""
CONTACTS = HERE / "any-size-shield-contacts.png"
MISSION = HERE.parents[2] / "examples" / "mission.yaml"
"""The example mission of ``mission stress``, for this script and the ones beside it."""
SPECIALIST_SIZES = (2, 3, 5, 8, 10)
SPECIALISTS = HERE / "any-size-specialists.csv"


def trained(run: Path) -> tuple[int, float]:
    """(episodes per seed, minutes) the run has trained so far (it may have been stopped early)."""
    rows = read_metrics(run / METRICS)
    return int(max(r["episodes"] for r in rows)), training_seconds(rows) / 60


def table(
    run: Path, episodes: int, sizes=SIZES, setting: str = "anysize", shield: bool = False
) -> list[dict[str, object]]:
    """One row per size of ``sizes``: every seed's normalised score and trap contacts, and the
    means the sweep tables give (``shield``: the policies behind the safety layer, ``evaluate
    --shield``)."""
    done, minutes = trained(run)
    if (run / FINETUNED).exists():  # a run of `roverswarm finetune`: the training of the run it fine-tuned, then that
        setting += f" + finetune ({json.loads((run / FINETUNED).read_text())['iterations_done']} iterations)"
    rows = []
    evaluated = evaluate_run(run, episodes, scenario="paper-" + ",".join(str(n) for n in sizes), shield=shield)
    for n in sizes:
        mine = [r for r in evaluated if r["scenario"] == f"paper-{n}"]
        by = {r["policy"]: r for r in mine}
        seeds = [r for r in mine if r["policy"] not in ("random", "oracle")]
        scores = [float(r["normalized_score"]) for r in seeds]
        rows.append(
            {
                "scenario": f"paper-{n}",
                "setting": f"{setting} ({done / 1000:g}k)",
                "episodes": done,
                "seeds": len(seeds),
                "scores": " / ".join(f"{s:.2f}" for s in scores),
                "min_score": min(scores),
                "mean_score": float(np.mean(scores)),
                **{k: float(np.mean([r[k] for r in seeds])) for k in ("pois_observed", "collisions", "trap_contacts")},
                "seed_trap_contacts": " / ".join(f"{r['trap_contacts']:.2f}" for r in seeds),
                "oracle_trap_contacts": by["oracle"]["trap_contacts"],
                "oracle_pois_observed": by["oracle"]["pois_observed"],
                "random_reward": by["random"]["episode_reward"],
                "oracle_reward": by["oracle"]["episode_reward"],
                "train_minutes": minutes,
            }
        )
    return rows


def anysize(episodes: int, seeds: int, **options) -> TrainConfig:
    """The anysize preset for ``episodes`` per seed, its learning rates annealed over them, with
    ``options`` named as on the command line (``fail_rate``, ``unobserved_shaping``, ...)."""
    base = dataclasses.replace(PRESETS["anysize"], episodes=episodes, seeds=seeds)
    return with_options(base, {"anneal_episodes": episodes, **options})


def off_policy(algo: str, episodes: int, seeds: int, **options) -> TrainConfig:
    """The ``anysize-ddpg`` preset (the off-policy family across sizes, as in the eleventh probe
    round: README.md) with ``algo`` and ``options``; MADDPG's critic sees each rover's 2 nearest
    others."""
    critic = {"critic_neighbors": 2} if algo == "maddpg" else {}
    base = {**critic, "algo": algo, "episodes": episodes, "seeds": seeds}
    return with_options(PRESETS["anysize-ddpg"], {**base, **options})


def setting(config: TrainConfig) -> str:
    """The rows' setting: ``anysize`` (or the off-policy learner across sizes), with what the
    run changes of the rover-loss lesson, the size draw, the trap shaping, the teacher (and
    its decay) and the safety layer when it has them."""
    limit = f" up to {config.fail_max_rovers} rovers" if config.fail_max_rovers else ""
    count = f" x up to {config.fail_count}" if config.fail_count > 1 else ""
    extra = [f"fail {config.fail_rate:g}{count}{limit}"] * (config.fail_rate > 0)
    extra += [f"shaping {config.learner.unobserved_shaping:g}"] * (config.learner.unobserved_shaping > 0)
    extra += ["stop when complete"] * config.stop_when_complete
    extra += [f"sizes N^-{config.size_draw_power:g}"] * (config.size_draw_power > 0)
    extra += [f"{config.learner.poi_order} POIs first"] * (config.learner.poi_order != "nearest")
    margin = f" from {config.learner.trap_margin:g} off" if config.learner.trap_margin else ""
    extra += [f"trap shaping {config.learner.trap_shaping:g}{margin}"] * (config.learner.trap_shaping > 0)
    hidden = config.learner.hidden
    extra += [f"{len(hidden)} x {hidden[0]}" if len(set(hidden)) == 1 else f"hidden {hidden}"] * (
        hidden != PRESETS["anysize"].learner.hidden
    )
    decay = f" to 0 over {config.ppo.teacher_episodes / 1000:g}k" if config.ppo.teacher_episodes else ""
    extra += [f"teacher {config.ppo.teacher:g}{decay}"] * (config.ppo.teacher > 0)
    extra += ["trained behind the shield"] * config.learner.shield
    algo = config.learner.algo
    return " + ".join(["anysize" if algo == "mappo" else f"{algo} across sizes", *extra])


def specialists(folder: Path, episodes: int, seeds: int, eval_episodes: int) -> list[dict[str, object]]:
    """The anysize network trained on one size each (resumed where a run is there): a row per size."""
    rows = []
    for n in SPECIALIST_SIZES:
        one_size = anysize(episodes, seeds, balance_sizes=False)  # one size: nothing to balance
        config = dataclasses.replace(one_size, scenario=f"paper-{n}", size_curriculum=0)
        run = folder / f"paper-{n}"
        train(config, out=run, resume=(run / CONFIG).exists())
        rows += table(run, eval_episodes, (n,), "anysize specialist")
    return rows


def draw(rows: list[dict[str, object]], path: Path) -> None:
    """The figure: ``rows`` (the one policy) beside its specialists, the earlier runs and the
    best per-size rows of the scale sweeps (every committed table but ``path``'s own)."""
    others = [r for r in read_table(HERE.parent / "swarm" / "score-vs-n.csv") if r["setting"] in BASELINES]
    for extra in (SPECIALISTS, *EARLIER, HERE / "any-size.csv", PRESET):
        others += read_table(extra) if extra.exists() and extra != path.with_suffix(".csv") else []
    figure(rows + others, path)


def draw_contacts(tables: dict[str, list[dict[str, object]]], path: Path) -> None:
    """Trap contacts per episode against N (left, log scale) and as a multiple of the oracle's
    (right), for each labelled table of :func:`table`'s rows (the seeds' mean), beside the
    oracle's (the first table's) and twice the oracle's, issue 44's bound."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(11, 4), dpi=100)
    counts, ratios = fig.subplots(1, 2)
    first = next(iter(tables.values()))
    n = [int(str(r["scenario"]).split("-")[1]) for r in first]
    oracle = np.array([float(r["oracle_trap_contacts"]) for r in first])
    counts.plot(n, oracle, color="black", marker="s", label="oracle")
    counts.plot(n, 2 * oracle, color="grey", linestyle="--", label="twice the oracle's")
    ratios.axhline(2.0, color="grey", linestyle="--", label="twice the oracle's")
    for label, rows in tables.items():
        contacts = np.array([float(r["trap_contacts"]) for r in rows])
        (line,) = counts.plot(n, contacts, marker="o", label=label)
        ratios.plot(n, contacts / oracle, marker="o", color=line.get_color(), label=label)
    for axes in (counts, ratios):
        axes.set_xscale("log", base=2)
        axes.set_xticks(n, [str(k) for k in n])
        axes.set_xlabel("rovers (N)")
        axes.legend(fontsize=8)
    counts.set_yscale("log")
    counts.set_ylabel("trap contacts per episode (mean of the seeds)")
    ratios.set_yscale("log")
    ratios.set_ylabel("trap contacts / the oracle's")
    counts.set_title("1000 deterministic episodes per size, the same layouts", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)


def stress(run: Path, seeds: int, episodes: int, shield: bool = False) -> list[dict[str, object]]:
    """``mission stress`` of the example mission for every seed's policy (and the oracle once):
    success, POIs observed and contacts without and with one random rover failure (``shield``:
    the policies behind the safety layer)."""
    from roverswarm.stress import stress_mission

    rows = []
    for seed in range(seeds):
        out = run / ("stress-shielded" if shield else "stress") / f"seed-{seed}"
        found = stress_mission(MISSION, str(run), out, episodes, policy_seed=seed, shield=shield)
        rows += [r for r in found if r["policy"] != "oracle"]  # named by their seed
    return rows + [r for r in found if r["policy"] == "oracle"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, help="the training run's folder")
    parser.add_argument("--specialists", type=Path, help="train and evaluate the per-size runs in this folder")
    parser.add_argument("--specialist-episodes", type=int, default=20_000, help="training episodes per specialist")
    parser.add_argument("--episodes", type=int, default=PRESETS["anysize"].episodes, help="training episodes per seed")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--eval-episodes", type=int, default=1000)
    parser.add_argument("--evaluate", action="store_true", help="evaluate the run as it stands, train nothing")
    parser.add_argument("--stress-only", action="store_true", help="only mission stress of the run as it stands")
    parser.add_argument("--stress-episodes", type=int, default=500, help="mission stress episodes per seed")
    parser.add_argument("--out", type=Path, default=HERE / "any-size", help="output path without suffix")
    parser.add_argument("--fail-rate", type=float, default=0.0, help="rover failures in training (train --fail-rate)")
    parser.add_argument("--unobserved-shaping", type=float, default=0.0, help="train --unobserved-shaping")
    parser.add_argument(
        "--fail-count", type=int, default=1, help="train --fail-count (rovers lost per failure episode)"
    )
    parser.add_argument("--fail-max-rovers", type=int, default=0, help="train --fail-max-rovers")
    parser.add_argument(
        "--stop-when-complete", action="store_true", help="train --stop-when-complete (training episodes end there)"
    )
    parser.add_argument("--size-draw-power", type=float, default=0.0, help="train --size-draw-power")
    parser.add_argument(
        "--poi-order",
        default=PRESETS["anysize"].learner.poi_order,
        choices=POI_ORDERS,
        help="train --poi-order (default: the preset's)",
    )
    parser.add_argument("--trap-shaping", type=float, default=0.0, help="train --trap-shaping")
    parser.add_argument("--trap-margin", type=float, default=0.0, help="train --trap-margin (with --trap-shaping)")
    parser.add_argument("--hidden", type=int, nargs="+", help="train --hidden (default: the preset's)")
    parser.add_argument("--teacher", type=float, default=0.0, help="train --teacher (rows of their own)")
    parser.add_argument(
        "--shield",
        action="store_true",
        help="the safety layer (rows of their own): train behind it (train --shield); with --evaluate or "
        "--stress-only, evaluate a run trained without it behind it",
    )
    parser.add_argument("--teacher-episodes", type=int, default=0, help="train --teacher-episodes (kickstarting)")
    parser.add_argument(
        "--algo",
        choices=["mappo", "ddpg", "maddpg"],
        default="mappo",
        help="mappo: the anysize preset; else the anysize-ddpg preset with this learner",
    )
    args = parser.parse_args()
    args.out.parent.mkdir(parents=True, exist_ok=True)  # before the training and evaluation it ends
    enable_compilation_cache()
    if args.specialists is not None:
        rows = specialists(args.specialists, args.specialist_episodes, args.seeds, args.eval_episodes)
        earlier = read_table(SPECIALISTS) if SPECIALISTS.exists() else []
        write_csv(SPECIALISTS, [r for r in earlier if r["setting"] != rows[0]["setting"]] + rows)
        draw(read_table(args.out.with_suffix(".csv")), args.out.with_suffix(".png"))
        return
    if args.run is None:
        parser.error("give --run (the one policy) or --specialists")
    if not (args.evaluate or args.stress_only):
        options = (
            "fail_rate",
            "fail_count",
            "unobserved_shaping",
            "fail_max_rovers",
            "stop_when_complete",
            "size_draw_power",
            "poi_order",
            "trap_shaping",
            "trap_margin",
            "teacher",
            "teacher_episodes",
            "shield",
        )
        chosen = {name: getattr(args, name) for name in options}
        chosen.update({"hidden": tuple(args.hidden)} if args.hidden else {})
        if args.algo == "mappo":
            config = anysize(args.episodes, args.seeds, **chosen)
        else:
            config = off_policy(args.algo, args.episodes, args.seeds, **chosen)
        train(config, out=args.run, resume=(args.run / CONFIG).exists())
    if not args.stress_only:
        config = read_config(args.run / CONFIG)
        named = setting(config) + " + shield" * (args.shield and not config.learner.shield)
        rows = table(args.run, args.eval_episodes, setting=named, shield=args.shield)
        write_csv(args.out.with_suffix(".csv"), rows)
        atomic_write(args.out.with_suffix(".md"), lambda f: f.write(markdown(rows)))
        draw(rows, args.out.with_suffix(".png"))
        if args.shield and PRESET.exists():
            own = args.out.with_suffix(".csv").resolve() in {path.resolve() for path in SHIELDED.values()}
            shielded = {label: read_table(path) for label, path in SHIELDED.items() if path.exists()}
            if not own:  # another run's line beside the committed ones, in a figure of its own
                shielded[named] = rows
            where = CONTACTS if own else args.out.with_name(args.out.name + "-contacts.png")
            draw_contacts({"the preset": read_table(PRESET), **shielded}, where)
        print(markdown(rows))
    stressed = stress(args.run, args.seeds, args.stress_episodes, args.shield)
    write_csv(args.out.with_name(args.out.name + "-stress.csv"), stressed)
    for row in stressed:
        print(row["policy"], row["condition"], f"success {row['success']:.2f}", f"POIs {row['pois_observed']:.2f}")


if __name__ == "__main__":
    main()
