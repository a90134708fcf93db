"""A probe of the anysize preset: one changed setting, 2 seeds, a short run, a quick evaluation.

    python docs/results/any-size/probe.py --name lead20k --episodes 20000
    python docs/results/any-size/probe.py --name cur20k --episodes 20000 --set '{"size_curriculum": 10000}'
    python docs/results/any-size/probe.py --name mix25 --episodes 20000 --sizes 2,3,5 --set '{"scenario": "paper-2..5"}'
    python docs/results/any-size/probe.py --name fail60k --episodes 60000 --stress --set '{"fail_rate": 0.5}'
    python docs/results/any-size/probe.py --name matd3 --preset swarm --set '{"scenario": "paper-2..10", ...}'

``--set`` is JSON: top-level fields of the config, ``learner.*`` and ``ppo.*`` fields. Trains
into ``--runs/NAME`` (resumed if there), evaluates every seed at ``--sizes`` (300 episodes per
policy by default, the same layouts for random, the oracle and every seed) and appends one
line to ``--log``: every seed's normalised score per size, and the mean trap contacts beside
the oracle's; with ``--stress``, also every seed's success on ``mission stress`` of the example
mission without and with one rover failure (500 episodes each, beside the oracle's);
``--shield`` evaluates both behind the safety layer. A probe ranks settings; it is not a
result (2 seeds, 300 episodes).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from any_size import anysize, stress  # the script beside this one

from roverswarm import train
from roverswarm.evaluate import evaluate_run
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.presets import PRESETS
from roverswarm.runs import CONFIG


def configured(overrides: dict, episodes: int, seeds: int, preset: str = "anysize"):
    """The anysize preset for ``episodes`` (its learning rates annealed over them), or another
    ``preset``, with ``overrides`` (``learner.x`` / ``ppo.x`` / top-level names)."""
    if preset == "anysize":
        base = anysize(episodes, seeds)
    else:
        base = dataclasses.replace(PRESETS[preset], episodes=episodes, seeds=seeds)
    top = {k: v for k, v in overrides.items() if "." not in k}
    part = lambda prefix: {  # noqa: E731
        k.split(".", 1)[1]: tuple(v) if isinstance(v, list) else v for k, v in overrides.items() if k.startswith(prefix)
    }
    return dataclasses.replace(
        base,
        **top,
        learner=dataclasses.replace(base.learner, **part("learner.")),
        ppo=dataclasses.replace(base.ppo, **part("ppo.")),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--name", required=True)
    parser.add_argument("--episodes", type=int, default=20_000)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--sizes", default="2,3,5,8,12")
    parser.add_argument("--eval-episodes", type=int, default=300)
    parser.add_argument("--set", default="{}", help="JSON of the changed settings")
    parser.add_argument("--preset", default="anysize", choices=sorted(PRESETS), help="the settings changed")
    parser.add_argument("--runs", type=Path, default=Path("runs/probes"))
    parser.add_argument("--log", type=Path, default=Path("runs/probes/probes.txt"))
    parser.add_argument("--stress", action="store_true", help="also mission stress of the example mission")
    parser.add_argument("--shield", action="store_true", help="evaluate behind the safety layer (evaluate --shield)")
    args = parser.parse_args()
    enable_compilation_cache()
    out = args.runs / args.name
    start = time.time()
    config = configured(json.loads(args.set), args.episodes, args.seeds, args.preset)
    train(config, out=out, resume=(out / CONFIG).exists(), progress=False)
    minutes = (time.time() - start) / 60
    sizes: dict[str, dict] = {}
    for row in evaluate_run(out, args.eval_episodes, scenario="paper-" + args.sizes, shield=args.shield):
        size = sizes.setdefault(row["scenario"][len("paper-") :], {"scores": [], "traps": []})
        if row["policy"] == "oracle":
            size["oracle_traps"] = row["trap_contacts"]
        elif row["policy"] != "random":
            size["scores"].append(f"{row['normalized_score']:.2f}")
            size["traps"].append(row["trap_contacts"])
    shielded = ", evaluated behind the safety layer" * args.shield
    line = f"{args.name} ({args.episodes} ep, {minutes:.1f} min training{shielded}): " + " | ".join(
        f"{n}: {'/'.join(s['scores'])} tr {np.mean(s['traps']):.2f} ({s['oracle_traps']:.2f})" for n, s in sizes.items()
    )
    if args.stress:
        success: dict[str, list[str]] = {}
        for row in stress(out, args.seeds, 500, args.shield):
            success.setdefault(str(row["condition"]), []).append(f"{row['success']:.2f}")  # every seed, then the oracle
        line += " || stress " + "; ".join(f"{c}: {'/'.join(v[:-1])} (oracle {v[-1]})" for c, v in success.items())
    print(line)
    args.log.parent.mkdir(parents=True, exist_ok=True)
    with open(args.log, "a") as log:
        log.write(f"{line}  {args.set}\n")


if __name__ == "__main__":
    main()
