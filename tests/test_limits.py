"""Limits on what the package reads and allocates: every refusal one line, exit 2, before work starts."""

from __future__ import annotations

import dataclasses
import json
import signal
import typing
from pathlib import Path

import pytest
import yaml

from roverswarm.cli import main
from roverswarm.config import TrainConfig, config_to_json, validate, with_options
from roverswarm.errors import RunStopped, UserError
from roverswarm.presets import MAPPO
from roverswarm.trainer import train

MISSION = str(Path(__file__).parent.parent / "examples" / "mission.yaml")


def refused(argv: list[str], message: str, capsys) -> None:
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err, err


@pytest.mark.parametrize(
    "argv",
    [
        ["render", "--seed", str(2**70)],
        ["evaluate", "some-run", "--seed", str(2**70)],
        ["mission", "run", MISSION, "--seed", str(2**70)],
        ["mission", "stress", MISSION, "--seed", str(2**70)],
        ["render", "--seed", "-1"],
    ],
)
def test_a_seed_a_prng_key_cannot_hold_is_one_line(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    refused(argv, "--seed must be an integer in [0, 2^32)", capsys)


@pytest.mark.parametrize(
    "top, setting, message",
    [
        ({"seeds": 2.0}, {}, "seeds must be an integer, got 2.0"),
        ({"episodes": "400"}, {}, "episodes must be an integer, got '400'"),
        ({}, {"hidden": 64}, "setting 'a': hidden must be a list of integers, got 64"),
        ({}, {"hidden": [64.5]}, "setting 'a': hidden must be a list of integers, got (64.5,)"),
        ({}, {"twin_critics": "yes"}, "setting 'a': twin_critics must be true or false, got 'yes'"),
        ({}, {"actor_lr": [1]}, "setting 'a': actor_lr must be a number, got (1,)"),
    ],
)
def test_a_wrong_typed_sweep_value_is_refused_before_training(top, setting, message, tmp_path, capsys):
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump({"scenarios": ["paper-2"], **top, "settings": {"a": setting}}))
    refused(["sweep", str(path), "--out", str(tmp_path / "out")], message, capsys)
    assert not (tmp_path / "out").exists()


def _literal_fields(config, path=()):
    """(path of field names, allowed values) of every ``Literal`` field of ``config``, nested too."""
    hints = typing.get_type_hints(type(config))
    for field in dataclasses.fields(config):
        value = getattr(config, field.name)
        if dataclasses.is_dataclass(value):
            yield from _literal_fields(value, (*path, field.name))
        elif typing.get_origin(hints[field.name]) is typing.Literal:
            yield (*path, field.name), typing.get_args(hints[field.name])


def test_every_choice_outside_its_values_is_refused_by_name():
    """A value of a ``Literal`` field (``network``, ``algo``, ``replay``...) outside its choices,
    as a sweep file or an edited config.json can hold it, is refused naming the option; the
    type check leaves the values to validate(), which must know every such field."""
    fields = list(_literal_fields(TrainConfig()))
    assert len(fields) >= 6, fields
    for path, allowed in fields:
        base = MAPPO if path[0] == "ppo" else TrainConfig()  # each option where it applies
        config = with_options(base, {path[-1]: "nonsense"})
        with pytest.raises(UserError, match=f"--{path[-1].replace('_', '-')} must be") as error:
            validate(config)
        assert all(str(value) in str(error.value) for value in allowed), (path, error.value)


