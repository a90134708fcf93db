"""Extending a run: `train --resume RUN --episodes M`, against a run trained to M at once."""

from __future__ import annotations

import dataclasses
import shutil
import signal
import time
from types import SimpleNamespace

import numpy as np
import pytest
from rich.console import Console

from roverswarm import trainer
from roverswarm.cli import main
from roverswarm.config import with_options
from roverswarm.errors import RunStopped
from roverswarm.experiments.arms import GridRun, status
from roverswarm.experiments.live import Summary
from roverswarm.learners import FAMILIES
from roverswarm.runs import CHECKPOINT, CONFIG, Run, read_metrics
from roverswarm.storage import trained_episodes
from roverswarm.trainer import train


def timeless(rows: list[dict]) -> list[dict]:
    """Metrics rows without their wall-clock seconds."""
    return [{k: v for k, v in r.items() if k != "wall_seconds"} for r in rows]


REPLAYS = {
    "uniform": {},
    # the ranked replay, partitioned for policy ensembles, with tables re-ranked before the
    # interruption, and importance weights whose exponent rises over the run's length (the
    # one schedule an extension stretches)
    "ranked-partitions": {
        "replay": "ranked",
        "ensemble": 2,
        "refresh_every": 5,
        "importance_weights": True,
        "importance_exponent": 0.5,
    },
}


def interrupted(config, out, signal_at_chunk) -> None:
    """Train ``config`` in ``out`` and stop it after its first chunk (a checkpoint with the replay)."""
    disarm = signal_at_chunk(signal.SIGINT, chunk=1)
    with pytest.raises(RunStopped, match=f"interrupted at episode {config.log_every}"):
        train(config, out=out, progress=False)
    disarm()


@pytest.mark.parametrize("replay", REPLAYS)
def test_an_interrupted_run_extended_equals_one_trained_to_the_new_length_at_once(
    replay, tiny_config, tmp_path, signal_at_chunk, monkeypatch
):
    """200 episodes interrupted at 100, then extended to 300: the metrics of a 300-episode run,
    though the replay grows from 5000 to 7500 transitions (capped at each length's own) and
    the noise decays over 250 episodes (an absolute count, across the extension). With
    importance weights, each chunk used the exponent of the length the run had when it ran:
    the first 200's, then 300's; a run whose first chunk is told 200 episodes gives them."""
    options = {**REPLAYS[replay], "buffer_size": 50_000, "noise_std": 0.3, "noise_final": 0.05}
    longer = with_options(tiny_config, {**options, "noise_decay_episodes": 250, "episodes": 300})
    interrupted(dataclasses.replace(longer, episodes=200), tmp_path, signal_at_chunk)
    assert main(["train", "--resume", str(tmp_path), "--episodes", "300"]) == 0
    extended = timeless(read_metrics(tmp_path / "metrics.csv"))
    at_once = timeless(train(longer, progress=False).metrics)
    if replay == "uniform":
        assert extended == at_once
        return
    family, lengths = FAMILIES["maddpg"], []

    def told(program, params, runner, total):  # the first chunk is told the run's first length
        lengths.append(200 if not lengths else int(total))
        return family.run_chunk(program, params, runner, np.int32(lengths[-1]))

    monkeypatch.setitem(FAMILIES, "maddpg", dataclasses.replace(family, run_chunk=told))
    assert extended == timeless(train(longer, progress=False).metrics) and lengths == [200, 300, 300]
    assert extended != at_once


@pytest.fixture(scope="module")
def finished(tiny_config, tmp_path_factory):
    """A finished 200-episode run (its checkpoint keeps no replay), and the same extended to 300."""
    base = tmp_path_factory.mktemp("finished")
    config = dataclasses.replace(tiny_config, episodes=200)
    train(config, out=base / "run", progress=False)
    with np.load(base / "run" / CHECKPOINT) as data:
        updates = int(data["updates"])
    train(dataclasses.replace(config, episodes=300), out=base / "run", resume=True, progress=False)
    return config, base / "run", updates


