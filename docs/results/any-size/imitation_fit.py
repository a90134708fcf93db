"""How closely can the anysize actor fit the teacher's actions at all? Plain regression, no RL.

    python docs/results/any-size/imitation_fit.py --rovers 5 --steps 800    # a few minutes
    python docs/results/any-size/imitation_fit.py --rovers 10 --steps 800

Each step rolls out 100 episodes of ``paper-N`` driven by the greedy oracle (``--teacher``'s
labels, :func:`roverswarm.oracle.greedy_plan`) with Gaussian noise of std 0.3 on its actions,
so that states off its path are seen too, and takes one Adam step (1e-3) on the mean squared
distance of the preset's actor's mean action (the nearest-4 view) from the oracle's actions.
Prints that distance as it falls: the floor of ``imitation_loss`` for this network and view.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import optax

from roverswarm.algos.ppo import init_ppo
from roverswarm.algos.ppo_networks import policy_networks
from roverswarm.config import validate
from roverswarm.env import get_scenario, reset
from roverswarm.env.mars import step_env
from roverswarm.jaxcache import enable_compilation_cache
from roverswarm.learners.onpolicy import configure
from roverswarm.oracle import greedy_plan, oracle_actions
from roverswarm.presets import ANYSIZE

EPISODES = 100
NOISE = 0.3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rovers", type=int, default=5)
    parser.add_argument("--steps", type=int, default=800)
    args = parser.parse_args()
    enable_compilation_cache()
    config = configure(ANYSIZE, validate(ANYSIZE))
    nets = policy_networks(config.learner, config.ppo)
    params = get_scenario(f"paper-{args.rovers}")

    def samples(key):
        states = jax.vmap(reset, in_axes=(0, None))(jax.random.split(key, EPISODES), params)[1]
        plans = jax.vmap(greedy_plan, in_axes=(0, None))(states, params)

        def body(states, step_key):
            labels = jax.vmap(oracle_actions, in_axes=(0, 0, None))(states, plans, params)
            driven = jnp.clip(labels + NOISE * jax.random.normal(step_key, labels.shape), -1.0, 1.0)
            inputs = nets.actor_inputs(jax.vmap(nets.observe, in_axes=(0, None))(states, params))
            return jax.vmap(step_env, in_axes=(0, 0, None))(states, driven, params)[1], (inputs, labels)

        _, (inputs, labels) = jax.lax.scan(body, states, jax.random.split(key, params.max_steps))
        flat = lambda x: x.reshape(-1, *x.shape[3:])  # noqa: E731 ([T, E, N, ...] -> [T E N, ...])
        return jax.tree.map(flat, inputs), flat(labels)

    actor = init_ppo(jax.random.PRNGKey(0), config, params.num_rovers, 0).actor
    adam = optax.adam(1e-3)

    @jax.jit
    def step(actor, opt_state, key):
        inputs, labels = samples(key)
        distance = lambda a: jnp.mean(jnp.sum(jnp.square(nets.policy(a, inputs)[0] - labels), -1))  # noqa: E731
        loss, grads = jax.value_and_grad(distance)(actor)
        updates, opt_state = adam.update(grads, opt_state, actor)
        return optax.apply_updates(actor, updates), opt_state, loss

    opt_state, start = adam.init(actor), time.time()
    for i in range(args.steps):
        actor, opt_state, loss = step(actor, opt_state, jax.random.PRNGKey(i))
        if i % max(args.steps // 10, 1) == 0 or i == args.steps - 1:
            print(f"step {i}: mean squared distance {float(loss):.3f} ({time.time() - start:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
