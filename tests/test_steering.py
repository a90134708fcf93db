"""The safety layer (``--shield``): against a plain NumPy loop over its rule, what it leaves
alone, what it prevents, and how the commands that drive a trained policy take it."""

from __future__ import annotations

import cmath
import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm.env import get_scenario, reset, step_env
from roverswarm.env.mars import ACTION_SIZE, masks_of, trap_radii
from roverswarm.env.scenarios import padded_scenario, sized
from roverswarm.policies import RANDOM, shielded
from roverswarm.rollout import rollout
from roverswarm.steering import FAILED_MARGIN, KEEP_OUT_MARGIN, SHIELD_STEPS, shield_actions

shield = jax.jit(shield_actions)


def _shield_reference(state, actions, params) -> tuple[np.ndarray, np.ndarray]:
    """The safety layer rover by rover, in complex numbers: the velocity the clipped action
    asks for, from where the rover will be after this step; every existing obstacle in order
    (the other rovers at their next positions, then the traps), twice over; a blocking one
    turns the heading to its keep-out circle's tangent on the side the heading leans to (the
    circle of a failed rover with the smaller margin).
    Returns the actions [N, 2] and [N] bool: a rover came within 1e-4 of one of the rule's
    thresholds, where float32 and float64 may decide otherwise."""
    pos, vel = np.asarray(state.rover_pos, float), np.asarray(state.rover_vel, float)
    masks = masks_of(state)
    n, t = pos.shape[0], np.asarray(state.trap_pos).shape[0]
    rovers = np.ones(n, bool) if masks is None else np.asarray(masks.rovers)
    traps = np.ones(t, bool) if masks is None else np.asarray(masks.traps)
    decay = 1.0 - float(params.damping)
    gain = float(params.sensitivity) / float(params.mass) * float(params.dt)
    radii = np.broadcast_to(np.asarray(trap_radii(params), float), (t,))
    frozen = np.asarray(state.time) >= np.asarray(state.fail_step)  # a failed rover stays where it is
    nxt = [complex(*p) + (0 if f else complex(*v) * float(params.dt)) for p, v, f in zip(pos, vel, frozen)]
    out = np.clip(np.asarray(actions, float), -1.0, 1.0)
    near = np.zeros(n, bool)
    for i in range(n):
        v = decay * complex(*vel[i]) + gain * complex(*out[i])
        speed, reach = abs(v), abs(v) * float(params.dt) * SHIELD_STEPS
        heading = v / speed if speed > 1e-9 else 0j
        blockers = [
            (nxt[j], 2 * float(params.rover_radius) + (FAILED_MARGIN if frozen[j] else KEEP_OUT_MARGIN))
            for j in range(n)
            if j != i and rovers[j]
        ]
        blockers += [
            (complex(*np.asarray(state.trap_pos)[k]), radii[k] + float(params.rover_radius) + KEEP_OUT_MARGIN)
            for k in range(t)
            if traps[k]
        ]
        turned, last = False, None
        for k, (centre, keep_out) in enumerate(blockers * 2):
            gap = centre - nxt[i]
            along = (heading.conjugate() * gap).real
            across = (heading.conjugate() * gap).imag
            if last != k % len(
                blockers
            ):  # the tangent of the obstacle that set the heading grazes it: either way, the same
                edges = (along, abs(across) - keep_out, along - reach - keep_out, abs(gap) - keep_out)
                near[i] |= min(abs(e) for e in edges) < 1e-4
            if along > 0 and abs(across) < keep_out and along < reach + keep_out:
                angle = math.asin(min(keep_out / max(abs(gap), 1e-9), 1.0))
                heading = gap / abs(gap) * cmath.exp(-1j * angle if across > 0 else 1j * angle)
                turned, last = True, k % len(blockers)
        if turned:
            a = (speed * heading - decay * complex(*vel[i])) / gain
            a = a / max(1.0, abs(a.real), abs(a.imag))
            out[i] = a.real, a.imag
    return out, near


shield_all = jax.jit(jax.vmap(shield, in_axes=(0, 0, None)))
"""The shield over a batch of layouts [B, ...], jitted (run op by op, its unrolled loop is
hundreds of operations each prepared on its own)."""


def _moving_states(params, count: int, seed: int):
    """``count`` fresh layouts of ``params`` with the rovers already moving (so that some are
    headed for a trap or one another), and random actions [count, N, 2] beyond [-1, 1] at times."""
    keys = jax.random.split(jax.random.PRNGKey(seed), 3)
    states = jax.jit(jax.vmap(lambda k: reset(k, params)[1]))(jax.random.split(keys[0], count))
    vel = jax.random.uniform(keys[1], states.rover_vel.shape, minval=-0.6, maxval=0.6)
    actions = jax.random.uniform(keys[2], (count, params.num_rovers, ACTION_SIZE), minval=-1.3, maxval=1.3)
    failed = states.fail_step.at[::3, 0].set(0)  # rover 0 of every third layout failed: it stays put
    return states.replace(rover_vel=vel, fail_step=failed), actions


