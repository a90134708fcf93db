"""Sweeps: a settings file trains every setting (seeds vmapped), evaluates every seed and writes one table."""

from __future__ import annotations

import csv
import re
from types import SimpleNamespace

import imageio.v3 as iio
import jax
import numpy as np
import pytest
import yaml

from roverswarm.animation import episode_frames
from roverswarm.cli import SIGPIPE_EXIT, main
from roverswarm.config import with_options
from roverswarm.errors import UserError
from roverswarm.evaluate import evaluate_run
from roverswarm.experiments.arms import usable_cpus
from roverswarm.experiments.sweep import (
    SweepConfig,
    by_size,
    evaluation,
    gapped,
    load_sweep,
    read_table,
    setting_colours,
    sweep,
)
from roverswarm.rollout import rollout
from roverswarm.runs import Run, read_metrics, write_csv

TINY_PPO = dict(num_envs=4, log_every=100, checkpoint_every=1, hidden=[16], epochs=2, minibatches=2)
TINY = dict(num_envs=4, batch_size=64, buffer_size=4000, warmup=500, log_every=100, checkpoint_every=1, hidden=[32, 32])


@pytest.fixture(scope="module")
def finished(tmp_path_factory):
    """A sweep of three settings on paper-2 (the first is the shared tiny config, the last starts
    from another preset: MAPPO), trained and evaluated."""
    folder = tmp_path_factory.mktemp("sweep")
    spec = {
        "preset": "default",
        "scenarios": ["paper-2"],
        "seeds": 2,
        "episodes": 400,
        "settings": {
            "plain": dict(TINY),
            "shared-td3": {**TINY, "share_parameters": True, "twin_critics": True},
            "mappo": {"preset": "mappo", **TINY_PPO},
        },
    }
    (folder / "sweep.yaml").write_text(yaml.safe_dump(spec))
    config = SweepConfig(folder / "sweep.yaml", folder / "out", eval_episodes=50)
    return config, sweep(config, live=False)


