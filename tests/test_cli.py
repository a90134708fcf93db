"""The command line, in-process (and once into a real pipe): every command works and bad input ends in
one line, exit 2."""

from __future__ import annotations

import re
from pathlib import Path

import imageio.v2 as imageio
import numpy as np
import pytest

from roverswarm.cli import SIGPIPE_EXIT, main, print_table
from roverswarm.env import SCENARIOS, get_scenario
from roverswarm.env.mars import observation_size
from roverswarm.errors import RunStopped


def test_scenarios_lists_every_preset_with_sizes(capsys):
    assert main(["scenarios"]) == 0
    out = capsys.readouterr().out
    for name in SCENARIOS:
        assert name in out
        assert str(observation_size(get_scenario(name))) in out


@pytest.mark.parametrize("columns", [60, 80, 87, 99, 104, 140])
def test_a_table_keeps_every_number_and_word_at_any_width(columns, capsys, monkeypatch):
    """An evaluation table of a large swarm, with and without its scenario column, at terminal
    widths around its own (80: output piped to a file): never a number cut short or a border
    cropped; a table that does not fit is printed at its full width, and one that fits (the
    scenarios, from 80 columns) stays within the width."""
    for name in ("FORCE_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("COLUMNS", str(columns))
    rows = [
        {"scenario": "paper-40", "policy": f"mappo seed {i}", "episode_reward": -15084.966 + i, "collisions": 137.53,
         "trap_contacts": 264.96, "coverage_distance": 16.113, "pois_observed": 22.48, "normalized_score": 1.009}
        for i in range(3)
    ]  # fmt: skip
    for table in (rows, [{k: v for k, v in r.items() if k != "scenario"} for r in rows]):
        print_table("wide", table, ("scenario", "policy"))
        out = capsys.readouterr().out
        lines = [line.rstrip() for line in out.splitlines() if line.strip() and line.strip() != "wide"]
        assert "…" not in out and all(line[-1] in "┓┃┩│┘" for line in lines), out
        for i in range(3):
            assert any(re.search(f"mappo seed {i} │ +{-15084.966 + i:.3f} │", line) for line in lines), out
        for word in ("normalized", "score", "contacts", "coverage", "distance", "observed", "264.960", "1.009"):
            assert word in out
    assert main(["scenarios"]) == 0  # its descriptions wrap to fit 80 columns
    assert max(map(len, capsys.readouterr().out.splitlines())) <= columns or columns < 80


def test_a_table_sizes_columns_by_terminal_cells(capsys, monkeypatch):
    """A word of wide characters (two terminal cells each) stays whole in a narrow terminal,
    and a column with no header and no text prints (empty) instead of failing."""
    monkeypatch.setenv("COLUMNS", "30")
    print_table("cells", [{"site": "火星探査基地", "": "", "reward": 1.5}], ("site",))
    out = capsys.readouterr().out
    assert "火星探査基地" in out and "1.500" in out, out


def test_folder_names_that_look_like_markup_print_whole(tmp_path, capsys):
    """rich read '[v1]' in a folder's name as markup and dropped it, and '[/x]' raised an
    error after the work was done; printed as text, both stay whole."""
    print_table("runs/a[v1]: 10 episodes", [{"policy": "ppo (a[/x], seed 0)", "reward": 1.0}], ("policy",))
    out = tmp_path / "render[/x].gif"
    assert main(["render", "--scenario", "paper-2", "--policy", "random", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "runs/a[v1]: 10 episodes" in printed and "a[/x]" in printed, printed
    assert f"wrote {out}" in printed.replace("\n", ""), printed


def test_render_writes_an_animation_and_its_last_frame(tmp_path):
    out = tmp_path / "ep.gif"
    assert main(["render", "--scenario", "paper-2", "--policy", "oracle", "--out", str(out), "--seed", "1"]) == 0
    frames = imageio.mimread(out)
    assert len(frames) == get_scenario("paper-2").max_steps + 1
    last = imageio.imread(out.with_suffix(".png"))
    assert last.ndim == 3 and last.shape[0] > 100 and last.std() > 10
    assert not np.array_equal(np.asarray(frames[0])[..., :3], np.asarray(frames[-1])[..., :3])


def test_render_drives_the_policy_behind_the_safety_layer_with_shield(tmp_path, monkeypatch, capsys):
    """`render --shield` hands the episode the policy behind the layer, and without it the policy as it is."""
    import roverswarm.animation

    drawn = []
    monkeypatch.setattr(
        roverswarm.animation, "render_episode", lambda p, policy, *a, **k: drawn.append(policy) or "x.png"
    )
    for extra in (["--shield"], []):
        assert (
            main(["render", "--scenario", "paper-2", "--policy", "random", "--out", str(tmp_path / "e.gif"), *extra])
            == 0
        )
    assert [(p.name, p.shield) for p in drawn] == [("random, shielded", True), ("random", False)]


@pytest.mark.parametrize(
    "argv, message",
    [
        (["render", "--scenario", "mars-11"], "unknown scenario 'mars-11'"),
        (["render", "--out", "episode.txt"], "--out must end in .gif or .mp4"),
        (["render", "--policy", "clever"], "--policy: expected 'oracle', 'random' or a run folder"),
        (
            [
                "train",
                "--mission",
                str(Path(__file__).parent.parent / "examples" / "mission.yaml"),
                "--scenario",
                "paper-2",
            ],
            "--scenario paper-2 (given, or set by --preset) and --mission: the mission file sets the layout and "
            "the number of rovers; give one of them",
        ),
        (
            [
                "train",
                "--preset",
                "anysize",
                "--mission",
                str(Path(__file__).parent.parent / "examples" / "mission.yaml"),
            ],
            "--scenario paper-2..10 (given, or set by --preset) and --mission: the mission file sets the layout",
        ),
        # numbers the program cannot represent or use, refused by class before anything runs
        (["train", "--actor-lr", "inf"], "--actor-lr must be a finite number, got inf"),
        (["train", "--alpha", "nan"], "--alpha must be a finite number, got nan"),
        (["train", "--tau", "1.5"], "--tau must be in (0, 1]"),
        (["train", "--seed", str(2**64 + 1)], "--seed must be an integer in [0, 2^32)"),
        (["train", "--episodes", str(10**20)], "--episodes must be below 2^31"),
        (["train", "--hidden", "0", "64"], "--hidden needs 1 or more widths in [1, 65536]"),
        (["train", "--preset", "mappo", "--twin-critics"], "--twin-critics True does not apply: --algo mappo"),
        (["train", "--epochs", "3"], "--epochs 3 does not apply: it is a PPO option"),
        (
            ["train", "--scenario", "paper-3", "--critic-neighbors", "3"],
            "--critic-neighbors must be in [0, 2]: the other rovers each critic sees besides its own, of 3 "
            "(0 = all), got 3",
        ),
        (["train", "--algo", "ddpg", "--critic-neighbors", "1"], "--critic-neighbors needs --algo maddpg"),
        (["train", "--action-penalty", "-1"], "--action-penalty must be a finite number >= 0, got -1.0"),
        (["train", "--preset", "mappo", "--init-log-std", "100"], "--init-log-std must be in [-10.0, 2.0]"),
        (
            ["train", "--preset", "anysize", "--entity-dim", "0"],
            "--entity-dim must be >= 1 (each token's width), got 0",
        ),
        (
            ["train", "--preset", "anysize", "--episodes", "100000", "--out", "runs/a"],
            "--episodes 100000 goes past --anneal-episodes 80000, where the learning rates reach 0: the last 20000 "
            "episodes per seed would train nothing; give --anneal-episodes >= 100000",
        ),
        (["reproduce", "--algorithms"], "--algorithms was given no value"),
        # an unset shell variable: not the current folder
        (["train", "--out", ""], "--out was given an empty value, most likely an unset shell variable"),
        (["train", "--out="], "--out was given an empty value, most likely an unset shell variable"),
        (["evaluate", " "], "an empty argument after evaluate, most likely an unset shell variable"),
        # a value tyro cannot convert, for options defaulting to None and for lists: one plain line
        (["reproduce", "--seeds", "abc"], "--seeds must be an integer (or None: the default), got 'abc'"),
        (["reproduce", "--alpha", "x"], "--alpha must be a number (or None: the default), got 'x'"),
        (["train", "--hidden", "64", "64.5"], "--hidden must be a list of integers, got '64', '64.5'"),
        (
            ["reproduce", "--episodes", "40"],
            "--episodes must be a positive multiple of 1000 (the episodes between the grid's metrics rows; 500 "
            "with --quick), got 40",
        ),
        # what tyro refuses itself (a choice, an option or a command it does not know, a missing
        # argument): one line of ours, not its box
        (
            ["train", "--preset", "bogus"],
            "--preset must be one of default, reference, swarm, mappo, ippo, anysize, anysize-ddpg, got 'bogus'",
        ),
        (
            ["train", "--episods", "5"],
            "unknown option --episods (did you mean --episodes?): see roverswarm train --help",
        ),
        (["render", "--animation", "webm"], "unknown option --animation: see roverswarm render --help"),
        (["evaluate", "some-run", "--bogus", "3"], "unknown option --bogus: see roverswarm evaluate --help"),
        (["nosuch"], "unknown command 'nosuch': choose one of scenarios, render, train, evaluate, sweep,"),
        (["mission", "bogus"], "unknown command 'bogus': choose one of run, stress"),
        (["export"], "roverswarm export needs PATH, --out: see roverswarm export --help"),
        # a list option with nothing after it (an unset shell variable): not its default
        (["reproduce", "--variants", "--quick"], "--variants was given no value, most likely an unset shell variable"),
        (["reproduce", "--scenarios"], "--scenarios was given no value"),
        (["train", "--hidden", "--episodes", "20"], "--hidden was given no value"),
        (
            ["reproduce", "--variants", "a:alpha=1,alpha=2"],
            "--variants: 'alpha' is given twice in 'a:alpha=1,alpha=2'",
        ),
    ],
)
def test_bad_input_is_one_line_and_exit_code_2(argv, message, capsys, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err


def test_tyro_refusals_are_one_line_in_a_narrow_terminal(capsys, monkeypatch):
    """tyro wraps its box to the terminal's width: the line read from it is the same."""
    monkeypatch.setenv("COLUMNS", "30")
    assert main(["train", "--algo", "sac"]) == 2
    assert capsys.readouterr().err == "roverswarm: error: --algo must be one of maddpg, ddpg, mappo, ippo, got 'sac'\n"
    assert main(["train", "--episods", "5"]) == 2
    expected = "roverswarm: error: unknown option --episods (did you mean --episodes?): see roverswarm train --help\n"
    assert capsys.readouterr().err == expected


def test_a_refused_forced_grid_keeps_the_earlier_timings(tmp_path, capsys):
    """``reproduce --force`` deletes the earlier grid's timings only once the new grid is
    checked: refused, it leaves them."""
    (tmp_path / "timing.csv").write_text("scenario,arm,chunk,seconds_per_1000\n")
    assert main(["reproduce", "--force", "--seeds", "0", "--out", str(tmp_path)]) == 2
    assert "--seeds must be >= 1" in capsys.readouterr().err
    assert (tmp_path / "timing.csv").read_text() == "scenario,arm,chunk,seconds_per_1000\n"


def test_an_output_that_cannot_be_written_is_refused_before_the_episode(tmp_path, capsys, monkeypatch):
    """An --out in a folder that takes no file, under a file, or naming a folder: one line,
    exit code 2, before an episode is run, and no writer left half closed (which printed a
    traceback when it was collected)."""
    import gc
    import sys

    import roverswarm.animation

    unraisable = []
    monkeypatch.setattr(sys, "unraisablehook", unraisable.append)
    monkeypatch.setattr(roverswarm.animation, "rollout", lambda *a, **k: pytest.fail("the episode was run"))
    (tmp_path / "notes.txt").write_text("")
    (tmp_path / "folder.gif").mkdir()
    (tmp_path / "still.png").mkdir()  # where the last frame of still.gif would go
    cases = {
        str(tmp_path / "notes.txt" / "ep.gif"): "is a file, not a folder",
        str(tmp_path / "folder.gif"): "is a folder; give a file ending in .gif or .mp4",
        str(tmp_path / "still.gif"): f"its last frame's '{tmp_path / 'still.png'}' is a folder",
    }
    if Path("/proc/self").exists():  # a folder no file can be made in, even by root
        cases["/proc/ep.gif"] = "folder '/proc' cannot be written (the file system there makes no new files)"
    for out, message in cases.items():
        assert main(["render", "--scenario", "paper-2", "--out", out]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    gc.collect()
    assert unraisable == []


def test_an_mp4_is_written_without_the_fork_warning(tmp_path, capsys):
    """ffmpeg is started by fork and exec, which JAX's fork warning does not concern: the
    command prints no warning."""
    import warnings

    out = tmp_path / "ep.mp4"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(["render", "--scenario", "paper-2", "--policy", "oracle", "--out", str(out)]) == 0
    assert not [w for w in caught if "fork" in str(w.message)], [str(w.message) for w in caught]
    assert len(imageio.mimread(out)) == get_scenario("paper-2").max_steps + 1 and out.with_suffix(".png").exists()


def test_out_and_resume_may_spell_one_folder_two_ways(tmp_path, capsys, monkeypatch):
    """`train --resume r1 --out /abs/r1` names one folder: it goes on to the resume's own
    checks (here: no checkpoint to continue); two folders are refused."""
    from roverswarm.config import TrainConfig, config_to_json

    monkeypatch.chdir(tmp_path)
    (tmp_path / "r1").mkdir()
    (tmp_path / "r1" / "config.json").write_text(config_to_json(TrainConfig()))
    for resume, out in (("r1", str(tmp_path / "r1")), (str(tmp_path / "r1"), "./r1/"), ("r1", "r2")):
        assert main(["train", "--resume", resume, "--out", out]) == 2
        err = capsys.readouterr().err
        expected = "name different folders" if out == "r2" else "--resume: no run to continue in"
        assert expected in err and err.count("\n") == 1, err


@pytest.mark.parametrize("argv", [["train", "--help"], ["scenarios"]])
def test_output_into_a_closed_pipe_ends_quietly(argv, cli_into_closed_pipe):
    """`roverswarm reproduce --help | head -1`: the reader goes away before the output ends; the
    command stops with the shell's code for it (141, as `yes | head`), saying nothing."""
    done = cli_into_closed_pipe(*argv)
    said = done.stderr
    assert done.returncode == SIGPIPE_EXIT and "Traceback" not in said and "Error" not in said, said


@pytest.mark.parametrize(
    "args, notes",
    [
        (["--scenario", "paper-2", "--episodes", "400", "--log-every", "200"], ["no update will run", "no --out"]),
        (
            ["--scenario", "paper-2", "--episodes", "400", "--log-every", "200", "--warmup", "5000", "--out", "{out}"],
            [],
        ),
        (["--scenario", "paper-2", "--episodes", "2000", "--out", "{out}"], []),  # 50,000 transitions
        (["--preset", "mappo", "--scenario", "paper-2", "--episodes", "400", "--log-every", "200"], ["no --out"]),
    ],
)
def test_train_says_before_it_starts_when_a_run_would_update_nothing_or_keep_nothing(
    args, notes, tmp_path, capsys, monkeypatch
):
    """An off-policy run shorter than its --warmup ends with its networks as initialised (25 steps
    x 400 episodes = 10,000 transitions, against 25,600); a run without --out keeps nothing."""
    import roverswarm.cli as cli

    reached = []

    def stopped(config, out=None, **kwargs):
        reached.append(config)
        raise RunStopped("stopped before training, by the test")

    monkeypatch.setattr(cli, "train", stopped)
    main(["train", *(a.replace("{out}", str(tmp_path / "run")) for a in args)])
    assert len(reached) == 1  # the command was valid and got as far as training
    captured = capsys.readouterr()
    said = " ".join((captured.out + captured.err).split()).split("note: ")[1:]  # lines wrap at the terminal's width
    assert len(said) == len(notes) and all(n in line for n, line in zip(notes, said)), said
    if notes[:1] == ["no update will run"]:
        assert "--warmup 25600" in said[0] and "--episodes >= 1024" in said[0]