def test_a_wrong_typed_config_json_is_refused_by_every_command(tiny_config, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    raw = json.loads(config_to_json(tiny_config))
    raw["seeds"] = 2.0
    (run / "config.json").write_text(json.dumps(raw))
    (run / "checkpoint.npz").write_bytes(b"")
    for argv in (["train", "--resume", str(run)], ["evaluate", str(run)]):
        refused(argv, "config.json: seeds must be an integer, got 2.0", capsys)
    raw["seeds"], raw["learner"]["action_penalty"] = 2, -1.0  # well typed, a value this version refuses
    (run / "config.json").write_text(json.dumps(raw))
    for argv in (["evaluate", str(run)], ["render", "--policy", str(run), "--out", str(tmp_path / "e.gif")]):
        refused(argv, f"the run in '{run}': its config.json: --action-penalty must be a finite number >= 0", capsys)


@pytest.fixture(scope="module")
def interrupted(tiny_config, tmp_path_factory):
    """A tiny run stopped after 2 of 3 chunks (200 episodes: 5000 transitions seen, 4000 kept)."""
    import os

    out = tmp_path_factory.mktemp("interrupted") / "run"
    config = dataclasses.replace(tiny_config, episodes=300)
    from roverswarm.learners import FAMILIES

    real, calls = dict(FAMILIES), []

    def signalled(run_chunk):
        def run(*args):
            calls.append(1)
            if len(calls) == 2:
                os.kill(os.getpid(), signal.SIGINT)
            return run_chunk(*args)

        return run

    FAMILIES.update({algo: dataclasses.replace(f, run_chunk=signalled(f.run_chunk)) for algo, f in real.items()})
    try:
        with pytest.raises(RunStopped):
            train(config, out=out, progress=False)
    finally:
        FAMILIES.update(real)
    return config, out


def test_a_replay_smaller_than_what_a_resumed_run_filled_is_one_line(interrupted):
    from roverswarm.config import validate, with_options
    from roverswarm.learners import learner_family
    from roverswarm.storage import load_checkpoint

    config, out = interrupted
    smaller = with_options(config, {"buffer_size": 1000})
    params = validate(smaller)
    family = learner_family(smaller.learner.algo)
    template = family.init(family.configure(smaller, params), params, smaller.seed)
    with pytest.raises(UserError, match="already holds 4000 transitions per seed .* --buffer-size >= 4000"):
        load_checkpoint(out / "checkpoint.npz", template)


def test_an_edited_config_json_or_another_presets_learner_is_not_resumed(interrupted, tmp_path, capsys):
    import shutil

    _, run = interrupted
    out = tmp_path / "run"
    shutil.copytree(run, out)
    refused(["train", "--resume", str(out), "--preset", "mappo"], "is --algo maddpg and --preset mappo trains", capsys)
    raw = json.loads((out / "config.json").read_text())
    raw["learner"]["actor_lr"] = 0.5
    raw["buffer"]["buffer_size"] = 1000
    (out / "config.json").write_text(json.dumps(raw))
    refused(
        ["train", "--resume", str(out)], "was edited since its checkpoint was written (actor_lr, buffer_size)", capsys
    )


def test_the_learning_curve_is_not_written_through_a_symlink(tmp_path):
    from roverswarm.runs import plot_learning_curve

    victim = tmp_path / "victim.txt"
    victim.write_text("mine")
    (tmp_path / "learning_curve.png").symlink_to(victim)
    plot_learning_curve([{"seed": 0, "episodes": 100, "episode_reward": 1.0}], tmp_path / "learning_curve.png", "t")
    assert victim.read_text() == "mine" and not (tmp_path / "learning_curve.png").is_symlink()


def test_reports_and_figures_are_not_written_through_a_symlink(tmp_path):
    """stress.md and stress.png (and Table I, report.md, the grid's and sweep's figures, which
    write by the same two helpers) were opened at their path, writing through a link there."""
    from pathlib import Path

    from roverswarm.stress import stress_mission

    victim = tmp_path / "victim.txt"
    victim.write_text("mine")
    out = tmp_path / "out"
    out.mkdir()
    for name in ("stress.md", "stress.png"):
        (out / name).symlink_to(victim)
    mission = Path(__file__).parent.parent / "examples" / "mission.yaml"
    stress_mission(mission, "random", out, episodes=4)
    assert victim.read_text() == "mine"
    assert not any((out / name).is_symlink() for name in ("stress.md", "stress.png"))


@pytest.mark.parametrize(
    "argv, part",
    [
        (
            ["train", "--hidden", "65536", "65536"],
            "for the networks (--hidden (65536, 65536), --ensemble 1, --seeds 1)",
        ),
        (["train", "--ensemble", "100000"], "--ensemble 100000, --seeds 1)"),
        (["train", "--preset", "mappo", "--seeds", "1000000"], "--seeds 1000000)"),
    ],
)
def test_memory_past_what_the_process_may_use_is_refused_before_it_is_allocated(argv, part, tmp_path, capsys):
    """Estimated from shapes only: the test would not finish (or be killed) if any were allocated."""
    refused([*argv, "--out", str(tmp_path / "run")], part, capsys)
    assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("command", ["reproduce", "sweep"])
def test_an_evaluation_too_large_is_refused_before_any_run_trains(command, tmp_path, capsys, monkeypatch):
    """The grid's and the sweep's evaluation batch was checked after every run had trained, and
    the message named --episodes; now before the first, naming --eval-episodes."""
    import roverswarm.experiments.pool as pool

    monkeypatch.setattr(pool, "train", lambda *a, **k: pytest.fail("a run trained"))
    if command == "reproduce":
        argv = ["reproduce", "--quick", "--scenarios", "paper-2", "--algorithms", "ddpg"]
    else:
        (tmp_path / "s.yaml").write_text("scenarios: [paper-2]\nepisodes: 2000\nsettings: {a: {}}\n")
        argv = ["sweep", str(tmp_path / "s.yaml")]
    big = str(2**30)
    refused([*argv, "--eval-episodes", big, "--out", str(tmp_path / "out")], f"(--eval-episodes {big})", capsys)


def test_evaluate_refuses_a_run_or_a_batch_too_large_before_reading_its_checkpoint(tiny_config, tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.npz").write_bytes(b"")  # never read: the estimate comes first
    huge = dataclasses.replace(tiny_config, learner=dataclasses.replace(tiny_config.learner, hidden=(65536, 65536)))
    (run / "config.json").write_text(config_to_json(huge))
    refused(["evaluate", str(run)], f"the run in '{run}' needs about", capsys)
    (run / "config.json").write_text(config_to_json(tiny_config))
    refused(
        ["evaluate", str(run), "--episodes", str(2**30)], "for the evaluation batch (--episodes 1073741824)", capsys
    )


def test_files_past_their_limit_are_refused_without_being_read(tiny_config, tmp_path, monkeypatch, capsys):
    """A sparse file of a few GB costs nothing to make; reading it whole would (the issue: a 1 GB
    config.json peaked at 2.4 GB). The limits: docs/limits.md."""
    import roverswarm.limits as limits
    from roverswarm.runs import read_metrics, write_csv

    run = tmp_path / "run"
    run.mkdir()
    with open(run / "config.json", "wb") as f:
        f.truncate(3 * 2**30)
    (run / "checkpoint.npz").write_bytes(b"")
    for argv in (["train", "--resume", str(run)], ["evaluate", str(run)]):
        refused(argv, f"config.json '{run / 'config.json'}' has {3 * 2**30} bytes; at most 1048576 (1 MiB)", capsys)
    sweep = tmp_path / "s.yaml"
    with open(sweep, "wb") as f:
        f.truncate(2 * 2**20)
    refused(["sweep", str(sweep), "--out", str(tmp_path / "out")], "has 2097152 bytes; at most 1048576", capsys)
    write_csv(
        tmp_path / "metrics.csv", [{"seed": 0, "episodes": 100, "episode_reward": 1.0, "wall_seconds": 1.0}] * 100
    )
    assert len(read_metrics(tmp_path / "metrics.csv")) == 100
    monkeypatch.setitem(limits.FILE_LIMITS, "metrics.csv", 1000)
    with pytest.raises(UserError, match=r"metrics.csv '.*' has \d+ bytes; at most 1000"):
        read_metrics(tmp_path / "metrics.csv")


def test_a_file_that_grows_while_it_is_read_is_cut_at_the_limit(tmp_path, monkeypatch):
    import roverswarm.limits as limits

    path = tmp_path / "metrics.csv"
    path.write_text("x" * 5000)
    monkeypatch.setitem(limits.FILE_LIMITS, "metrics.csv", 1000)
    monkeypatch.setattr(limits.os, "fstat", lambda fd: type("S", (), {"st_size": 10})())  # it was small when opened
    with pytest.raises(UserError, match="has more than 1000 bytes"):
        with limits.open_limited(path, "metrics.csv") as f:
            f.read()


def test_a_grid_checks_every_runs_memory_before_the_first_trains(tmp_path, capsys):
    refused(
        ["reproduce", "--quick", "--ensemble", "100000", "--out", str(tmp_path / "grid")], "--ensemble 100000", capsys
    )
    assert not (tmp_path / "grid" / "runs").exists()


@pytest.fixture
def memory_of(monkeypatch):
    """``set(gib)`` makes the process's memory limit ``gib`` GiB (refusals then hold on any machine);
    no rollout may run: the estimates must come first."""
    import roverswarm.evaluate
    import roverswarm.limits as limits
    import roverswarm.mission
    import roverswarm.stress

    def rolled(*args, **kwargs):
        raise AssertionError("a rollout ran before the memory check")

    for module in (roverswarm.evaluate, roverswarm.mission, roverswarm.stress):
        monkeypatch.setattr(module, "rollout", rolled)
    return lambda gib: monkeypatch.setattr(limits, "memory_limit", lambda: gib * 2**30)


@pytest.mark.parametrize("command, episodes", [("run", 1), ("stress", 500)])
def test_mission_commands_refuse_episodes_or_an_episode_length_past_memory_before_any_rollout(
    command, episodes, memory_of, tmp_path, capsys
):
    """`mission run` and `mission stress` estimate their episodes as `evaluate` does: too many
    episodes, or a mission file's episode_length too long, is one line naming it (it was a JAX
    RESOURCE_EXHAUSTED traceback, or all the memory), before any rollout and any file."""
    memory_of(16)
    out = str(tmp_path / "out")
    refused(
        ["mission", command, MISSION, "--episodes", "99999999999", "--out", out],
        "for the evaluation batch (--episodes 99999999999, the mission's episode_length 25), and this process may "
        "use 16.0 GiB; lower one of them",
        capsys,
    )
    long = tmp_path / "long.yaml"
    long.write_text(Path(MISSION).read_text().replace("episode_length: 25 ", "episode_length: 1000000000 "))
    if episodes == 1:
        length = "(the mission's episode_length 1000000000), and this process may use 16.0 GiB; lower it"
    else:
        length = f"(--episodes {episodes}, the mission's episode_length 1000000000)"
    refused(["mission", command, str(long), "--out", out], length, capsys)
    assert not Path(out).exists()


def test_training_on_a_mission_names_its_episode_length_when_it_is_too_long(memory_of, tmp_path, capsys):
    """A mission's episode_length sets the rollouts: the replay that cannot hold one iteration
    (off-policy) and the memory past the limit (on-policy) name it, not only the options; one
    past 2^31 is refused by the mission file's own field."""
    memory_of(16)
    long = tmp_path / "long.yaml"
    text = Path(MISSION).read_text()
    long.write_text(text.replace("episode_length: 25 ", "episode_length: 100000000 "))
    out = str(tmp_path / "run")
    refused(
        ["train", "--mission", str(long), "--out", out],
        "must hold one iteration's transitions (--num-envs 20 x the mission's episode_length 100000000 = 2000000000)",
        capsys,
    )
    refused(
        ["train", "--mission", str(long), "--algo", "mappo", "--out", out],
        "--seeds 1, the mission's episode_length 100000000), and this process may use 16.0 GiB; lower one of them",
        capsys,
    )
    long.write_text(text.replace("episode_length: 25 ", f"episode_length: {2**31} "))
    refused(
        ["train", "--mission", str(long), "--out", out], "episode_length: must be an integer from 1 to 2^31 - 1", capsys
    )
    assert not Path(out).exists()


def test_evaluate_checks_the_memory_of_every_size_it_runs_before_any_rollout(memory_of, tmp_path, capsys):
    """A size-agnostic run evaluated on a larger scenario: the batch is estimated at each target
    size (it was at the run's own, paper-3, and paper-64 then ran for minutes toward all the
    memory), before its checkpoint is read."""
    from roverswarm.config import with_options
    from roverswarm.presets import MAPPO

    memory_of(4)  # 12000 episodes of paper-3 take 0.3 GiB, of paper-64 34 GiB
    config = dataclasses.replace(
        with_options(MAPPO, {"network": "nearest", "entity_nearest": 4, "hidden": (16,)}), scenario="paper-3"
    )
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(config_to_json(config))
    (run / "checkpoint.npz").write_bytes(b"")  # never read: the estimate comes first
    for scenario in ("paper-64", "paper-2..64"):
        refused(
            ["evaluate", str(run), "--scenario", scenario, "--episodes", "12000"],
            f"GiB of it for the evaluation batch (--episodes 12000, --scenario {scenario}), and this process may use "
            "4.0 GiB; lower one of them",
            capsys,
        )
