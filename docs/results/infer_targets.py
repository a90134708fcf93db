"""Inferred policies with target approximations (paper eq. 8's primes) on paper-3, beside plain
MADDPG trained anew by the same code: 3 seeds, 30,000 episodes each, 1000 deterministic
evaluation episodes (the same layouts for every policy). Resumes an interrupted run.

    python docs/results/infer_targets.py --out runs/infer-targets

Writes docs/results/ensembles-paper-3-targets.csv (docs/extensions.md#inferred-policies).
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from roverswarm.config import TrainConfig
from roverswarm.evaluate import evaluate_run
from roverswarm.runs import CHECKPOINT, write_csv
from roverswarm.storage import trained_episodes
from roverswarm.trainer import train

RUNS = {
    "plain MADDPG": {},
    "--infer-policies, target approximations (--infer-window 10000)": {"infer_policies": True},
}
COLUMNS = ("run", "policy", "episode_reward", "normalized_score", "collisions", "trap_contacts", "pois_observed")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("runs/infer-targets"))
    parser.add_argument("--table", type=Path, default=Path(__file__).parent / "ensembles-paper-3-targets.csv")
    args = parser.parse_args()
    base = TrainConfig(scenario="paper-3", seeds=3, episodes=30_000)
    rows = []
    for index, (name, options) in enumerate(RUNS.items()):
        folder = args.out / ("plain" if index == 0 else "infer")
        config = dataclasses.replace(base, learner=dataclasses.replace(base.learner, **options))
        started = (folder / CHECKPOINT).exists()
        if not started or trained_episodes(folder / CHECKPOINT) < config.episodes:
            train(config, out=folder, resume=started, progress=True)
        for row in evaluate_run(folder, episodes=1000):
            if row["policy"] not in ("random", "oracle") or index == 0:
                rows.append({"run": name if row["policy"].startswith("maddpg") else row["policy"], **row})
    write_csv(args.table, [{k: r[k] for k in COLUMNS} for r in rows], list(COLUMNS))


if __name__ == "__main__":
    main()