def test_a_finished_run_extended_warms_its_emptied_replay_up_again(finished, tiny_config):
    """The final checkpoint keeps no replay, so the extension starts from an empty one: no
    update until it holds --warmup transitions again (5 of the chunk's 25 iterations of 4
    environments x 25 steps), then the updates of every iteration (4); the metrics rows of
    the first 200 episodes are kept, the next ones continue the file."""
    config, run, updates = finished
    with np.load(run / CHECKPOINT) as data:
        assert int(data["episodes"]) == 300 and not any(k.startswith("buffer/") for k in data.files)
        iterations, per_iteration = 100 // config.num_envs, config.num_envs * 25 // config.update_every
        skipped = -(-config.warmup // (config.num_envs * 25)) - 1  # the iteration that reaches it updates
        assert int(data["updates"]) - updates == (iterations - skipped) * per_iteration
    rows = read_metrics(run / "metrics.csv")
    first = timeless(train(config, progress=False).metrics)
    assert timeless(rows[: len(first)]) == first
    assert [r["episodes"] for r in rows] == [e for e in (100, 200, 300) for _ in range(config.seeds)]
    assert [r["seed"] for r in rows] == [0, 1] * 3


def test_an_extension_lost_before_its_first_checkpoint_leaves_the_run_as_it_was(finished, tmp_path, monkeypatch):
    """config.json was rewritten with the new --episodes before the extension's first
    checkpoint: one lost before it (a killed process, a lost machine) left a finished run that
    `export` and the sweeps took for an unfinished one. It is written with that checkpoint."""
    config, run, _ = finished
    copy = tmp_path / "run"
    shutil.copytree(run, copy)
    before = (copy / CONFIG).read_text()

    def lost(*args):
        raise RuntimeError("the machine was lost")

    monkeypatch.setitem(
        FAMILIES, config.learner.algo, dataclasses.replace(FAMILIES[config.learner.algo], run_chunk=lost)
    )
    with pytest.raises(RuntimeError, match="the machine was lost"):
        train(dataclasses.replace(config, episodes=500), out=copy, resume=True, progress=False)
    assert (copy / CONFIG).read_text() == before
    assert Run(copy).config.episodes == trained_episodes(copy / CHECKPOINT) == 300


def test_an_on_policy_run_extended_equals_one_trained_to_the_new_length_at_once(tiny_ppo_config, tmp_path, capsys):
    """MAPPO keeps no replay and its schedules count absolute episodes (here the learning rates
    decay to 0 over 400 episodes): a finished 200-episode run extended to 400 is the 400-episode
    run. Extended past the horizon (500), it is refused: those episodes would train at rate 0."""
    config = with_options(tiny_ppo_config, {"anneal_episodes": 400, "episodes": 200})
    train(config, out=tmp_path, progress=False)
    assert main(["train", "--resume", str(tmp_path), "--episodes", "400"]) == 0
    at_once = train(dataclasses.replace(config, episodes=400), progress=False)
    assert timeless(read_metrics(tmp_path / "metrics.csv")) == timeless(at_once.metrics)
    before = (tmp_path / "metrics.csv").read_text()
    assert main(["train", "--resume", str(tmp_path), "--episodes", "500"]) == 2
    err = capsys.readouterr().err
    assert "--episodes 500 goes past --anneal-episodes 400" in err and err.count("\n") == 1, err
    assert (tmp_path / "metrics.csv").read_text() == before


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--episodes", "200"], "--episodes 200 is below the 300 episodes this run has trained per seed"),
        (["--episodes", "2.5"], "--episodes must be an integer, got '2.5'"),
        (["--episodes", "x"], "--episodes must be an integer, got 'x'"),
        (["--episodes", "350"], "--episodes (350) must be a multiple of --log-every (100)"),
        (["--episodes", "0"], "--episodes must be >= 1, got 0"),
        (["--episodes", str(2**31)], "--episodes must be below 2^31"),
        (["--episodes", "400", "--batch-size", "32"], "--resume: the run has batch_size=64, not 32"),
    ],
)
def test_a_bad_extension_is_one_line_and_exit_2(finished, argv, message, capsys):
    _, run, _ = finished
    before = (run / "metrics.csv").read_text()
    assert main(["train", "--resume", str(run), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert (run / "metrics.csv").read_text() == before and "300" in (run / "config.json").read_text()


@pytest.mark.parametrize("family", ["maddpg", "mappo"])
def test_a_run_ends_at_its_budget_and_a_larger_budget_continues_it(
    family, tiny_config, tiny_ppo_config, tmp_path, monkeypatch, capsys
):
    """On a clock where every chunk takes 30 s, --budget-minutes 1 ends a 400-episode run after
    two chunks (200 episodes, with its replay), which a sweep counts as done; resuming it with
    the spent budget is one line and exit 2 and changes nothing in the folder; --budget-minutes
    1.5 adds one chunk (the minutes count over both sessions); 2 then continues it to the
    numbers of the run trained at once."""
    config = tiny_config if family == "maddpg" else tiny_ppo_config
    config = dataclasses.replace(config, episodes=4 * config.log_every, budget_minutes=1.0)
    clock = iter(range(0, 10_000, 30))
    fake = SimpleNamespace(perf_counter=lambda: next(clock), monotonic=time.monotonic, sleep=time.sleep)
    monkeypatch.setattr(trainer, "time", fake)

    def trained() -> int:
        with np.load(tmp_path / CHECKPOINT) as data:
            return int(data["episodes"])

    train(config, out=tmp_path, progress=False)
    assert trained() == 2 * config.log_every
    with np.load(tmp_path / CHECKPOINT) as data:
        assert any(k.startswith("buffer/") for k in data.files) == (family == "maddpg")
    run = GridRun("paper-2", family, config, tmp_path)
    assert status(run) == "done"  # a sweep keeps it as it is, and its live table says how far it went
    console = Console(record=True, width=100)
    console.print(Summary([run], {run.name}))
    assert f"{2 * config.log_every}/{config.episodes}" in console.export_text()
    files = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    before = {name: (tmp_path / name).read_bytes() for name in ("config.json", "metrics.csv")}
    for more in ([], ["--episodes", "800"]):
        capsys.readouterr()
        assert main(["train", "--resume", str(tmp_path), *more]) == 2
        err = capsys.readouterr().err
        assert "the run has spent its budget (1 of --budget-minutes 1)" in err and err.count("\n") == 1, err
    assert {name: (tmp_path / name).read_bytes() for name in before} == before
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == files
    assert main(["train", "--resume", str(tmp_path), "--budget-minutes", "1.5"]) == 0
    assert trained() == 3 * config.log_every
    assert main(["train", "--resume", str(tmp_path), "--budget-minutes", "2"]) == 0
    at_once = train(dataclasses.replace(config, budget_minutes=0.0), progress=False)
    assert timeless(read_metrics(tmp_path / "metrics.csv")) == timeless(at_once.metrics)
