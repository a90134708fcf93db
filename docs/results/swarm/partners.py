"""Partners never trained with: every seed's swarm against the swarm whose rover i comes from
seed (s + i) mod S (`roverswarm evaluate --partners other-seeds`), for the runs given, on the
same 1000 deterministic episodes.

    python docs/results/swarm/partners.py docs/results/swarm/partners.csv \\
        results/swarm-scale/runs/paper-{3,4,5}/{swarm,swarm-ddpg}

Writes the CSV (one row per run and partners) and prints it as a Markdown table.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from roverswarm.evaluate import evaluate_run
from roverswarm.runs import Run, markdown_table, write_csv


def main(out: Path, runs: list[Path], episodes: int) -> list[dict[str, object]]:
    rows = []
    for folder in runs:
        run = Run(folder)
        for partners in ("own", "other-seeds"):
            seeds = evaluate_run(folder, episodes, partners=partners)[2:]  # after random and oracle
            scores = np.array([r["normalized_score"] for r in seeds])
            rows.append(
                {
                    "scenario": run.config.scenario,
                    "run": folder.name,
                    "partners": partners,
                    "scores": " / ".join(f"{x:.2f}" for x in scores),
                    "mean_score": float(scores.mean()),
                    "collisions": float(np.mean([r["collisions"] for r in seeds])),
                    "trap_contacts": float(np.mean([r["trap_contacts"] for r in seeds])),
                    "episodes": episodes,
                }
            )
    write_csv(out, rows)
    header = ["scenario", "run", "partners", "score, every seed", "mean", "collisions", "trap contacts"]
    body = [
        [r["scenario"], r["run"], r["partners"], r["scores"], f"{r['mean_score']:.2f}"]
        + [f"{r['collisions']:.2f}", f"{r['trap_contacts']:.2f}"]
        for r in rows
    ]
    print(markdown_table(header, body))
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="the CSV to write")
    parser.add_argument("runs", type=Path, nargs="+", help="run folders of `roverswarm train` (--seeds >= 2)")
    parser.add_argument("--episodes", type=int, default=1000, help="deterministic evaluation episodes per policy")
    args = parser.parse_args()
    main(args.out, args.runs, args.episodes)
