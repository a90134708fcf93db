"""``roverswarm finetune``: the gradient of the episode reward through the environment.

The objective's value is checked against the environment stepped in a plain Python loop, the
counts' slope against the sigmoid's written out in NumPy, the fine-tune against a learning
effect (a barely trained run's deterministic policy gains reward on held-out layouts), and a
stopped fine-tune against one that ran through.
"""

from __future__ import annotations

import dataclasses
import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm import train
from roverswarm.cli import main
from roverswarm.config import config_to_json, with_options
from roverswarm.env.mars import reset, step_env
from roverswarm.env.scenarios import padded_scenario, sized
from roverswarm.errors import RunStopped, UserError
from roverswarm.evaluate import evaluate_run
from roverswarm.finetune import RECORD, FinetuneConfig, episode_objective, finetune, smooth_count
from roverswarm.presets import ANYSIZE
from roverswarm.runs import CHECKPOINT, CONFIG, Run
from roverswarm.storage import read_arrays


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """The anysize preset's network kind (each rover's nearest entities), shrunk: swarms of 2
    and 3, 200 episodes (barely trained)."""
    config = dataclasses.replace(
        with_options(ANYSIZE, {"hidden": (32, 32), "epochs": 2, "minibatches": 2}),
        scenario="paper-2..3",
        size_curriculum=0,
        episodes=200,
        seeds=2,
        num_envs=4,
        log_every=100,
    )
    out = tmp_path_factory.mktemp("small") / "run"
    train(config, out=out, progress=False)
    return out


def settings(run, out, **changes) -> FinetuneConfig:
    return FinetuneConfig(run=run, out=out, **{"iterations": 4, "envs": 4, **changes})