def test_a_sweep_writes_one_row_per_run_with_every_seed(finished, tiny_config):
    config, table = finished
    with open(config.out / "sweep.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    runs = load_sweep(config.file, config.out)
    assert [r["setting"] for r in rows] == [run.algorithm for run in runs] == ["mappo", "plain", "shared-td3"]
    by_name = {run.algorithm: run.config for run in runs}  # (the YAML was written with sorted keys)
    assert by_name["plain"] == with_options(tiny_config, {"episodes": 400, "seeds": 2, "scenario": "paper-2"})
    assert by_name["shared-td3"].learner.share_parameters and by_name["shared-td3"].learner.twin_critics
    assert by_name["mappo"].learner.algo == "mappo" and by_name["mappo"].nearest_first
    for row, run in zip(rows, runs):  # the scores are the deterministic evaluation's, seed by seed
        evaluated = evaluate_run(run.folder, episodes=50)
        scores = [f"{r['normalized_score']:.2f}" for r in evaluated[2:]]
        assert row["scores"] == " / ".join(scores) and len(scores) == 2
        assert float(row["min_score"]) == pytest.approx(min(r["normalized_score"] for r in evaluated[2:]))
        assert float(row["oracle_trap_contacts"]) == pytest.approx(evaluated[1]["trap_contacts"])
        assert float(row["random_reward"]) == pytest.approx(evaluated[0]["episode_reward"])
        assert float(row["train_minutes"]) > 0
    assert "shared-td3" in table.read_text()
    assert (config.out / "sweep.png").stat().st_size > 10_000


@pytest.mark.parametrize("setting", ["mappo", "shared-td3"])
def test_render_draws_a_trained_run_in_its_own_environment(finished, setting, tmp_path, capsys):
    config, _ = finished
    run = Run(next(r.folder for r in load_sweep(config.file, config.out) if r.algorithm == setting))
    out = tmp_path / "episode.gif"
    assert main(["render", "--policy", str(run.folder), "--policy-seed", "1", "--seed", "3", "--out", str(out)]) == 0
    policy = run.policy(1)  # the run's seed 1, deterministic, on the run's own scenario
    episode = rollout(policy, jax.random.PRNGKey(3), run.params, num_episodes=1)
    expected = episode_frames(episode, run.params, 0, label=f"paper-2 {policy.name}").frames[-1]
    np.testing.assert_array_equal(iio.imread(out.with_suffix(".png")), expected)
    assert sum(1 for _ in iio.imiter(out)) == run.params.max_steps + 1
    capsys.readouterr()
    assert main(["render", "--policy", str(run.folder), "--scenario", "paper-3", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "was trained for 2 rovers, 2 POIs, 2 traps (paper-2); scenario 'paper-3' has 3 rovers" in err
    assert err.count("\n") == 1


def test_a_rerun_keeps_finished_runs(finished, monkeypatch):
    import roverswarm.experiments.pool as pool_module

    config, _ = finished
    monkeypatch.setattr(pool_module, "train", lambda *a, **k: pytest.fail("a finished run was trained again"))
    sweep(config, live=False)


def test_a_rerun_into_a_closed_pipe_ends_quietly_with_its_table_written(finished, cli_into_closed_pipe):
    """`roverswarm sweep FILE | head -0`: the live table's last print meets the closed pipe; the
    command ends with the shell's code for it (141), not rich's 1 of a stopped run, and the
    table is written as before."""
    config, table = finished
    before = table.read_text()
    table.unlink()
    done = cli_into_closed_pipe("sweep", str(config.file), "--out", str(config.out), "--eval-episodes", "50")
    assert done.returncode == SIGPIPE_EXIT and "Traceback" not in done.stderr, done.stderr
    assert table.read_text() == before


def test_a_sweep_of_more_episodes_extends_its_finished_runs_and_refuses_fewer(finished, tmp_path):
    """The sweep file's episodes raised: the finished run is resumed to the new length (as
    `train --resume RUN --episodes M`), its table row says so; lowered: one line, nothing trained."""
    import shutil

    from roverswarm.storage import trained_episodes

    config, _ = finished
    out = shutil.copytree(config.out, tmp_path / "out")

    def sweep_of(episodes):
        spec = {"preset": "default", "scenarios": ["paper-2"], "seeds": 2, "episodes": episodes}
        spec["settings"] = {"mappo": {"preset": "mappo", **TINY_PPO}}
        (tmp_path / "sweep.yaml").write_text(yaml.safe_dump(spec))
        return SweepConfig(tmp_path / "sweep.yaml", out, eval_episodes=50)

    longer = sweep_of(600)
    (run,) = load_sweep(longer.file, out)
    assert trained_episodes(run.folder / "checkpoint.npz") == 400
    sweep(longer, live=False)
    assert trained_episodes(run.folder / "checkpoint.npz") == 600
    assert [r["episodes"] for r in read_table(out / "sweep.csv")] == [600]
    with pytest.raises(UserError, match=r"other settings \(600 episodes, more than 400\)"):
        sweep(sweep_of(400), live=False)


def test_an_evaluation_is_kept_until_the_run_is_trained_further(finished, tmp_path, monkeypatch):
    """A run's evaluation.csv serves the same evaluation episodes of the same training length;
    a run trained further since (extended by `train --resume RUN --episodes M`), or a table
    that does not say how long its run trained, is evaluated again."""
    import dataclasses
    import shutil

    import roverswarm.evaluate as evaluate_module

    config, _ = finished
    run = load_sweep(config.file, config.out)[1]
    run = dataclasses.replace(run, folder=shutil.copytree(run.folder, tmp_path / "run"))
    calls = []
    fresh = [{"policy": "random", "episode_reward": -1.0}]
    monkeypatch.setattr(evaluate_module, "evaluate_run", lambda folder, episodes: calls.append(episodes) or fresh)
    kept = read_table(run.folder / "evaluation.csv")
    assert {r["trained_episodes"] for r in kept} == {400} and evaluation(run, 50) == kept and calls == []
    for stale in ({"trained_episodes": 200}, {}):
        rows = [{**{k: v for k, v in r.items() if k != "trained_episodes"}, **stale} for r in kept]
        write_csv(run.folder / "evaluation.csv", rows)
        assert evaluation(run, 50) == [{**fresh[0], "episodes": 50, "trained_episodes": 400}]
    assert calls == [50, 50] and read_table(run.folder / "evaluation.csv") == evaluation(run, 50)


def test_rows_past_the_checkpoint_count_nowhere(finished, tmp_path):
    """An extension killed between its metrics.csv and its checkpoint leaves rows of episodes
    never saved: the sweep table, Table I's curves, the progress and the evaluation's key read
    the checkpoint's rows only, and the run stays finished."""
    import dataclasses
    import shutil

    from roverswarm.experiments.arms import episodes_done, episodes_logged, status
    from roverswarm.experiments.results import load
    from roverswarm.experiments.sweep import table_row

    config, _ = finished
    saved = load_sweep(config.file, config.out)[1]
    run = dataclasses.replace(saved, folder=shutil.copytree(saved.folder, tmp_path / "run"))
    rows = read_metrics(run.folder / "metrics.csv")
    ahead = [{**r, "episodes": r["episodes"] + 100, "episode_reward": 1e6, "wall_seconds": 1e6} for r in rows[-2:]]
    write_csv(run.folder / "metrics.csv", rows + ahead)
    evaluated = evaluation(saved, 50)
    assert table_row(run, evaluated) == table_row(saved, evaluated)
    assert episodes_done(run) == 400 and status(run) == "done"
    assert episodes_logged(run) == 500  # a running job's progress reads every chunk's row
    ours, theirs = load(run, {}), load(saved, {})
    np.testing.assert_array_equal(ours.curves, theirs.curves)
    np.testing.assert_array_equal(ours.chunk_seconds, theirs.chunk_seconds)
    # killed between the extension's first checkpoint and its config.json: refused, not finished
    with np.load(run.folder / "checkpoint.npz") as data:
        arrays = {k: data[k] for k in data.files}
    np.savez(run.folder / "checkpoint.npz", **{**arrays, "episodes": np.asarray(500)})
    with pytest.raises(UserError, match="other settings .500 episodes trained, more than 400: an extension stopped"):
        status(run)


@pytest.mark.skipif(len(usable_cpus()) < 2, reason="needs 2 CPUs")
def test_jobs_train_a_sweep_side_by_side_to_the_numbers_of_one_process(finished, tmp_path, capsys, monkeypatch):
    """Two settings of the fixture's sweep (trained one after another in this process) again
    with --jobs 2, each run in its own process: the same metrics, wall time aside, and the same
    table."""
    import roverswarm.experiments.pool as pool_module

    monkeypatch.setattr(pool_module, "run_local", lambda *a, **k: pytest.fail("a run trained in this process"))
    config, _ = finished
    spec = yaml.safe_load(config.file.read_text())
    spec["settings"] = {k: v for k, v in spec["settings"].items() if k != "mappo"}
    (tmp_path / "two.yaml").write_text(yaml.safe_dump(spec))
    sweep(SweepConfig(tmp_path / "two.yaml", tmp_path / "out", eval_episodes=50, jobs=2), live=False)
    for setting in spec["settings"]:
        ours, theirs = (
            read_table(out / "runs" / "paper-2" / setting / "metrics.csv") for out in (tmp_path / "out", config.out)
        )
        assert [{k: v for k, v in r.items() if k != "wall_seconds"} for r in ours] == [
            {k: v for k, v in r.items() if k != "wall_seconds"} for r in theirs
        ]
    ours, theirs = (read_table(out / "sweep.csv") for out in (tmp_path / "out", config.out))
    kept = ("setting", "scores", "mean_score", "collisions", "trap_contacts")
    assert [{k: r[k] for k in kept} for r in ours] == [
        {k: r[k] for k in kept} for r in theirs if r["setting"] != "mappo"
    ]
    for jobs in (0, len(usable_cpus()) + 1):
        assert main(["sweep", str(tmp_path / "two.yaml"), "--out", str(tmp_path / "out"), "--jobs", str(jobs)]) == 2
        assert f"--jobs must be in [1, {len(usable_cpus())}]" in capsys.readouterr().err


@pytest.mark.parametrize(
    "spec, message",
    [
        ({"settings": {"a": {"learning_rate": 1}}}, "bad.yaml': setting 'a': unknown option 'learning_rate'"),
        ({"scenarios": ["mars-1"], "settings": {"a": {}}}, "unknown scenario 'mars-1'"),
        ({"scenarios": ["paper-99"], "settings": {"a": {}}}, "scenario 'paper-99': every N must be in 2..64"),
        ({"preset": "anysize", "scenarios": ["paper-3"], "settings": {"a": {}}}, "needs a range of swarm sizes"),
        ({"preset": "fast", "settings": {"a": {}}}, "preset must be one of default, reference, swarm"),
        ({"settings": {"a": {"share_parameters": True, "ensemble": 2}}}, "--share-parameters does not compose"),
        ({"settings": {}}, "settings must map names to options"),
        ({"settings": {"a": {"preset": "fast"}}}, "bad.yaml': setting 'a': preset must be one of"),
        ({"runs": 3, "settings": {"a": {}}}, "unknown keys ['runs']"),
        # a setting's name becomes a folder: one safe path component only
        ({"settings": {"/srv/victim": {}}}, "setting name: '/srv/victim' cannot name a folder"),
        ({"settings": {"../../escape": {}}}, "setting name: '../../escape' cannot name a folder"),
        ({"settings": {"a..b": {}}}, "setting name: 'a..b' cannot name a folder"),
        ({"settings": {"..": {}}}, "setting name: '..' cannot name a folder"),
        ({"settings": {"a b": {}}}, "setting name: 'a b' cannot name a folder"),
        ({"settings": {3: {}}}, "setting name: 3 cannot name a folder"),
        ({"settings": {"Plain": {}, "plain": {}}}, "setting names 'Plain' and 'plain' differ only in case"),
        # what names a row cannot be changed by a setting
        ({"settings": {"a": {"scenario": "paper-4"}}}, "setting 'a' may not set 'scenario' (it names the row)"),
        ({"settings": {"a": {"mission": "m.yaml"}}}, "setting 'a' may not set 'mission' (it names the row)"),
        ({"settings": {"a": {"seeds": 3}}}, "setting 'a' may not set 'seeds' (it names the row)"),
        ({"scenarios": ["paper-2", "paper-2"], "settings": {"a": {}}}, "scenarios must each be given once"),
        # a value the config refuses names the file and the setting it came from
        ({"settings": {"a": {"beta": 2.0}}}, "bad.yaml': setting 'a' on paper-3: --beta must be in [0, 1]"),
        # what training refuses too, before the first run trains
        (
            {
                "preset": "anysize",
                "scenarios": ["paper-2..3"],
                "episodes": 2000,
                "settings": {"a": {"anneal_episodes": 1000}},
            },
            "setting 'a' on paper-2..3: --episodes 2000 goes past --anneal-episodes 1000",
        ),
    ],
)
def test_bad_sweep_files_are_one_line_and_exit_2(spec, message, tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(spec))
    with pytest.raises(UserError, match=re.escape(message)):
        load_sweep(path, tmp_path / "out")
    assert main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert "mission_text" not in err  # the known options listed are those a user can give


def test_a_name_given_twice_is_refused_before_anything_trains(tmp_path, capsys):
    """YAML keeps the last of two equal keys; a sweep file refuses them, naming the line."""
    path = tmp_path / "twice.yaml"
    path.write_text("scenarios: [paper-2]\nsettings:\n  a: {}\n  a: {buffer_size: 50000}\n")
    assert main(["sweep", str(path), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "line 4: 'a' is given twice" in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_an_out_that_is_a_file_is_refused_as_other_commands_refuse_it(tmp_path, capsys):
    """``--out`` naming a file: the message every command gives, not the system's "File exists"."""
    path, out = tmp_path / "one.yaml", tmp_path / "notes.txt"
    path.write_text("scenarios: [paper-2]\nsettings:\n  a: {}\n")
    out.write_text("kept")
    assert main(["sweep", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"output folder '{out}' is a file (or lies inside one), not a folder" in err and err.count("\n") == 1
    assert out.read_text() == "kept"


def test_numbers_with_an_exponent_are_numbers(tmp_path):
    """YAML 1.1 reads 3e-4 (no dot) and 1.0e5 (no sign) as strings; a sweep file reads them as
    JSON and YAML 1.2 do."""
    path = tmp_path / "lr.yaml"
    path.write_text("scenarios: [paper-2]\nsettings:\n  a: {actor_lr: 3e-4, critic_lr: 1.0e-3, grad_clip: 5E+1}\n")
    (run,) = load_sweep(path, tmp_path / "out")
    assert (run.config.learner.actor_lr, run.config.learner.critic_lr, run.config.learner.grad_clip) == (3e-4, 1e-3, 50)


def test_a_sweep_over_a_range_of_sizes_gives_a_row_per_size(tmp_path):
    """The anysize preset trains one policy for paper-2..3; the sweep evaluates it at 2 and 3
    rovers, one row per size (its setting named with the range), each row that size's
    evaluation; a figure orders its scenarios by swarm size."""
    spec = {
        "preset": "anysize",
        "scenarios": ["paper-2..3"],
        "seeds": 2,
        "episodes": 200,
        "settings": {"tiny": {**TINY_PPO, "size_curriculum": 0, "anneal_episodes": 200, "entity_nearest": 2}},
    }
    (tmp_path / "any.yaml").write_text(yaml.safe_dump(spec))
    config = SweepConfig(tmp_path / "any.yaml", tmp_path / "out", eval_episodes=20)
    sweep(config, live=False)
    rows = read_table(config.out / "sweep.csv")
    assert [(r["scenario"], r["setting"]) for r in rows] == [(f"paper-{n}", "tiny (paper-2..3)") for n in (2, 3)]
    (run,) = load_sweep(config.file, config.out)
    evaluated = evaluate_run(run.folder, episodes=20)
    for row, size in zip(rows, ("paper-2", "paper-3")):
        mine = [r for r in evaluated if r["scenario"] == size]
        assert row["scores"] == " / ".join(f"{r['normalized_score']:.2f}" for r in mine[2:])
        assert row["random_reward"] == pytest.approx(mine[0]["episode_reward"], abs=1e-3)
    assert by_size(["paper-10", "spread-3", "paper-2", "paper-3"]) == ["paper-2", "spread-3", "paper-3", "paper-10"]


def test_a_setting_name_cannot_write_outside_out(tmp_path, capsys):
    """The issue's case: an absolute name (and a relative escape) trains nothing and writes nothing."""
    victim = tmp_path / "victim"
    victim.mkdir()
    for name in (str(victim), "../../victim"):
        path = tmp_path / "s.yaml"
        path.write_text(f"scenarios: [paper-2]\nepisodes: 1000\nsettings:\n  {name}: {{buffer_size: 50000}}\n")
        assert main(["sweep", str(path), "--out", str(tmp_path / "sw" / "x")]) == 2
        assert "cannot name a folder" in capsys.readouterr().err
    assert list(victim.iterdir()) == [] and not (tmp_path / "sw").exists()


def test_the_score_against_n_script_joins_tables_by_rover_count(finished, tmp_path, monkeypatch, capsys):
    """docs/results/swarm/score_vs_n.py: the paper-N rows of several sweep tables, labelled with
    their budget and sorted by N; other scenarios are left out."""
    import runpy
    import sys
    from pathlib import Path

    config, _ = finished
    rows = read_table(config.out / "sweep.csv")
    other = tmp_path / "other.csv"
    write_csv(other, [{**rows[1], "scenario": "paper-1"}, {**rows[0], "scenario": "spread-3", "episodes": 60000}])
    out = tmp_path / "combined"
    script = Path(__file__).parents[1] / "docs" / "results" / "swarm" / "score_vs_n.py"
    monkeypatch.setattr(sys, "argv", ["score_vs_n.py", str(config.out / "sweep.csv"), str(other), "--out", str(out)])
    runpy.run_path(str(script), run_name="__main__")
    combined = read_table(out.with_suffix(".csv"))
    assert [(r["scenario"], r["setting"]) for r in combined] == [
        ("paper-1", "plain (0.4k)"),
        ("paper-2", "mappo (0.4k)"),
        ("paper-2", "plain (0.4k)"),
        ("paper-2", "shared-td3 (0.4k)"),
    ]
    assert [r["scores"] for r in combined[1:]] == [r["scores"] for r in rows]
    assert combined[0]["train_minutes"] == pytest.approx(rows[1]["train_minutes"])
    assert "| paper-1 | plain (0.4k) | 2 |" in out.with_suffix(".md").read_text()
    assert out.with_suffix(".png").stat().st_size > 10_000
    assert "4 rows" in capsys.readouterr().out


def test_a_line_through_a_settings_scores_stops_at_a_scenario_it_did_not_run():
    """Scenarios 0, 1, 3 and 5 of the figure run, 2 and 4 not: three pieces of line, in order."""
    xs, ys = gapped([3, 0, 1, 5], [30.0, 0.0, 10.0, 50.0])
    assert xs[:2] == [0, 1] and ys[:2] == [0.0, 10.0]
    assert np.isnan(xs[2]) and np.isnan(ys[2]) and (xs[3], ys[3]) == (3, 30.0)
    assert np.isnan(xs[4]) and (xs[5], ys[5]) == (5, 50.0) and len(xs) == 6
    assert gapped([0, 1, 2], [1.0, 2.0, 3.0]) == ([0, 1, 2], [1.0, 2.0, 3.0])


@pytest.mark.parametrize("count", [3, 10, 11, 14])
def test_every_setting_of_a_figure_has_a_colour_of_its_own_up_to_twenty(count):
    """Up to ten settings keep matplotlib's default colours (the figures drawn before); from
    eleven on (the any-size figure has twelve) none repeats."""
    from matplotlib import rcParams
    from matplotlib.colors import to_hex

    colours = [to_hex(c) for c in setting_colours(count)]
    assert len(set(colours)) == count
    if count <= 10:
        assert colours == [to_hex(c) for c in rcParams["axes.prop_cycle"].by_key()["color"][:count]]


def _sweep_on_ray(file, out) -> dict[str, object]:
    """On one local Ray cluster: `roverswarm sweep FILE --backend ray --address ...` as a
    command, sent SIGTERM, SIGINT and SIGTERM once its task trains (its exit code, output,
    the rows its run saved, the locks left); then the same sweep again in this process while
    a worker is killed (the pids killed)."""
    import signal
    import subprocess
    import sys
    import time

    from local_ray import killing_a_worker, local_ray, wait_for_training

    with local_ray() as address:
        argv = ["sweep", str(file), "--out", str(out), "--eval-episodes", "50"]
        argv += ["--backend", "ray", "--address", address]
        driver = subprocess.Popen(
            [sys.executable, "-m", "roverswarm.cli", *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        wait_for_training()
        time.sleep(1.0)  # past the task's first look at the stop flag
        for signum in (signal.SIGTERM, signal.SIGINT, signal.SIGTERM):
            driver.send_signal(signum)
            time.sleep(0.3)
        stdout, stderr = driver.communicate(timeout=600)
        metrics = out / "runs" / "paper-2" / "plain" / "metrics.csv"
        stopped = {
            "code": driver.returncode,
            "stdout": stdout,
            "stderr": stderr,
            "rows": read_table(metrics) if metrics.exists() else [],
            "locks": list(out.rglob(".lock")),
        }
        with killing_a_worker(after=0.0) as killed:
            sweep(SweepConfig(file, out, eval_episodes=50, backend="ray", address=address), live=False)
    return {**stopped, "killed": killed}


def test_a_sweep_on_ray_stops_on_a_signal_resumes_and_retries_a_killed_worker(finished, tmp_path):
    """`sweep --backend ray`: a finished run is kept; the first signal stops the other's task
    at its next chunk, whose files come back with a checkpoint (later signals ignored, the
    command ends in its message, exit 1, no lock left); the rerun sends them with the task,
    which resumes (the saved rows kept as they were, wall time too), is killed, retried, and
    ends with the numbers and table of the local backend."""
    import multiprocessing
    import shutil

    from local_ray import CHILD_TIMEOUT

    config, _ = finished
    spec = yaml.safe_load(config.file.read_text())
    spec["settings"] = {k: v for k, v in spec["settings"].items() if k != "mappo"}
    spec["settings"]["plain"]["episodes"] = 4000  # 40 chunks: still training when stopped
    (tmp_path / "two.yaml").write_text(yaml.safe_dump(spec))
    out, local = tmp_path / "out", tmp_path / "local"
    kept = out / "runs" / "paper-2" / "shared-td3"
    for root in (out, local):
        shutil.copytree(config.out / "runs" / "paper-2" / "shared-td3", root / kept.relative_to(out))
    sweep(SweepConfig(tmp_path / "two.yaml", local, eval_episodes=50), live=False)  # the local backend's numbers
    with multiprocessing.get_context("spawn").Pool(1) as pool:
        result = pool.apply_async(_sweep_on_ray, (tmp_path / "two.yaml", out)).get(timeout=CHILD_TIMEOUT)
    assert result["code"] == 1 and "Traceback" not in result["stderr"], result["stderr"]
    assert "interrupted; every running run saved a checkpoint" in result["stderr"]
    assert "stops at its next chunk" in result["stdout"] and result["locks"] == []
    saved = result["rows"]
    assert 0 < len(saved) < 80, "the run must be stopped mid-way"
    assert result["killed"], "no worker was killed"
    ours, theirs = (read_table(root / "runs" / "paper-2" / "plain" / "metrics.csv") for root in (out, local))
    assert ours[: len(saved)] == saved  # resumed from what came back, not trained again
    assert [{k: v for k, v in r.items() if k != "wall_seconds"} for r in ours] == [
        {k: v for k, v in r.items() if k != "wall_seconds"} for r in theirs
    ]
    original = config.out / kept.relative_to(out) / "checkpoint.npz"
    assert (kept / "checkpoint.npz").read_bytes() == original.read_bytes()
    table, local_table = (read_table(root / "sweep.csv") for root in (out, local))
    columns = ("setting", "scores", "mean_score", "collisions", "trap_contacts")
    assert [{k: r[k] for k in columns} for r in table] == [{k: r[k] for k in columns} for r in local_table]
    assert not list(out.rglob(".lock"))


class _Ref:
    def __init__(self, value):
        self.value = value


class _InlineRay:
    """Ray as ``run_ray`` uses it, each task done as it is sent: its result is ``results[name]``."""

    exceptions = SimpleNamespace(RayError=RuntimeError)

    def __init__(self, results):
        self.results = results

    def is_initialized(self):
        return True

    def remote(self, **options):
        from roverswarm.experiments.remote import Board

        def wrap(target):
            if target is not Board:
                return SimpleNamespace(remote=lambda config, files, board, name, start: _Ref(self.results[name]))
            board = Board()
            call = lambda method: SimpleNamespace(remote=lambda *a: _Ref(getattr(board, method)(*a)))  # noqa: E731
            return SimpleNamespace(remote=lambda: SimpleNamespace(**{m: call(m) for m in ("ask", "report", "reports")}))

        return wrap

    def wait(self, refs, num_returns, timeout):
        return refs[:num_returns], refs[num_returns:]

    def get(self, ref):
        return ref.value


def test_an_error_on_one_ray_run_still_collects_the_other_runs_files(finished, tmp_path, monkeypatch):
    """The command fails on one finished task's files or table row (here a damaged table, read
    as an evaluation.csv with a header only reads): every other task's run still comes back to
    its folder, then the error is raised."""
    import dataclasses

    from roverswarm.experiments import remote
    from roverswarm.experiments.live import Summary

    config, _ = finished
    saved = load_sweep(config.file, config.out)
    runs = [dataclasses.replace(r, folder=tmp_path / r.algorithm) for r in saved]
    monkeypatch.setattr(
        remote, "_ray", lambda: _InlineRay({r.name: (remote.read_files(r.folder), None) for r in saved})
    )

    def on_finish(run):
        if run.name == runs[0].name:
            raise IndexError("list index out of range")

    with pytest.raises(IndexError, match="list index out of range"):
        remote.run_ray(runs, Summary(runs, set()), None, 0, on_finish)
    for run, original in zip(runs, saved):
        assert remote.read_files(run.folder) == remote.read_files(original.folder)


def test_a_ray_sweep_sends_nothing_while_a_run_folder_is_being_written(finished, tmp_path, capsys, monkeypatch):
    import socket
    import subprocess
    import sys

    from roverswarm.experiments import remote

    monkeypatch.setattr(remote, "_ray", lambda: pytest.fail("Ray was started"))
    config, _ = finished
    run = tmp_path / "out" / "runs" / "paper-2" / "plain"
    run.mkdir(parents=True)
    writer = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])  # a live writer holds the folder
    try:
        (run / ".lock").write_text(f"{writer.pid} {socket.gethostname()}")
        with pytest.raises(UserError, match=f"run 'paper-2 plain': '{run}' is being written by process {writer.pid}"):
            sweep(SweepConfig(config.file, tmp_path / "out", eval_episodes=50, backend="ray"), live=False)
    finally:
        writer.kill()
        writer.wait()
    assert not (tmp_path / "out" / ".lock").exists() and not (tmp_path / "out" / "runs" / "paper-2" / "mappo").exists()
    argv = ["sweep", str(config.file), "--out", str(tmp_path / "out")]
    assert main([*argv, "--address", "x:1"]) == 2
    assert "--address needs --backend ray" in capsys.readouterr().err
    assert main([*argv, "--backend", "ray", "--jobs", "1"]) == 2
    assert "--jobs is for --backend local" in capsys.readouterr().err