@pytest.mark.parametrize("layout", ["paper-5", "padded paper-2..6 with 4"])
def test_the_shield_is_its_rule_rover_by_rover(layout):
    """JAX against the NumPy loop, on layouts where rovers move towards traps and one another
    (a failed rover among them); in a padded layout the empty slots are no obstacle. Rovers
    within 1e-4 of a threshold of the rule are left out (float32 against float64)."""
    params = get_scenario("paper-5") if layout == "paper-5" else sized(padded_scenario("paper-2..6"), 4)
    states, actions = _moving_states(params, 64, seed=1)
    got = np.asarray(shield_all(states, actions, params))
    turned = compared = 0
    for e in range(64):
        state = jax.tree.map(lambda x: x[e], states)
        want, near = _shield_reference(state, actions[e], params)
        np.testing.assert_allclose(got[e][~near], want[~near], atol=2e-5)
        compared += int((~near).sum())
        turned += int(np.any(np.abs(want - np.clip(np.asarray(actions[e]), -1, 1))[~near] > 1e-6))
    assert turned >= 10 and compared >= 0.95 * 64 * 4, (turned, compared)  # the rule was exercised


def test_a_clear_way_passes_the_action_unchanged_and_empty_slots_change_nothing():
    """With the traps far away and the rovers far apart, the shield only clips; in a padded
    layout, whatever sits in the empty slots (here: right ahead of the rovers) changes no
    action of a rover that exists."""
    params = get_scenario("paper-3")
    states, actions = _moving_states(params, 32, seed=2)
    spread = jnp.array([[-50.0, 0.0], [0.0, 0.0], [50.0, 0.0]])
    clear = states.replace(rover_pos=jnp.broadcast_to(spread, states.rover_pos.shape), trap_pos=states.trap_pos + 100.0)
    got = shield_all(clear, actions, params)
    np.testing.assert_array_equal(got, jnp.clip(actions, -1.0, 1.0))

    padded = sized(padded_scenario("paper-2..6"), 3)
    states, actions = _moving_states(padded, 32, seed=3)
    ahead = states.rover_pos[:, :3] + 0.25 * states.rover_vel[:, :3]  # 2.5 steps on the rovers' way
    crowded = states.replace(
        rover_pos=states.rover_pos.at[:, 3:6].set(ahead), trap_pos=states.trap_pos.at[:, 3:6].set(ahead)
    )
    np.testing.assert_array_equal(
        shield_all(states, actions, padded)[:, :3], shield_all(crowded, actions, padded)[:, :3]
    )
    every = lambda s: s.replace(rover_mask=jnp.ones_like(s.rover_mask), trap_mask=jnp.ones_like(s.trap_mask))  # noqa: E731
    turned = shield_all(every(crowded), actions, padded)[:, :3] != shield_all(every(states), actions, padded)[:, :3]
    assert np.asarray(turned).any(axis=-1).mean() > 0.3  # were they there, they would turn the rovers


def test_a_rover_driven_at_a_trap_goes_round_it_behind_the_shield():
    """One rover driven straight at a trap at full throttle: without the shield it drives into
    the trap, behind it the rover passes it untouched and ends past it."""
    params = get_scenario("paper-2")
    _, state = reset(jax.random.PRNGKey(0), params)
    state = state.replace(
        rover_pos=jnp.array([[-0.8, 0.01], [0.0, 0.9]]),
        rover_vel=jnp.zeros((2, 2)),
        trap_pos=state.trap_pos.at[:].set(jnp.array([0.0, -0.9])).at[0].set(jnp.array([0.0, 0.0])),
    )
    push = jnp.array([[1.0, 0.0], [0.0, 0.0]])  # rover 0 east at full force, through the trap at the origin

    def drive(with_shield: bool):
        def body(s, _):
            a = shield_actions(s, push, params) if with_shield else push
            _, s, _, _, _, info = step_env(s, a, params)
            return s, info["trap_contacts"][0]

        return jax.lax.scan(body, state, None, length=params.max_steps)

    end, contacts = jax.jit(drive, static_argnums=0)(False)
    assert contacts.sum() > 0
    end, contacts = jax.jit(drive, static_argnums=0)(True)
    assert contacts.sum() == 0 and float(end.rover_pos[0, 0]) > 0.5  # past the trap, never in it