def test_a_count_keeps_its_value_and_takes_the_sigmoids_slope():
    gaps = jnp.array([[-0.03, 0.01, 0.2], [0.05, -0.2, jnp.inf]])
    tau = 0.02
    np.testing.assert_allclose(smooth_count(gaps, tau), [1.0, 1.0], atol=1e-6)  # the count, to rounding
    slope = jax.grad(lambda g: jnp.sum(smooth_count(g, tau)))(gaps)
    g = np.array(gaps)
    s = 1 / (1 + np.exp(g / tau))  # sigmoid(-g / tau)
    np.testing.assert_allclose(slope, -s * (1 - s) / tau, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("stop_when_complete", [False, True])
def test_the_objective_is_the_episode_reward_stepped_in_python(small_run, tmp_path, stop_when_complete):
    """Its value: the environment's reward summed over the rovers and steps, over N^2, as a
    plain loop of ``step_env`` with the policy's clipped mean gives it (a swarm of 2 in the
    padded layout of 3); with --stop-when-complete, up to the step that observes the last POI."""
    trained = Run(small_run)
    config = dataclasses.replace(trained.config, stop_when_complete=stop_when_complete)
    run = Run.of(config, trained.learner)
    objective, params = episode_objective(run, settings(small_run, tmp_path))
    actor = jax.tree.map(lambda x: x[1], run.learner.actor)
    state = reset(jax.random.PRNGKey(3), sized(padded_scenario("paper-2..3"), 2))[1]
    if stop_when_complete:  # rover 0 beside the one POI left to observe: the episode ends at its first step
        state = state.replace(
            observed=state.observed.at[1].set(True), rover_pos=state.rover_pos.at[0].set(state.poi_pos[0] + 0.02)
        )
    value, counts = objective(actor, state)
    policy = trained.policy(1)
    total, contacts, steps = 0.0, 0.0, 0
    for _ in range(params.max_steps):
        action = policy.act(None, None, state, None, policy.weights, params)
        _, state, rewards, terminated, _, info = step_env(state, action, params)
        total += float(jnp.sum(jnp.where(state.rover_mask, rewards, 0.0)))
        contacts += float(jnp.sum(info["trap_contacts"]))
        steps += 1
        if terminated:
            break
    assert steps == (1 if stop_when_complete else params.max_steps)
    np.testing.assert_allclose(float(value) * 4, total, rtol=1e-5)
    assert float(counts[0]) == contacts


def test_a_finetune_raises_the_reward_of_a_barely_trained_run(small_run, tmp_path):
    """On 200 layouts it never trained on, every seed's deterministic policy gains reward."""
    out = tmp_path / "tuned"
    finetune(settings(small_run, out, iterations=60, envs=16, lr=1e-3), progress=False)

    def scores(folder):
        rows = evaluate_run(folder, 200, seed=7, scenario="paper-2")
        return np.array([r["normalized_score"] for r in rows if r["policy"] not in ("random", "oracle")])

    before, after = scores(small_run), scores(out)
    assert np.all(after > before + 0.1), (before, after)


def test_a_stopped_finetune_resumes_to_the_numbers_of_one_that_ran_through(small_run, tmp_path, monkeypatch):
    whole = tmp_path / "whole"
    finetune(settings(small_run, whole, iterations=6, checkpoint_every=2), progress=False)

    import roverswarm.finetune as module

    class StopAtThree(module.StopFlag):
        checks = 0

        @property
        def raised(self):
            StopAtThree.checks += 1
            return StopAtThree.checks >= 3  # one check an iteration: after the third

        @raised.setter
        def raised(self, value):
            pass

    parted = tmp_path / "parted"
    monkeypatch.setattr(module, "StopFlag", StopAtThree)
    with pytest.raises(RunStopped, match="interrupted at iteration 3; state saved: give the same command to resume"):
        finetune(settings(small_run, parted, iterations=6, checkpoint_every=2), progress=False)
    assert json.loads((parted / RECORD).read_text())["iterations_done"] == 3
    monkeypatch.undo()
    finetune(settings(small_run, parted, iterations=6, checkpoint_every=2), progress=False)
    a, b = (read_arrays(folder / CHECKPOINT, "learner/actor/") for folder in (whole, parted))
    assert a.keys() == b.keys()
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    assert (parted / "finetune.csv").read_text() == (whole / "finetune.csv").read_text()
    # killed after the state was saved, before the checkpoint: the same command writes it again
    shutil.copyfile(small_run / CHECKPOINT, parted / CHECKPOINT)
    finetune(settings(small_run, parted, iterations=6, checkpoint_every=2), progress=False)
    b = read_arrays(parted / CHECKPOINT, "learner/actor/")
    for key in a:
        np.testing.assert_array_equal(a[key], b[key])
    with pytest.raises(UserError, match="holds a fine-tune of other settings"):  # resumed only as it was begun
        finetune(settings(small_run, parted, iterations=7, checkpoint_every=2), progress=False)
    # a run of its own, evaluated as any run, also at a size it never trained on
    rows = evaluate_run(parted, 20, scenario="paper-5")
    assert {r["policy"] for r in rows} == {"random", "oracle", "mappo seed 0", "mappo seed 1"}


def test_bad_finetunes_are_one_line_and_exit_2(small_run, tiny_config, tmp_path, capsys):
    def refused(argv, message):
        assert main(["finetune", *map(str, argv)]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err

    refused([small_run, "--out", small_run], "is the run itself")
    refused([small_run, "--out", tmp_path / "a", "--lr", "0"], "--lr must be a finite number > 0.0, got 0.0")
    refused([small_run, "--out", tmp_path / "a", "--iterations", "0"], "--iterations must be >= 1")
    refused([small_run, "--out", tmp_path / "a", "--envs", "257"], "--envs must be at most 256 episodes per step")
    off = tmp_path / "off"  # an off-policy run's folder (its networks are never read)
    off.mkdir()
    (off / CONFIG).write_text(config_to_json(tiny_config))
    (off / CHECKPOINT).write_bytes(b"")
    refused([off, "--out", tmp_path / "c"], "finetune needs a run of --algo mappo or ippo")
    assert not (tmp_path / "c").exists()
