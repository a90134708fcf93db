"""Score against the number of rovers: several sweep tables in one figure and one table.

    python docs/results/swarm/score_vs_n.py                 # the committed tables, below
    python docs/results/swarm/score_vs_n.py A.csv B.csv --out figure-name

Reads sweep tables (``sweep.csv`` of ``roverswarm sweep``), keeps the ``paper-N`` rows,
labels each setting with its training budget ("swarm (60k)") and writes ``OUT.png`` (every
seed's score and the minutes of training per run, by N), ``OUT.csv`` and ``OUT.md``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from roverswarm.experiments.sweep import figure, markdown, read_table
from roverswarm.runs import write_csv
from roverswarm.storage import atomic_write

HERE = Path(__file__).resolve().parent
TABLES = [HERE / "scale.csv", HERE / "targets.csv", HERE / "targets-ddpg.csv", HERE.parent / "ppo" / "ppo-scale.csv"]
COLUMNS = [
    "scenario", "setting", "seeds", "scores", "min_score", "mean_score", "pois_observed",
    "collisions", "trap_contacts", "oracle_trap_contacts", "random_reward", "oracle_reward", "train_minutes",
]  # fmt: skip


def rovers(scenario: str) -> int:
    return int(scenario.removeprefix("paper-"))


def combined(tables: list[Path]) -> list[dict[str, object]]:
    """The ``paper-N`` rows of every table, settings labelled with their budget, sorted by N."""
    rows = []
    for table in tables:
        for row in read_table(table):
            if str(row["scenario"]).startswith("paper-"):
                label = f"{row['setting']} ({float(row['episodes']) / 1000:g}k)"
                rows.append({**{k: row.get(k, "") for k in COLUMNS}, "setting": label})
    return sorted(rows, key=lambda r: rovers(str(r["scenario"])))  # stable: settings keep their order


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tables", nargs="*", type=Path, default=[t for t in TABLES if t.exists()])
    parser.add_argument("--out", type=Path, default=HERE / "score-vs-n", help="output path without suffix")
    args = parser.parse_args()
    rows = combined(args.tables)
    if not rows:
        parser.error(f"no paper-N rows in {', '.join(map(str, args.tables)) or 'no tables'}")
    write_csv(args.out.with_suffix(".csv"), rows)
    atomic_write(args.out.with_suffix(".md"), lambda f: f.write(markdown(rows)))
    figure(rows, args.out.with_suffix(".png"))
    print(f"{len(rows)} rows -> {args.out}.png, .csv, .md")


if __name__ == "__main__":
    main()
