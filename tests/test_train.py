"""The trainer: outputs, determinism, resume after SIGKILL and Ctrl-C, divergence, bad input, learning."""

from __future__ import annotations

import csv
import dataclasses
import errno
import json
import math
import os
import shutil
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from tensorboardX.proto.event_pb2 import Event, SessionLog

import roverswarm.limits as limits
import roverswarm.trainer as trainer_module
from roverswarm.cli import main
from roverswarm.config import TrainConfig, config_from_json, config_to_json, validate, with_options
from roverswarm.env import get_scenario
from roverswarm.errors import RunStopped, UserError
from roverswarm.evaluate import evaluate_run
from roverswarm.learners import FAMILIES, offpolicy
from roverswarm.learners.offpolicy import run_buffer
from roverswarm.policies import ORACLE
from roverswarm.presets import REFERENCE, SWARM
from roverswarm.runs import CHECKPOINT, LOCK, METRICS, Run, folder_lock, read_metrics, write_csv
from roverswarm.storage import atomic_write, trained_episodes
from roverswarm.trainer import checkpoint_due, train

TIMELESS = lambda rows: [{k: v for k, v in r.items() if k != "wall_seconds"} for r in rows]  # noqa: E731


def cli_args(config: TrainConfig) -> list[str]:
    """The `roverswarm train` flags that reproduce ``config``."""
    args = []
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        flag = f.name.replace("_", "-")
        if f.name == "mission_text":  # kept by training, not an option
            continue
        if f.name in ("learner", "buffer", "ppo"):
            args += cli_args(value)
        elif isinstance(value, bool):
            args.append(f"--{flag}" if value else f"--no-{flag}")
        elif isinstance(value, tuple):
            args += [f"--{flag}", *map(str, value)]
        else:
            args += [f"--{flag}", str(value)]
    return args


@pytest.fixture(scope="module")
def unbroken(tiny_config, tmp_path_factory):
    out = tmp_path_factory.mktemp("unbroken")
    return train(tiny_config, out=out, progress=False)


def test_outputs_of_a_run(unbroken, tiny_config):
    out = unbroken.out
    assert config_from_json((out / "config.json").read_text()) == tiny_config
    rows = read_metrics(out / "metrics.csv")
    chunks = tiny_config.episodes // tiny_config.log_every
    assert len(rows) == chunks * tiny_config.seeds
    assert [r["episodes"] for r in rows[:: tiny_config.seeds]] == [100.0 * (c + 1) for c in range(chunks)]
    for column in (
        "episode_reward",
        "agent_0_reward",
        "agent_1_reward",
        "collisions",
        "trap_contacts",
        "coverage_distance",
        "wall_seconds",
    ):
        assert column in rows[0]
    for r in rows:  # the episode reward is the sum of the agents' rewards
        assert r["episode_reward"] == pytest.approx(r["agent_0_reward"] + r["agent_1_reward"], rel=1e-4)
    assert (out / "learning_curve.png").stat().st_size > 1000
    assert any(p.name.startswith("events") for p in (out / "tb").iterdir())
    assert (out / CHECKPOINT).exists() and not list(out.glob("*.tmp"))
    with np.load(out / CHECKPOINT) as data:  # a finished run keeps its networks, not its replay
        assert any(k.startswith("learner/actor/") for k in data.files)
        assert not any(k.startswith("buffer/") for k in data.files)
    again = train(tiny_config, out=out, resume=True, progress=False)  # nothing left to do
    assert TIMELESS(again.metrics) == TIMELESS(unbroken.metrics)


def test_same_seed_same_numbers_different_seeds_different_networks(unbroken, tiny_config):
    again = train(tiny_config, progress=False)
    assert TIMELESS(again.metrics) == TIMELESS(unbroken.metrics)
    seed0, seed1 = (jax.tree.map(lambda x: np.asarray(x[s]), unbroken.learner.actor) for s in (0, 1))
    assert not all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(seed0), jax.tree.leaves(seed1)))


SWARM_OPTIONS = dict(
    share_parameters=True,
    twin_critics=True,
    target_noise=0.2,
    actor_delay=2,
    layer_norm=True,
    normalize_obs=True,
    reward_scale=0.5,
)
"""The swarm preset's learner options (and reward scaling) on the tiny config."""


