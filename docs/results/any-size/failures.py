"""Rover loss beyond one failure on one mission: both example missions, one and two rovers failing.

    python docs/results/any-size/failures.py --run runs/anysize-uncrossed --run runs/anysize-shield-fail:shield \
        --run runs/anysize-stop-fail
    python docs/results/any-size/failures.py --mission examples/outpost.yaml --failures 1,2,3 \
        --run runs/anysize-uncrossed --out docs/results/any-size/failures-outpost

``mission stress`` (500 episodes, seed 0, the same starts and failures for every policy) of
``examples/mission.yaml`` (3 rovers from fixed starts, 3 POIs) and ``examples/survey.yaml`` (3
rovers released in a zone, 6 POIs: each rover must observe two, so a failure leaves two rovers
three POIs each at worst), with one and with two random rover failures, for every seed of each
run beside the oracle. A run is driven as it is and behind the safety layer; ``RUN:shield``
only behind it (a run trained behind the layer). ``--mission`` (repeatable) and ``--failures``
measure other missions and failure counts. Writes ``failures.csv`` and ``failures.md``.

``--failed-margin M`` (a probe) sets the clearance that the oracle's steering and the safety
layer keep from a failed rover's edge (``roverswarm.steering.FAILED_MARGIN``, 0.03) for the
whole measurement; minus the two bodies' radii (-0.3 for rovers of radius 0.15) makes a
failed rover no obstacle to them, so a working rover may push against it to observe a POI
beneath it, as the trained policies do.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from any_size import MISSION  # the script beside this one

import roverswarm.steering
from roverswarm.env.missions import load_mission
from roverswarm.errors import UserError
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.mission import load_policy
from roverswarm.policies import ORACLE
from roverswarm.runs import Run, write_csv
from roverswarm.storage import atomic_write
from roverswarm.stress import check_failures, condition, stress_rows

HERE = Path(__file__).resolve().parent
MISSIONS = (MISSION, MISSION.parent / "survey.yaml")
EPISODES = 500


def measure(
    runs: list[tuple[Path, tuple[bool, ...]]],
    missions: tuple[Path, ...] = MISSIONS,
    counts: tuple[int, ...] = (1, 2),
    episodes: int = EPISODES,
) -> list[dict[str, object]]:
    """One row per mission, failure count and policy: the oracle, then every run, layer and seed."""
    rows = []
    for path in missions:
        mission = load_mission(path)
        policies, names = [ORACLE], [("oracle", False)]
        for run, layers in runs:
            for shield in layers:
                for seed in range(Run(run).config.seeds):
                    policies.append(load_policy(str(run), mission, seed, shield))
                    names.append((run.name, shield))
        for failures in counts:
            found, _ = stress_rows(policies, mission, episodes, seed=0, failures=failures)
            for (run, shield), clean, failed in zip(names, found[::2], found[1::2]):
                rows.append(
                    {
                        "mission": path.name,
                        "failures": failures,
                        "run": run,
                        "shield": shield,
                        "policy": failed["policy"],
                        "success_clean": clean["success"],
                        **{
                            k: failed[k]
                            for k in ("success", "time_to_all", "pois_observed", "collisions", "trap_contacts")
                        },
                    }
                )
                print(*(f"{v:.3f}" if isinstance(v, float) else v for v in rows[-1].values()), flush=True)
    return rows


def markdown(rows: list[dict[str, object]], command: str, episodes: int = EPISODES, margin: float | None = None) -> str:
    """One line per mission, failure count, run and layer: every seed's success beside the
    oracle's; ``command`` reruns it; ``margin``: the probe's clearance from a failed rover."""
    missions = sorted({str(r["mission"]) for r in rows})
    named = "both example missions" if missions == sorted(p.name for p in MISSIONS) else ", ".join(missions)
    probe = "" if margin is None else f"; the oracle's and the layer's clearance from a failed rover {margin:g}"
    lines = [
        f"# Rover loss on {named} ({episodes} episodes per row, seed 0{probe})",
        "",
        "Success with the failures (every seed; without any failure in brackets where below 100%), "
        "then the seeds' mean POIs observed, collisions and trap contacts. "
        f"Rerun: `{command}`.",
        "",
        "| mission | rovers failing | policy | success, every seed | POIs observed | collisions | trap contacts |",
        "|---|---|---|---|---|---|---|",
    ]
    groups: dict[tuple, list[dict[str, object]]] = {}
    for r in rows:
        groups.setdefault((r["mission"], r["failures"], r["run"], r["shield"]), []).append(r)
    for (mission, failures, run, shield), group in groups.items():
        seeds = " / ".join(
            f"{r['success']:.1%}" + (f" ({r['success_clean']:.1%})" if r["success_clean"] < 1 else "") for r in group
        )
        mean = {k: sum(r[k] for r in group) / len(group) for k in ("pois_observed", "collisions", "trap_contacts")}
        name = f"{run}, behind the layer" if shield else run
        lines.append(
            f"| {mission} | {condition(failures)} | {name} | {seeds} | {mean['pois_observed']:.2f} "
            f"| {mean['collisions']:.2f} | {mean['trap_contacts']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def counts(text: str) -> tuple[int, ...]:
    """``--failures``: counts of at least 1, comma-separated."""
    try:
        found = tuple(int(k) for k in text.split(","))
    except ValueError:
        found = ()
    if not found or min(found) < 1:
        raise argparse.ArgumentTypeError(f"expected counts >= 1, comma-separated, such as 1,2,3; got '{text}'")
    return found


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", action="append", required=True, help="a run folder; RUN:shield: only behind the layer")
    parser.add_argument("--mission", type=Path, action="append", help="a mission file (default: both examples)")
    parser.add_argument("--failures", type=counts, default=(1, 2), help="failure counts, comma-separated")
    parser.add_argument("--out", type=Path, default=HERE / "failures")
    parser.add_argument("--failed-margin", type=float, help="probe: the steering's clearance from a failed rover")
    args = parser.parse_args()
    enable_compilation_cache()
    if args.failed_margin is not None:  # read when the steering is traced, so before any rollout
        roverswarm.steering.FAILED_MARGIN = args.failed_margin
    runs = [
        (Path(spec.removesuffix(":shield")), (True,) if spec.endswith(":shield") else (False, True))
        for spec in args.run
    ]
    missions = tuple(args.mission) if args.mission else MISSIONS
    for path in missions:  # before any rollout: a count the smallest mission cannot lose is refused
        try:
            check_failures(max(args.failures), load_mission(path).params.num_rovers)
        except UserError as error:
            parser.error(f"{path}: {error}")
    rows = measure(runs, missions, args.failures)
    write_csv(args.out.with_suffix(".csv"), rows)
    chosen = [f"--mission {path}" for path in args.mission or ()]
    chosen += [f"--failures {','.join(map(str, args.failures))}"] * (args.failures != (1, 2))
    chosen += [f"--run {spec}" for spec in args.run]
    chosen += [f"--failed-margin {args.failed_margin:g}"] * (args.failed_margin is not None)
    chosen += [f"--out {args.out}"] * (args.out.resolve() != (HERE / "failures").resolve())
    command = " ".join(["python docs/results/any-size/failures.py", *chosen])
    markdown_text = markdown(rows, command, margin=args.failed_margin)
    atomic_write(args.out.with_suffix(".md"), lambda f: f.write(markdown_text))


if __name__ == "__main__":
    main()
