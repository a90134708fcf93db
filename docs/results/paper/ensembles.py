"""The paper's policy ensembles on their own: plain MADDPG with K = 3 sub-policies per agent
(part reference-k3 of second-pass.sh) against K = 1 (part reference-k1), at every N both
parts ran (N = 4 and 5), the same seeds, settings and budget (20,000 episodes, 5 seeds, the
reference preset).

    python docs/results/paper/ensembles.py results/paper-second-pass

Writes docs/results/paper/second-pass/ensembles.csv (or --csv) and prints it as a Markdown
table. Each reading is compared unpaired (Welch interval and test): K changes every network's
initialisation, so seed s of one part is not a matched copy of seed s of the other.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from roverswarm.config import config_from_json
from roverswarm.env.scenarios import get_scenario
from roverswarm.experiments.arms import GridRun
from roverswarm.experiments.results import TIMING, load
from roverswarm.experiments.significance import relative_change
from roverswarm.experiments.sweep import evaluation, read_table
from roverswarm.runs import CONFIG, markdown_table, write_csv

PARTS = {1: "reference-k1", 3: "reference-k3"}


def readings(part: Path, scenario: str, eval_episodes: int) -> dict[str, np.ndarray]:
    """Plain MADDPG's per-seed readings in one part at one scenario."""
    folder = part / "runs" / scenario / "maddpg"
    run = GridRun(scenario, "maddpg", config_from_json((folder / CONFIG).read_text()), folder)
    result = load(run, {})
    seeds = [r for r in evaluation(run, eval_episodes) if r["policy"] not in ("random", "oracle")]
    timed = [
        r["seconds_per_1000"] for r in read_table(part / TIMING) if (r["scenario"], r["arm"]) == (scenario, "maddpg")
    ]
    return {
        "max mean episode reward": result.best,
        "last-window reward": result.last,
        "deterministic score": np.array([r["normalized_score"] for r in seeds]),
        "trap contacts": np.array([r["trap_contacts"] for r in seeds]),
        "s / 1000 episodes": np.array(timed),
    }


def main(out: Path, csv: Path, eval_episodes: int) -> list[dict[str, object]]:
    rows = []
    ran = [{p.parent.name for p in (out / PARTS[k] / "runs").glob("*/maddpg")} for k in PARTS]
    for scenario in sorted(set.intersection(*ran), key=lambda s: get_scenario(s).num_rovers):
        n = get_scenario(scenario).num_rovers
        k1, k3 = (readings(out / PARTS[k], scenario, eval_episodes) for k in (1, 3))
        for name in k1:
            change, low, high, p = relative_change(k3[name], k1[name])
            rows.append(
                {
                    "rovers": n,
                    "reading": name,
                    "k1": float(k1[name].mean()),
                    "k3": float(k3[name].mean()),
                    "change_pct": change,
                    "ci_low": low,
                    "ci_high": high,
                    "p": p,
                }
            )
    write_csv(csv, rows)
    header = ["N", "reading", "K = 1", "K = 3", "change (K = 3 vs 1)", "95% CI", "p"]
    body = [
        [
            str(r["rovers"]),
            str(r["reading"]),
            f"{r['k1']:.2f}",
            f"{r['k3']:.2f}",
            f"{r['change_pct']:+.1f}%",
            f"[{r['ci_low']:+.1f}, {r['ci_high']:+.1f}]",
            f"{r['p']:.2g}",
        ]
        for r in rows
    ]
    print(markdown_table(header, body))
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="second-pass.sh's output folder (holding reference-k1/, reference-k3/)")
    parser.add_argument("--csv", type=Path, default=Path(__file__).parent / "second-pass" / "ensembles.csv")
    parser.add_argument("--eval-episodes", type=int, default=1000, help="deterministic evaluation episodes")
    args = parser.parse_args()
    main(args.out, args.csv, args.eval_episodes)