def test_a_failed_rover_is_kept_at_a_smaller_margin_than_a_working_one():
    """A rover about to pass 0.34 from another's centre (0.30 is touching): the shield turns it
    away from a working rover (keep-out 0.30 + KEEP_OUT_MARGIN) and lets it pass a failed one
    (0.30 + FAILED_MARGIN), which stands still."""
    params = get_scenario("paper-2")
    _, state = reset(jax.random.PRNGKey(0), params)
    touching = 2 * params.rover_radius
    assert touching + FAILED_MARGIN < 0.34 < touching + KEEP_OUT_MARGIN
    state = state.replace(
        rover_pos=jnp.array([[-0.3, 0.34], [0.0, 0.0]]),
        rover_vel=jnp.array([[0.5, 0.0], [0.0, 0.0]]),
        trap_pos=state.trap_pos + 100.0,
    )
    push = jnp.array([[1.0, 0.0], [0.0, 0.0]])  # rover 0 east, past rover 1
    working = shield(state, push, params)
    failed = shield(state.replace(fail_step=state.fail_step.at[1].set(0)), push, params)
    assert float(working[0, 1]) > 0.05  # turned north, away from the working rover
    np.testing.assert_array_equal(failed, push)


def test_random_actions_behind_the_shield_touch_a_tenth_of_the_traps():
    """The same 200 layouts of paper-3: uniform random actions touch traps about 5 times per
    episode; the same actions behind the shield less than a tenth of that."""
    params = get_scenario("paper-3")
    plain = rollout(RANDOM, jax.random.PRNGKey(0), params, 200).stats
    safe = rollout(shielded(RANDOM), jax.random.PRNGKey(0), params, 200).stats
    assert plain.trap_contacts.mean() > 2.0
    assert safe.trap_contacts.mean() < 0.1 * plain.trap_contacts.mean(), (
        safe.trap_contacts.mean(),
        plain.trap_contacts.mean(),
    )


@pytest.mark.parametrize("family", ["on-policy", "off-policy"])
def test_training_behind_the_shield_gives_the_environment_the_shielded_actions(family, tiny_config, tiny_ppo_config):
    """``--shield`` in training: the same fresh networks and key, with and without the layer,
    draw the same first actions (the learner keeps its own), and the environment, given the
    shielded ones, sees far fewer trap contacts."""
    from roverswarm.algos.learner import init_learner
    from roverswarm.algos.ppo import init_ppo
    from roverswarm.config import validate, with_options
    from roverswarm.env.mars import observation_size
    from roverswarm.learners import offpolicy, onpolicy

    base = with_options(tiny_ppo_config if family == "on-policy" else tiny_config, {"scenario": "paper-3"})
    got = {}
    for shield_on in (False, True):
        config = with_options(base, {"shield": shield_on})
        params = validate(config)
        if family == "on-policy":
            program = onpolicy.configure(config, params)
            actor = init_ppo(jax.random.PRNGKey(0), program, params.num_rovers, observation_size(params)).actor
            traj, totals = jax.jit(lambda k: onpolicy.collect(program, params, actor, k))(jax.random.PRNGKey(1))
            first = traj.actions[0]
        else:
            program = offpolicy.configure(config, params)
            learner = init_learner(jax.random.PRNGKey(0), program.learner, params.num_rovers, observation_size(params))
            collected, _, totals = jax.jit(lambda k: offpolicy.collect(program, params, learner, k, 0.5))(
                jax.random.PRNGKey(1)
            )
            first = collected.actions[0]
        got[shield_on] = (np.asarray(first), float(np.sum(totals["trap_contacts"])))
    np.testing.assert_array_equal(got[True][0], got[False][0])
    assert got[False][1] >= 4 and got[True][1] < 0.5 * got[False][1], got


def test_a_run_trained_behind_the_shield_keeps_it(tiny_ppo_config, tmp_path, capsys):
    """Its policies act behind the layer wherever they run (named so; ``evaluate --shield`` adds
    nothing more), and its export holds the layer."""
    from roverswarm import train
    from roverswarm.cli import main
    from roverswarm.config import with_options
    from roverswarm.evaluate import evaluate_run
    from roverswarm.runs import Run

    train(with_options(tiny_ppo_config, {"shield": True, "episodes": 100}), out=tmp_path, progress=False)
    policy = Run(tmp_path).policy(0)
    assert policy.shield and policy.name.endswith(", shielded")
    rows = evaluate_run(tmp_path, episodes=10)
    assert [r["policy"] for r in rows] == ["random", "oracle", "mappo seed 0, shielded", "mappo seed 1, shielded"]
    assert evaluate_run(tmp_path, episodes=10, shield=True) == rows
    assert main(["export", str(tmp_path), "--out", str(tmp_path / "export")]) == 0
    assert "with the safety layer" in " ".join(capsys.readouterr().out.split())
    assert json.loads((tmp_path / "export" / "policy.json").read_text())["shield"]["trained_behind"]