@pytest.mark.parametrize("kind", ["default", "swarm", "mappo"])
def test_resume_after_sigkill_gives_the_numbers_of_an_unbroken_run(tiny_config, tiny_ppo_config, tmp_path, kind):
    """Killed mid-run and resumed, the metrics are the unbroken run's: replay, networks,
    optimisers and (swarm options) the observation normaliser and the update counter, (mappo)
    the value-target statistics, are all in the checkpoint."""
    base, options = {
        "default": (tiny_config, {}),
        "swarm": (tiny_config, SWARM_OPTIONS),
        "mappo": (tiny_ppo_config, {}),
    }[kind]
    out = tmp_path / "killed"
    config = with_options(base, {**options, "episodes": 1000})  # 10 chunks, killed at its first checkpoint
    reference = train(config, progress=False)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    process = subprocess.Popen(
        [sys.executable, "-m", "roverswarm.cli", "train", *cli_args(config), "--out", str(out)],
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.time() + 120
    while not (out / CHECKPOINT).exists() and time.time() < deadline and process.poll() is None:
        time.sleep(0.01)
    process.send_signal(signal.SIGKILL)
    process.wait()
    done = len(read_metrics(out / "metrics.csv")) // config.seeds
    assert 0 < done < config.episodes // config.log_every, "the run must be killed mid-way"
    assert main(["train", "--resume", str(out)]) == 0
    assert TIMELESS(read_metrics(out / "metrics.csv")) == TIMELESS(reference.metrics)
    seeds = [line.split(",")[0] for line in (out / "metrics.csv").read_text().splitlines()[1:]]
    assert seeds == [str(s) for _ in range(config.episodes // config.log_every) for s in range(config.seeds)], (
        "rows rewritten on resume keep integer seeds"
    )


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_ctrl_c_or_sigterm_saves_a_checkpoint_and_resume_finishes(tiny_config, tmp_path, signum):
    """Ctrl-C, or SIGTERM as schedulers and Ray send it: the run checkpoints, stops with exit
    code 1, and resumes to the end."""
    out = tmp_path / "interrupted"
    config = dataclasses.replace(tiny_config, episodes=4000, checkpoint_every=1000)
    process = subprocess.Popen(
        [sys.executable, "-m", "roverswarm.cli", "train", *cli_args(config), "--out", str(out)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.time() + 120
    while not (out / "tb").exists() and time.time() < deadline:
        time.sleep(0.01)
    time.sleep(0.5)
    process.send_signal(signum)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 1, err
    assert "interrupted at episode" in err and "--resume" in err
    assert f"{signal.Signals(signum).name}: stopping after this chunk, with a checkpoint" in " ".join(err.split())
    rows = read_metrics(out / "metrics.csv")
    assert 0 < len(rows) < config.episodes // config.log_every * config.seeds
    assert main(["train", "--resume", str(out)]) == 0
    assert read_metrics(out / "metrics.csv")[-1]["episodes"] == config.episodes


def test_a_run_resumed_by_a_version_with_other_metrics_keeps_its_rows(unbroken, tiny_config, tmp_path, signal_at_chunk):
    """metrics.csv written by a version that had a column since dropped and lacked one since
    added: the resumed run writes every column, NaN where a row has none, and the numbers of a
    run never interrupted (the CSV writer had stopped it with a traceback)."""
    disarm = signal_at_chunk(signal.SIGINT, chunk=2)
    with pytest.raises(RunStopped, match="interrupted at episode 200"):
        train(tiny_config, out=tmp_path, progress=False)
    disarm()
    old = [
        {**{k: v for k, v in r.items() if k != "actor_loss"}, "retired": 1.0} for r in read_metrics(tmp_path / METRICS)
    ]
    write_csv(tmp_path / METRICS, old)
    train(tiny_config, out=tmp_path, resume=True, progress=False)
    rows = read_metrics(tmp_path / METRICS)
    assert set(rows[0]) == set(unbroken.metrics[0]) | {"retired"} and len(rows) == len(unbroken.metrics)
    assert all(math.isnan(r["actor_loss"]) and r["retired"] == 1.0 for r in rows[: len(old)])
    assert all(math.isnan(r["retired"]) for r in rows[len(old) :])
    kept = lambda rs: [{k: v for k, v in r.items() if k not in ("wall_seconds", "retired")} for r in rs]  # noqa: E731
    assert kept(rows[len(old) :]) == kept(unbroken.metrics[len(old) :])


def test_ctrl_c_is_announced_once_and_repeated_still_saves_after_the_chunk(
    unbroken, tiny_config, tmp_path, signal_at_chunk, capsys
):
    """Ctrl-C pressed twice during a chunk: the first is announced (once), the run checkpoints
    after the chunk and stops with exit code 1, and resumes to the numbers of a run never
    interrupted; TensorBoard is told to drop what the stopped session logged past the checkpoint."""
    disarm = signal_at_chunk(signal.SIGINT, chunk=2, times=2)
    try:
        code = main(["train", *cli_args(tiny_config), "--out", str(tmp_path)])
    finally:
        disarm()
    assert code == 1
    err = " ".join(capsys.readouterr().err.split())
    assert err.count("SIGINT: stopping after this chunk, with a checkpoint") == 1, err
    assert "interrupted at episode 200" in err
    assert trained_episodes(tmp_path / CHECKPOINT) == 2 * tiny_config.log_every
    resumed = train(tiny_config, out=tmp_path, resume=True, progress=False)
    assert TIMELESS(resumed.metrics) == TIMELESS(unbroken.metrics)
    starts = [e.step for e in tensorboard_events(tmp_path / "tb") if e.session_log.status == SessionLog.START]
    assert starts == [3 * tiny_config.log_every]


def tensorboard_events(folder: Path) -> list:
    """Every event in ``folder``'s TensorBoard files (records: length, its CRC, the event, its CRC)."""
    events = []
    for path in sorted(folder.glob("events.out.tfevents.*")):
        data, at = path.read_bytes(), 0
        while at < len(data):
            (length,) = struct.unpack("<Q", data[at : at + 8])
            events.append(Event.FromString(data[at + 12 : at + 12 + length]))
            at += 12 + length + 4
    return events


def test_the_logged_rewards_are_those_the_replay_stored(tiny_config, tmp_path, signal_at_chunk):
    """metrics.csv against what the replay holds after the first chunk (stopped there, its
    checkpoint keeps the replay: 100 episodes per seed, all of them stored): each seed's
    agent_i_reward is agent i's stored rewards summed over those episodes, divided by them;
    episode_reward is the sum over the rovers."""
    disarm = signal_at_chunk(signal.SIGINT, chunk=1)
    with pytest.raises(RunStopped, match="interrupted at episode 100"):
        train(tiny_config, out=tmp_path, progress=False)
    disarm()
    with np.load(tmp_path / CHECKPOINT) as data:
        rewards = data["buffer/data/rewards"]  # [S, transitions, N]
    episodes = tiny_config.log_every
    assert rewards.shape[:2] == (tiny_config.seeds, episodes * get_scenario(tiny_config.scenario).max_steps)
    rows = read_metrics(tmp_path / METRICS)
    assert [r["seed"] for r in rows] == list(range(tiny_config.seeds))
    for s, row in enumerate(rows):
        returns = rewards[s].sum(0) / episodes
        np.testing.assert_allclose([row[f"agent_{i}_reward"] for i in range(len(returns))], returns, rtol=1e-4)
        assert row["episode_reward"] == pytest.approx(returns.sum(), rel=1e-4)
        assert abs(returns.sum()) > 1  # rewards that are there to compare


def test_a_checkpoint_is_due_by_chunks_or_once_the_minutes_have_passed(tiny_config):
    config = dataclasses.replace(tiny_config, checkpoint_every=3, checkpoint_minutes=10.0)
    now = time.monotonic()
    assert [checkpoint_due(config, n, now) for n in (1, 2, 3, 6)] == [False, False, True, True]
    assert not checkpoint_due(config, 1, now - 599) and checkpoint_due(config, 1, now - 601)
    assert not checkpoint_due(dataclasses.replace(config, checkpoint_minutes=0.0), 1, now - 10**6)


def test_checkpoint_minutes_save_mid_run_without_changing_the_numbers(unbroken, tiny_config, tmp_path, monkeypatch):
    """With --checkpoint-every beyond the run's end, a tiny --checkpoint-minutes writes a
    checkpoint (with the replay) after every chunk, and 0 only the final one (without it)."""
    original, saves = trainer_module.save_checkpoint, []

    def recorded(path, runner, replay, **kept):
        saves.append(replay)
        original(path, runner, replay=replay, **kept)

    monkeypatch.setattr(trainer_module, "save_checkpoint", recorded)
    chunks = tiny_config.episodes // tiny_config.log_every
    for minutes, expected in ((1e-9, [True] * (chunks - 1) + [False]), (0.0, [False])):
        saves.clear()
        config = dataclasses.replace(tiny_config, checkpoint_every=1000, checkpoint_minutes=minutes)
        result = train(config, out=tmp_path / str(minutes), progress=False)
        assert saves == expected
        assert TIMELESS(result.metrics) == TIMELESS(unbroken.metrics)


@pytest.mark.parametrize("poisoned", ["loss or reward", "network parameters"])
def test_non_finite_losses_stop_the_run_and_keep_the_last_good_checkpoint(poisoned, tiny_config, tmp_path, monkeypatch):
    """A NaN loss, or NaN weights from a chunk's last update (which no loss has seen yet: they
    would have been saved over the last good checkpoint), stop the run before its checkpoint."""
    real = offpolicy.run_chunk
    calls = []

    def poisoning(config, params, runner, total):
        runner, metrics = real(config, params, runner, total)
        calls.append(1)
        if len(calls) == 3 and poisoned == "loss or reward":
            metrics = {**metrics, "critic_loss": metrics["critic_loss"] * np.nan}
        if len(calls) == 3 and poisoned == "network parameters":
            learner = runner.learner.replace(
                actor=jax.tree.map(lambda x: x.at[0].multiply(np.nan), runner.learner.actor)
            )
            runner = runner.replace(learner=learner)
        return runner, metrics

    monkeypatch.setitem(FAMILIES, "maddpg", dataclasses.replace(FAMILIES["maddpg"], run_chunk=poisoning))
    out = tmp_path / "diverged"
    with pytest.raises(RunStopped, match=f"non-finite {poisoned} at episode 300.*last good checkpoint"):
        train(tiny_config, out=out, progress=False)
    with np.load(out / CHECKPOINT) as data:
        assert int(data["episodes"]) == 200
    logged = 2 if poisoned == "loss or reward" else 3  # the third chunk's losses were finite (resume trims them)
    assert len(read_metrics(out / "metrics.csv")) == logged * tiny_config.seeds


RANKED_OPTIONS = dict(
    replay="ranked",
    refresh_every=10,
    reading="schaul",
    alpha=0.7,
    beta=0.0,
    importance_weights=True,
    importance_exponent=0.5,
)
"""The ranked replay in Schaul's 1/rank reading, with importance weights whose exponent rises from 0.5."""


def test_a_resume_holds_one_replay_and_no_host_copy_of_it(tiny_config, tmp_path, monkeypatch):
    """``load_checkpoint`` reads a checkpoint's arrays one at a time, pads the replay back to
    its capacity on the device and lets go of the fresh runner's empty replay array by array:
    numpy's allocations (traced) peak below a tenth of the replay's size, the device arrays
    alive while it places each one below 1.2 replays (it held host copies of the whole
    replay beside the file's arrays, and the empty replay beside the restored one: about three
    replays of memory where a fresh run needs one), and the runner read back is the one saved."""
    import tracemalloc

    import roverswarm.storage as storage
    from roverswarm.config import validate_training

    config = with_options(tiny_config, {"episodes": 20_000, "buffer_size": 500_000})  # 61 MB of replay
    params = validate_training(config)
    family = FAMILIES[config.learner.algo]
    program = family.configure(config, params)
    pattern = (jnp.arange(300) % 7 + 1).reshape(1, 300)  # 300 transitions of every seed, none zero

    def saved():
        runner = family.init(program, params, config.seed)
        data = jax.tree.map(
            lambda x: x.at[:, :300].set(pattern.reshape(1, 300, *[1] * (x.ndim - 2)).astype(x.dtype)),
            runner.buffer.data,
        )
        return runner.replace(buffer=runner.buffer.replace(data=data, size=jnp.full_like(runner.buffer.size, 300)))

    storage.save_checkpoint(tmp_path / "checkpoint.npz", saved())
    replay = sum(x.nbytes for x in jax.tree.leaves(family.init(program, params, config.seed).buffer))
    alive, place = [], storage.placed
    monkeypatch.setattr(
        storage, "placed", lambda *a: alive.append(sum(x.nbytes for x in jax.live_arrays())) or place(*a)
    )
    before = sum(x.nbytes for x in jax.live_arrays())
    tracemalloc.start()
    try:
        loaded = storage.load_checkpoint(
            tmp_path / "checkpoint.npz",
            family.init(program, params, config.seed),
            family.replay_buffer(program, params),
        )
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert replay > 5 * 10**7 and peak < replay / 10, (peak, replay)
    placed = len(jax.tree.leaves(loaded.buffer))  # every array of the replay was placed, one at a time
    assert len(alive) == placed and max(alive) - before < 1.2 * replay, (alive, before, replay)
    for got, want in zip(jax.tree.leaves(loaded), jax.tree.leaves(saved())):
        np.testing.assert_array_equal(got, want)


def test_ranked_replay_is_deterministic_and_resumes_exactly(tiny_config, tmp_path, signal_at_chunk):
    """Same seed => same numbers with the experience sample optimizer, also across a Ctrl-C
    (checkpoint of losses and sampling table) and a resume; here in Schaul's 1/rank reading,
    with importance weights whose exponent rises from 0.5 over the run."""
    config = with_options(tiny_config, RANKED_OPTIONS)
    reference = train(config, progress=False)
    disarm = signal_at_chunk(signal.SIGINT)  # Ctrl-C mid-run: the trainer checkpoints and stops
    with pytest.raises(RunStopped, match="interrupted at episode 200"):
        train(config, out=tmp_path, progress=False)
    disarm()
    resumed = train(config, out=tmp_path, resume=True, progress=False)
    assert TIMELESS(resumed.metrics) == TIMELESS(reference.metrics)
    newest = [r["sampled_newest"] for r in reference.metrics if r["critic_loss"] > 0]
    assert newest and all(0 < x < 1 for x in newest)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--batch-size", "2000", "--buffer-size", "1000"], "--batch-size (2000) must not exceed --buffer-size (1000)"),
        (["--num-envs", "3"], "must be a multiple of --num-envs (3)"),
        (["--scenario", "mars-9"], "unknown scenario 'mars-9'"),
        (["--gamma", "1.5"], "--gamma must be in [0, 1]"),
        (["--replay", "ranked", "--alpha", "-1"], "--alpha must be >= 0, got -1.0"),
        (["--replay", "ranked", "--beta", "1.5"], "--beta must be in [0, 1], got 1.5"),
        (["--replay", "ranked", "--refresh-every", "0"], "--refresh-every must be >= 1, got 0"),
        (["--importance-exponent", "1.5"], "--importance-exponent must be in [0, 1], got 1.5"),
        (["--noise-decay-episodes", "-5"], "--noise-decay-episodes must be >= 0, got -5"),
        (["--checkpoint-minutes", "-1"], "--checkpoint-minutes must be a finite number >= 0, got -1.0"),
    ],
)
def test_bad_training_input_is_one_line_and_exit_2(argv, message, capsys, tmp_path):
    assert main(["train", *argv, "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_unknown_algorithm_is_refused_with_exit_2(capsys):
    assert main(["train", "--algo", "qmix"]) == 2
    assert capsys.readouterr().err == "roverswarm: error: --algo must be one of maddpg, ddpg, mappo, ippo, got 'qmix'\n"


def test_resume_with_a_different_config_is_refused(unbroken, capsys):
    assert main(["train", "--resume", str(unbroken.out), "--scenario", "paper-5"]) == 2
    assert "has scenario='paper-2', not 'paper-5'" in capsys.readouterr().err
    assert main(["train", "--out", str(unbroken.out), "--scenario", "paper-2"]) == 2
    assert "already holds a run" in capsys.readouterr().err


def test_a_new_run_does_not_overwrite_a_run_whose_checkpoint_was_removed(unbroken, capsys, tmp_path):
    """A finished run kept as its record (config, metrics, curve) after its checkpoint was
    removed to save space is refused, its files unchanged."""
    out = tmp_path / "record"
    shutil.copytree(unbroken.out, out)
    (out / CHECKPOINT).unlink()
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    assert main(["train", "--episodes", "20", "--log-every", "20", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "holds a run's metrics.csv and learning_curve.png but no checkpoint.npz" in err and err.count("\n") == 1
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before


def test_a_new_run_does_not_overwrite_another_commands_metrics(capsys, tmp_path):
    """A folder holding a mission's outputs (metrics.csv, no config.json) is refused before
    anything is written there."""
    out = tmp_path / "mission"
    out.mkdir()
    (out / "metrics.csv").write_text("episode,reward\n0,1.5\n")
    assert main(["train", "--episodes", "20", "--log-every", "20", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "holds another command's metrics.csv" in err and err.count("\n") == 1
    assert sorted(p.name for p in out.iterdir()) == ["metrics.csv"]
    assert (out / "metrics.csv").read_text() == "episode,reward\n0,1.5\n"


def test_a_folder_being_written_is_refused_and_a_stale_lock_is_taken_over(tiny_config, tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    # a live Python process that holds no flock (perhaps an older roverswarm) holds the folder
    writer = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    stranger = subprocess.Popen(["sleep", "60"])
    try:
        # a lock naming a live process that is not Python (its number reused) is stale
        (out / LOCK).write_text(f"{stranger.pid} {socket.gethostname()}")
        with folder_lock(out):
            assert (out / LOCK).read_text() == f"{os.getpid()} {socket.gethostname()}"
        (out / LOCK).write_text(f"{writer.pid} {socket.gethostname()}")
        # (200 episodes: 5000 transitions, the replay stays 4000 long: the tiny runs' program)
        args = ["train", *cli_args(dataclasses.replace(tiny_config, episodes=200)), "--out", str(out)]
        assert main(args) == 2
        err = capsys.readouterr().err
        assert f"is being written by process {writer.pid}" in err and err.count("\n") == 1
        assert not (out / "config.json").exists() and (out / LOCK).exists()
    finally:
        for process in (writer, stranger):
            process.kill()
            process.wait()
    # its process is gone: the lock is stale, taken over, and released at the end
    assert main(args) == 0
    assert (out / CHECKPOINT).exists() and not (out / LOCK).exists()
    assert (out / "notes.txt").read_text() == "mine"
    # a failed command leaves no empty folder behind
    assert main(["train", "--resume", str(tmp_path / "typo")]) == 2
    assert not (tmp_path / "typo").exists()


def test_faults_end_in_one_line_and_exit_2_and_leave_the_run_as_it_was(unbroken, tiny_config, tmp_path, capsys):
    def refused(argv: list[str], message: str) -> None:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err

    run = tmp_path / "run"
    shutil.copytree(unbroken.out, run)
    (tmp_path / "file").write_text("not a folder")
    refused(["train", *cli_args(tiny_config), "--out", str(tmp_path / "file")], "is a file")
    if Path("/proc/self").exists():  # a file system no folder can be made in, even by root
        refused(
            ["train", *cli_args(tiny_config), "--out", "/proc/roverswarm-run"],
            "output folder '/proc/roverswarm-run' cannot be written (the file system there makes no new files)",
        )
    metrics = (run / METRICS).read_text()
    (run / METRICS).write_text("seed,episodes,episode_reward,wall_seconds\n0,100,oops,1\n")
    refused(["train", "--resume", str(run)], "metrics.csv' is damaged")
    (run / METRICS).write_text("a,b\n1,2\n")  # another file's columns: a KeyError once
    refused(["train", "--resume", str(run)], "metrics.csv' is damaged (no column 'seed')")
    (run / METRICS).write_text(metrics.replace("wall_seconds", "seconds"))
    refused(["train", "--resume", str(run)], "metrics.csv' is damaged (no column 'wall_seconds')")
    (run / METRICS).unlink()
    refused(["train", "--resume", str(run)], "metrics.csv' is missing or lacks rows of the 400 episodes")
    (run / METRICS).write_text(metrics)
    assert main(["train", "--resume", str(run)]) == 0  # restored: nothing left to do


def test_a_full_disk_keeps_the_previous_file_and_leaves_no_temporary_one(tiny_config, tmp_path, capsys, monkeypatch):
    path = tmp_path / "checkpoint.npz"
    path.write_bytes(b"the previous checkpoint")

    def full(f):
        f.write(b"half")
        raise OSError(errno.ENOSPC, "No space left on device")

    with pytest.raises(UserError, match="No space left on device\\); the previous version is kept"):
        atomic_write(path, full, binary=True)
    assert path.read_bytes() == b"the previous checkpoint" and not list(tmp_path.glob("*.tmp"))

    def interrupted(f):  # a second Ctrl-C while a checkpoint is written
        f.write(b"half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(path, interrupted, binary=True)
    assert path.read_bytes() == b"the previous checkpoint" and not list(tmp_path.glob("*.tmp"))

    def no_space(writer):
        raise OSError(errno.ENOSPC, "No space left on device")

    with monkeypatch.context() as patch:  # the first metrics.csv of a new run cannot be written
        patch.setattr(csv.DictWriter, "writeheader", no_space)
        assert main(["train", *cli_args(tiny_config), "--out", str(tmp_path / "new")]) == 2
    err = capsys.readouterr().err
    assert "No space left on device); nothing was written" in err and err.count("\n") == 1
    assert not list((tmp_path / "new").glob("*.tmp"))


@pytest.mark.parametrize("options", [{}, RANKED_OPTIONS, {"ensemble": 2}], ids=["uniform", "ranked", "partitions"])
def test_a_replay_capped_at_the_runs_own_transitions_gives_the_numbers_of_the_full_one(
    tiny_config, monkeypatch, options
):
    # 100 episodes (2500 transitions) beside the tiny config's replay of 4000: the full replay
    # is the program of the module's other runs with these options
    config = with_options(tiny_config, {**options, "episodes": 100})
    params = validate(config)
    assert run_buffer(config, params).capacity == 100 * params.max_steps  # not 4000
    capped = train(config, progress=False)
    monkeypatch.setattr(offpolicy, "run_replay", lambda c, p: c.buffer)
    full = train(config, progress=False)
    assert TIMELESS(capped.metrics) == TIMELESS(full.metrics)


def test_a_replay_larger_than_the_machine_is_refused_before_it_is_allocated(tiny_config, monkeypatch):
    monkeypatch.setattr(limits, "memory_limit", lambda: 2**24)  # a process allowed 16 MiB (the replay: 32 MB)
    config = with_options(tiny_config, {"episodes": 10_000, "buffer_size": 10**6})  # 250,000 transitions
    with pytest.raises(UserError, match=r"this run needs about .* GiB of it for the replay \(--buffer-size 1000000, "):
        train(config, progress=False)


def test_evaluate_reports_policies_beside_random_and_oracle(unbroken, capsys, monkeypatch):
    rows = evaluate_run(unbroken.out, episodes=50)
    names = [r["policy"] for r in rows]
    assert names == ["random", "oracle", "maddpg seed 0", "maddpg seed 1"]
    assert rows[0]["normalized_score"] == 0.0 and rows[1]["normalized_score"] == 1.0
    learner = Run(unbroken.out).learner
    np.testing.assert_array_equal(jax.tree.leaves(learner.actor)[0], jax.tree.leaves(unbroken.learner.actor)[0])
    for name in ("FORCE_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE"):
        monkeypatch.delenv(name, raising=False)
    capsys.readouterr()
    evaluate_run(unbroken.out, episodes=5, progress=True)
    assert capsys.readouterr().out == ""  # piped: no bar, not even an empty line
    monkeypatch.setenv("FORCE_COLOR", "1")  # a terminal: the command shows its progress bar
    monkeypatch.setenv("TERM", "xterm")
    assert main(["evaluate", str(unbroken.out), "--episodes", "50"]) == 0
    out = capsys.readouterr().out
    assert "maddpg seed 1, 50 episodes" in out  # the bar ran, and left the table's numbers alone:
    assert all(f"{r['episode_reward']:.3f}" in out and f"{r['normalized_score']:.3f}" in out for r in rows)


def test_the_references_roll_out_once_per_size_seed_and_episode_count(unbroken, monkeypatch):
    """Another evaluation at the same size, seed and episode count (another run of a grid, say)
    is scored against the same random and oracle episodes without rolling them out again; another
    seed, episode count or layout (a mission's arrays) rolls them out anew."""
    import roverswarm.evaluate as evaluate_module

    evaluate_module._references.clear()
    first = evaluate_run(unbroken.out, episodes=50, seed=7)
    rolled, real = [], evaluate_module.rollout
    monkeypatch.setattr(
        evaluate_module, "rollout", lambda policy, *args: rolled.append(policy.name) or real(policy, *args)
    )
    assert evaluate_run(unbroken.out, episodes=50, seed=7) == first
    assert rolled == ["maddpg seed 0", "maddpg seed 1"]
    for seed, episodes in ((8, 50), (7, 5)):
        rolled.clear()
        evaluate_run(unbroken.out, episodes=episodes, seed=seed)
        assert rolled == ["random", "oracle", "maddpg seed 0", "maddpg seed 1"]
    rolled.clear()
    params = Run(unbroken.out).params
    for pois in ([[0.5, 0.5], [-0.5, 0.5]], [[0.5, 0.5], [-0.5, 0.5]], [[0.5, 0.5], [0.5, -0.5]]):
        fixed = params.replace(fixed_pois=jnp.asarray(pois))
        fresh = real(ORACLE, jax.random.PRNGKey(7), fixed, 5).stats.summary()
        assert evaluate_module.reference_summary("oracle", 7, fixed, 5) == fresh
    assert rolled == ["oracle", "oracle"]  # the second layout is the first's values


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["maddpg", "ddpg"])
def test_a_short_run_learns_to_beat_random_by_a_wide_margin(algo, tmp_path):
    """The reference settings (the cheapest to train) on paper-2, 4000 episodes."""
    config = with_options(
        REFERENCE, dict(scenario="paper-2", algo=algo, episodes=4000, seeds=2, batch_size=256, buffer_size=50_000)
    )
    result = train(config, out=tmp_path, progress=False)
    rows = evaluate_run(tmp_path, episodes=500)
    # a score above 0.3 closes 30% of the random-to-oracle gap (about 20 reward per episode
    # on paper-2, over ten standard errors of random's mean over 500 episodes)
    scores = [r["normalized_score"] for r in rows[2:]]
    assert min(scores) > 0.3, rows
    assert result.metrics[-1]["episode_reward"] > result.metrics[0]["episode_reward"]


@pytest.mark.slow
def test_the_swarm_preset_beats_random_by_a_wide_margin(tmp_path):
    """The swarm preset's learner (shared networks, MATD3, nearest-first view) on paper-2,
    3000 episodes, its networks (64, 64) and its batch 128 (0.48 / 0.43 when written; the
    preset's 128 units and 256: 0.60 / 0.57 in 2.4 times the time)."""
    config = with_options(SWARM, dict(scenario="paper-2", episodes=3000, seeds=2, hidden=(64, 64), batch_size=128))
    train(config, out=tmp_path, progress=False)
    scores = [r["normalized_score"] for r in evaluate_run(tmp_path, episodes=500)[2:]]
    assert min(scores) > 0.3, scores


def test_preset_reference_starts_from_the_reference_values(monkeypatch, tmp_path):
    import roverswarm.cli as cli

    seen = []
    monkeypatch.setattr(
        cli, "train", lambda config, **kw: seen.append(config) or (_ for _ in ()).throw(RunStopped("parsed"))
    )
    assert main(["train", "--preset", "reference", "--scenario", "spread-3", "--out", str(tmp_path / "a")]) == 1
    assert main(["train", "--scenario", "spread-3", "--out", str(tmp_path / "b")]) == 1
    assert seen[0] == dataclasses.replace(REFERENCE, scenario="spread-3")
    assert seen[1] == TrainConfig(scenario="spread-3") != seen[0]
    assert (seen[0].learner.actor_lr, seen[0].update_every, seen[0].buffer.batch_size) == (1e-2, 100, 1024)


def test_the_python_api_is_roverswarm_train(unbroken, tiny_config):
    import roverswarm

    result = roverswarm.train(tiny_config, progress=False)
    assert isinstance(result, roverswarm.Result) and TIMELESS(result.metrics) == TIMELESS(unbroken.metrics)


def test_run_folders_written_before_the_replay_config_moved_still_load(unbroken, tmp_path, capsys):
    """A config.json with the replay settings at the top level (as written before they moved
    into ``buffer``) loads, evaluates and resumes."""
    import shutil

    old = tmp_path / "old"
    shutil.copytree(unbroken.out, old)
    raw = json.loads((old / "config.json").read_text())
    raw.update(raw.pop("buffer"))
    (old / "config.json").write_text(json.dumps(raw))
    assert Run(old).config == unbroken.config
    assert [r["policy"] for r in evaluate_run(old, episodes=50)][2:] == ["maddpg seed 0", "maddpg seed 1"]
    assert main(["train", "--resume", str(old)]) == 0
    assert TIMELESS(read_metrics(old / "metrics.csv")) == TIMELESS(unbroken.metrics)


def test_a_truncated_checkpoint_is_one_line_and_exit_2(unbroken, tmp_path, capsys):
    import shutil

    broken = tmp_path / "broken"
    shutil.copytree(unbroken.out, broken)
    data = (broken / CHECKPOINT).read_bytes()
    (broken / CHECKPOINT).write_bytes(data[: len(data) // 2])
    for argv in (["evaluate", str(broken), "--episodes", "5"], ["train", "--resume", str(broken)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "cannot be read" in err and "truncated" in err and err.count("\n") == 1, err
    # bytes that are no zip at all: numpy takes them for a pickle and advises allow_pickle=True,
    # which no checkpoint needs
    (broken / CHECKPOINT).write_bytes(bytes(range(256)) * 4)
    assert main(["evaluate", str(broken), "--episodes", "5"]) == 2
    err = capsys.readouterr().err
    assert "not a roverswarm checkpoint" in err and "pickle" not in err and err.count("\n") == 1, err


def test_a_missing_checkpoint_says_so(tmp_path):
    """Reading a checkpoint that is not there (the Python API: the CLI checks the run folder
    first) names the file and says it does not exist, not that it is truncated."""
    from roverswarm.storage import trained_episodes

    with pytest.raises(UserError, match=r"^no checkpoint at '.*nowhere\.npz': the file does not exist$"):
        trained_episodes(tmp_path / "nowhere.npz")


@pytest.mark.parametrize("algo", ["maddpg", "mappo"])
@pytest.mark.parametrize(
    "shaping, penalty, contacts, big",
    [
        ("trap_shaping", "trap_penalty", "trap_contacts", {"trap_radius": 0.4}),
        ("collision_shaping", "collision_penalty", "collisions", {"rover_radius": 0.5, "contact_force": 0.0}),
    ],
)
def test_contact_shaping_trains_on_a_heavier_penalty_and_reports_the_environments_reward(
    algo, shaping, penalty, contacts, big, tiny_config, tiny_ppo_config
):
    """--trap-shaping k (--collision-shaping k): the rewards the learner keeps are those of the
    same environment with the trap (collision) penalty 1 + k (the environment's own reward
    formula), step by step; the episode rewards it reports are those of the unshaped environment."""
    import roverswarm.learners.onpolicy as onpolicy
    from roverswarm.algos import ppo
    from roverswarm.algos.learner import init_learner
    from roverswarm.env import observation_size

    config = tiny_config if algo == "maddpg" else tiny_ppo_config
    shaped = with_options(config, {shaping: 4.0})
    params = validate(config).replace(**big)  # big craters, or big rovers not pushed apart: many contacts
    heavy = params.replace(**{penalty: 5.0})
    sizes = (params.num_rovers, observation_size(params))
    if algo == "maddpg":
        learner = init_learner(jax.random.PRNGKey(0), config.learner, *sizes)
        run = jax.jit(lambda c, p: offpolicy.collect(c, p, learner, jax.random.PRNGKey(1), 0.3), static_argnums=0)
    else:
        actor = ppo.init_ppo(jax.random.PRNGKey(0), config, *sizes).actor
        run = jax.jit(lambda c, p: onpolicy.collect(c, p, actor, jax.random.PRNGKey(1)), static_argnums=0)
    kept = lambda out: out[0].rewards  # noqa: E731  (the replay's or the trajectory's)
    plain, on_heavy, trained = run(config, params), run(config, heavy), run(shaped, params)
    assert float(plain[-1][contacts].sum()) > 10
    np.testing.assert_allclose(kept(trained), kept(on_heavy), rtol=1e-6, atol=1e-5)
    assert not np.allclose(kept(trained), kept(plain))
    for name in ("episode_reward", "agent_rewards", contacts):
        np.testing.assert_allclose(trained[-1][name], plain[-1][name], rtol=1e-6)
    if shaping == "trap_shaping":  # --trap-margin: the same collection, charged also near a trap
        margined = with_options(config, {shaping: 4.0, "trap_margin": 0.2})
        assert config_from_json(config_to_json(margined)) == margined  # kept in the run's config.json
        near = kept(run(margined, params))
        assert np.all(near <= kept(trained) + 1e-5) and np.any(near < kept(trained) - 0.1)
    flag = "--" + shaping.replace("_", "-")
    with pytest.raises(UserError, match=f"{flag} must be a finite number >= 0, got -1"):
        validate(with_options(config, {shaping: -1.0}))


def test_the_swarm_shaping_pays_for_pois_first_observed_and_charges_the_unobserved_distance(tiny_ppo_config):
    """--observe-bonus b and --unobserved-shaping u on every rover's reward at every step of
    random episodes: + b per POI first observed at that step, - u times the distance left to the
    POIs not yet observed (both checked against NumPy loops in test_env_mars), not the coverage
    distance, which counts observed POIs too and differs on these steps."""

    from roverswarm.env.mars import reset, step_env
    from roverswarm.metrics import shaped_rewards

    b, u = 0.7, 0.3
    learner = with_options(tiny_ppo_config, {"observe_bonus": b, "unobserved_shaping": u}).learner
    params = get_scenario("paper-3")

    def episode(key):
        _, state = reset(key, params)

        def step(state, key):
            actions = jax.random.uniform(key, (params.num_rovers, 2), minval=-1, maxval=1)
            _, state, rewards, *_, info = step_env(state, actions, params)
            return state, (rewards, info)

        return jax.lax.scan(step, state, jax.random.split(key, params.max_steps))[1]

    rewards, info = jax.jit(jax.vmap(episode))(jax.random.split(jax.random.PRNGKey(3), 16))
    first, left = np.asarray(info["pois_first_observed"]), np.asarray(info["unobserved_distance"])
    expected = np.asarray(rewards) + (b * first - u * left)[..., None]
    np.testing.assert_allclose(shaped_rewards(rewards, info, learner), expected, rtol=1e-5, atol=1e-5)
    assert first.sum() > 5 and not np.allclose(left, np.asarray(info["coverage_distance"]))


def test_trap_margin_charges_the_shaping_on_a_ramp_from_the_margin_to_contact(tiny_ppo_config):
    """--trap-margin M: each rover pays --trap-shaping k times clip(1 - gap / M, 0, 1) per trap
    and step, the gap computed here in NumPy from the positions (distance less both radii):
    the full k on contact, a part within M, nothing beyond it nor for traps or rovers a padded
    layout leaves out; the environment's reward and contact count are unchanged."""
    import jax.numpy as jnp

    from roverswarm.env.mars import reset, step_env
    from roverswarm.env.scenarios import padded_scenario, sized
    from roverswarm.metrics import shaped_rewards

    k, margin = 2.0, 0.3
    learner = with_options(tiny_ppo_config, {"trap_shaping": k, "trap_margin": margin}).learner
    plain = with_options(tiny_ppo_config, {"trap_shaping": k}).learner
    params = sized(padded_scenario("paper-2..5"), 3).replace(trap_radius=0.25)  # big craters: near and on them
    near = contact = 0
    reset_jit, step_jit, shaped = jax.jit(reset), jax.jit(step_env), jax.jit(shaped_rewards, static_argnums=2)
    for seed in range(20):
        _, state = reset_jit(jax.random.PRNGKey(seed), params)
        offsets = jax.random.uniform(jax.random.PRNGKey(100 + seed), (params.num_rovers, 2), minval=-0.5, maxval=0.5)
        state = state.replace(rover_pos=state.trap_pos + offsets)  # rover i by trap i, on it or near it
        actions = jnp.zeros((params.num_rovers, 2))
        _, after, rewards, _, _, info = step_jit(state, actions, params)
        pos, traps = np.asarray(after.rover_pos, np.float64), np.asarray(after.trap_pos, np.float64)
        gaps = np.linalg.norm(pos[:, None] - traps[None], axis=-1) - params.rover_radius - 0.25
        gaps[3:, :] = np.inf  # rovers 3 and 4 and traps 3 and 4 are not in this swarm of 3
        gaps[:, 3:] = np.inf
        charge = np.clip(1 - gaps / margin, 0, 1).sum(axis=1)
        np.testing.assert_allclose(shaped(rewards, info, learner), rewards - k * charge, atol=1e-5)
        np.testing.assert_allclose(shaped(rewards, info, plain), rewards - k * (gaps < 0).sum(1), atol=1e-5)
        np.testing.assert_array_equal(info["trap_contacts"], (gaps < 0).sum(axis=1))
        near += int(((gaps > 0) & (gaps < margin)).sum())
        contact += int((gaps < 0).sum())
    assert near > 5 and contact > 2  # both parts of the ramp were exercised
    with pytest.raises(UserError, match="--trap-margin 0.1 sets where --trap-shaping starts"):
        validate(with_options(tiny_ppo_config, {"trap_margin": 0.1}))


@pytest.mark.parametrize("algo", ["maddpg", "mappo"])
def test_observe_bonus_pays_every_rover_for_each_poi_first_observed(algo, tiny_config, tiny_ppo_config):
    """--observe-bonus b: the learner's rewards exceed the environment's by b times the POIs
    first observed at that step (the same for every rover: at most one payment per POI and
    episode); the episode rewards it reports are the environment's."""
    import roverswarm.learners.onpolicy as onpolicy
    from roverswarm.algos import ppo
    from roverswarm.algos.learner import init_learner
    from roverswarm.env import observation_size

    config = dataclasses.replace(tiny_config if algo == "maddpg" else tiny_ppo_config, num_envs=25)
    params = validate(config).replace(observe_radius=0.3)  # wide sight: many POIs observed
    sizes = (params.num_rovers, observation_size(params))
    if algo == "maddpg":
        learner = init_learner(jax.random.PRNGKey(0), config.learner, *sizes)
        run = lambda c: offpolicy.collect(c, params, learner, jax.random.PRNGKey(1), 0.3)  # noqa: E731
    else:
        actor = ppo.init_ppo(jax.random.PRNGKey(0), config, *sizes).actor
        run = lambda c: onpolicy.collect(c, params, actor, jax.random.PRNGKey(1))  # noqa: E731
    plain, paid = run(config), run(with_options(config, {"observe_bonus": 2.5}))
    first = (np.asarray(paid[0].rewards) - np.asarray(plain[0].rewards)) / 2.5  # [T, E, N]
    np.testing.assert_allclose(first, np.round(first), atol=1e-4)
    np.testing.assert_allclose(first, first[..., :1] + 0 * first, atol=1e-4)  # every rover alike
    per_episode = np.round(first[..., 0]).sum(axis=0)  # [E]
    assert per_episode.min() >= 0 and per_episode.max() <= params.num_pois and per_episode.sum() >= 5
    for name in ("episode_reward", "agent_rewards"):
        np.testing.assert_allclose(paid[-1][name], plain[-1][name], rtol=1e-6)
    with pytest.raises(UserError, match="--observe-bonus must be a finite number >= 0, got -1"):
        validate(with_options(config, {"observe_bonus": -1.0}))


def test_unobserved_shaping_charges_every_rover_the_distance_left_to_open_pois(tiny_ppo_config):
    """--unobserved-shaping w: the learner's rewards fall short of the environment's by w times
    the step's unobserved distance (never negative), the same for every rover; the episode
    rewards it reports are the environment's."""
    import roverswarm.learners.onpolicy as onpolicy
    from roverswarm.algos import ppo
    from roverswarm.env import observation_size

    config = dataclasses.replace(tiny_ppo_config, num_envs=25)
    params = validate(config).replace(observe_radius=0.3)
    actor = ppo.init_ppo(jax.random.PRNGKey(0), config, params.num_rovers, observation_size(params)).actor
    run = lambda c: onpolicy.collect(c, params, actor, jax.random.PRNGKey(1))  # noqa: E731
    plain, shaped = run(config), run(with_options(config, {"unobserved_shaping": 0.5}))
    charge = (np.asarray(plain[0].rewards) - np.asarray(shaped[0].rewards)) / 0.5  # [T, E, N]
    np.testing.assert_allclose(charge, charge[..., :1] + 0 * charge, atol=1e-4)  # every rover alike
    assert charge.min() >= -1e-5 and charge.mean() > 0.1  # the exact distance: test_env_mars
    for name in ("episode_reward", "agent_rewards"):
        np.testing.assert_allclose(shaped[-1][name], plain[-1][name], rtol=1e-6)
    with pytest.raises(UserError, match="--unobserved-shaping must be a finite number >= 0, got -1"):
        validate(with_options(config, {"unobserved_shaping": -1.0}))
