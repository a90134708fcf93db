"""The paper's policy ensembles on their own: plain MADDPG with K = 3 sub-policies per agent
(part reference-k3 of second-pass.sh) against K = 1 (part reference-k1), at N = 4 and 5, the
same seeds, settings and budget (20,000 episodes, 5 seeds, the reference preset).

    python docs/results/paper/ensembles.py results/paper-second-pass

Writes docs/results/paper/second-pass/ensembles.csv and prints it as a Markdown table. Each
reading is compared unpaired (Welch interval and test): K changes every network's
initialisation, so seed s of one part is not a matched copy of seed s of the other.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from roverswarm.config import config_from_json
from roverswarm.experiments.grid import GridRun
from roverswarm.experiments.paper import TIMING, load, relative_change
from roverswarm.experiments.sweep import evaluation, read_table
from roverswarm.runs import CONFIG, markdown_table, write_csv

PARTS = {1: "reference-k1", 3: "reference-k3"}
EVAL_EPISODES = 1000


def readings(part: Path, scenario: str) -> dict[str, np.ndarray]:
    """Plain MADDPG's per-seed readings in one part at one scenario."""
    folder = part / "runs" / scenario / "maddpg"
    run = GridRun(scenario, "maddpg", config_from_json((folder / CONFIG).read_text()), folder)
    result = load(run, {})
    seeds = [r for r in evaluation(run, EVAL_EPISODES) if r["policy"] not in ("random", "oracle")]
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


def main(out: Path) -> list[dict[str, object]]:
    rows = []
    for n in (4, 5):
        k1, k3 = (readings(out / PARTS[k], f"paper-{n}") for k in (1, 3))
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
    write_csv(Path(__file__).parent / "second-pass" / "ensembles.csv", rows)
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
    if len(sys.argv) != 2:
        sys.exit("usage: python docs/results/paper/ensembles.py SECOND_PASS_OUT")
    main(Path(sys.argv[1]))
