"""The any-size PPO update against a plain ``jax.numpy`` reference of the same update.

For N = 5 and 10 rovers (``paper-N``), one minibatch of the ``anysize`` preset (episode
length 25 x 100 environments x N rovers / 4 minibatches = 625 N samples) of real
nearest-4 views (625 environments reset and stepped a few times with random actions), with
random actions near the policy's, rollout log-probabilities a little off the current ones,
random advantages and standardised value targets, and about a tenth of the samples masked
out (as absent rovers of a mixed-size batch). In one run:

* ``ours``: :func:`roverswarm.algos.ppo.update_minibatch`, jitted, with the preset's
  on-policy config: Flax MLPs over :func:`~roverswarm.env.entities.flat_tokens`,
  optax's global-norm clipping and Adam;
* ``reference``: the same update written below in plain ``jax.numpy`` (no Flax, no optax):
  the tanh MLPs (2 x 128) on the same parameter dicts, the Gaussian log-probability and
  entropy, the PPO loss, gradients by ``jax.grad``, clipping by global norm, Adam with bias
  correction; it reads and returns the same pytrees (:class:`~roverswarm.algos.ppo.PPOState`
  and the loss parts). Both start from a state a few updates old (so Adam's moments are not
  zero) and must give the same numbers: the largest difference of the updated parameters
  (next to the largest change an update makes) and of the loss parts is printed;
* ``ours / ref``: the median over ``--repeats`` back-to-back pairs of each pair's ratio of
  times, each half ``--calls`` updates, the order within a pair alternating (smallest and
  largest pair in brackets), so load shared by both halves cancels. Target: within 1.2x
  (issue 44).

Run ``nice python benchmarks/anysize_update.py`` (``--repeats 5`` for a quick look).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from functools import partial
from statistics import median

import jax
import jax.numpy as jnp

from roverswarm.algos.ppo import Batch, PPOState, gaussian_log_prob, init_ppo, update_minibatch
from roverswarm.algos.ppo_networks import policy_networks
from roverswarm.config import validate
from roverswarm.env.mars import ACTION_SIZE, observation_size, reset, step_env
from roverswarm.experiments.timing import paired_ratio
from roverswarm.learners.onpolicy import configure
from roverswarm.presets import PRESETS

B1, B2, ADAM_EPS = 0.9, 0.999, 1e-5
"""Adam's decay rates (optax's defaults) and the eps the presets use."""

# ---------------------------------------------------------------------------------------
# The reference: one PPO update in plain jax.numpy, on Flax's and optax's pytrees
# ---------------------------------------------------------------------------------------


def ref_mlp(p, x):
    """tanh layers ``Dense_0`` .. ``Dense_{L-2}``, then a linear ``Dense_{L-1}``."""
    layers = len(p)
    for i in range(layers):
        x = x @ p[f"Dense_{i}"]["kernel"] + p[f"Dense_{i}"]["bias"]
        if i < layers - 1:
            x = jnp.tanh(x)
    return x


def masked_mean(x, mask):
    """Mean of ``x`` weighted by ``mask`` (0/1 here: the benchmark leaves --balance-sizes off)."""
    return jnp.sum(x * mask) / jnp.maximum(jnp.sum(mask), 1.0)


def ref_loss(actor, critic, batch: Batch, ppo):
    """The PPO loss (clipped surrogate on per-minibatch standardised advantages, value loss
    without clipping, entropy bonus) and its parts."""
    mean = ref_mlp(actor["params"]["MLP_0"], batch.actor_inputs)
    log_std = actor["params"]["log_std"]
    z = (batch.actions - mean) * jnp.exp(-log_std)
    log_probs = jnp.sum(-0.5 * z * z - log_std - 0.5 * jnp.log(2 * jnp.pi), axis=-1)
    entropy = jnp.sum(log_std + 0.5 * jnp.log(2 * jnp.pi * jnp.e))
    values = ref_mlp(critic["params"], batch.critic_inputs)[:, 0]

    mask = batch.mask
    adv_mean = masked_mean(batch.advantages, mask)
    adv_std = jnp.sqrt(masked_mean(jnp.square(batch.advantages - adv_mean), mask))
    adv = (batch.advantages - adv_mean) / (adv_std + 1e-8)
    log_ratio = log_probs - batch.log_probs
    ratio = jnp.exp(log_ratio)
    clipped = jnp.clip(ratio, 1 - ppo.clip_eps, 1 + ppo.clip_eps)
    policy_loss = -masked_mean(jnp.minimum(ratio * adv, clipped * adv), mask)
    value_loss = 0.5 * masked_mean(jnp.square(values - batch.targets), mask)
    mean_entropy = masked_mean(jnp.full_like(log_probs, entropy), mask)
    total = policy_loss + ppo.vf_coef * value_loss - ppo.ent_coef * mean_entropy
    parts = {
        "policy_loss": policy_loss,
        "value_loss": value_loss,
        "entropy": mean_entropy,
        "approx_kl": masked_mean(ratio - 1.0 - log_ratio, mask),
        "clip_fraction": masked_mean((jnp.abs(ratio - 1.0) > ppo.clip_eps).astype(jnp.float32), mask),
    }
    return total, parts


def ref_adam(params, grads, opt_state, lr: float, max_norm: float):
    """Clip ``grads`` to global norm ``max_norm``, then one Adam step; ``opt_state`` is
    optax's ``(clip state, (Adam state, learning-rate state))``."""
    norm = jnp.sqrt(sum(jnp.sum(jnp.square(g)) for g in jax.tree.leaves(grads)))
    grads = jax.tree.map(lambda g: jnp.where(norm < max_norm, g, g / norm * max_norm), grads)
    clip_state, (adam, lr_state) = opt_state
    count = adam.count + 1
    mu = jax.tree.map(lambda m, g: B1 * m + (1 - B1) * g, adam.mu, grads)
    nu = jax.tree.map(lambda v, g: B2 * v + (1 - B2) * g * g, adam.nu, grads)
    fix1, fix2 = 1 - B1 ** count.astype(jnp.float32), 1 - B2 ** count.astype(jnp.float32)
    params = jax.tree.map(lambda p, m, v: p - lr * (m / fix1) / (jnp.sqrt(v / fix2) + ADAM_EPS), params, mu, nu)
    return params, (clip_state, (adam._replace(count=count, mu=mu, nu=nu), lr_state))


def ref_update(config, state: PPOState, batch: Batch):
    """One update of actor and value network: (state, loss parts), as ``update_minibatch``."""
    learner = config.learner
    (_, parts), (actor_grads, critic_grads) = jax.value_and_grad(ref_loss, argnums=(0, 1), has_aux=True)(
        state.actor, state.critic, batch, config.ppo
    )
    actor, actor_opt = ref_adam(state.actor, actor_grads, state.actor_opt, learner.actor_lr, learner.grad_clip)
    critic, critic_opt = ref_adam(state.critic, critic_grads, state.critic_opt, learner.critic_lr, learner.grad_clip)
    return state.replace(actor=actor, critic=critic, actor_opt=actor_opt, critic_opt=critic_opt), parts


# ---------------------------------------------------------------------------------------
# Inputs and timing
# ---------------------------------------------------------------------------------------


def anysize_config(n: int):
    """The ``anysize`` preset on ``paper-N``: (on-policy config, environment params)."""
    preset = PRESETS["anysize"]
    # one size: --balance-sizes (weights of largest size / N, here all 1) needs a range; the
    # reference's Adam has a constant rate (the preset's annealing scales the step by one
    # number per update: the same cost)
    ppo = dataclasses.replace(preset.ppo, balance_sizes=False, anneal_episodes=0)
    run = dataclasses.replace(preset, scenario=f"paper-{n}", size_curriculum=0, ppo=ppo)
    params = validate(run)
    config = configure(run, params)
    ppo = config.ppo
    # What the reference implements; another preset would need another reference.
    assert ppo.activation == "tanh" and ppo.value_clip is None and ppo.normalize_advantages
    assert ppo.anneal_episodes == 0 and config.learner.network == "nearest"
    return config, params


def make_batch(key, config, params, steps: int) -> Batch:
    """A minibatch of the preset's size: nearest views of E = 25 x num_envs / minibatches
    environments after ``steps`` random steps, E x N samples."""
    nets = policy_networks(config.learner, config.ppo)
    envs = params.max_steps * config.num_envs // config.ppo.minibatches
    k_reset, k_act, k_state, k_noise, k_old, k_adv, k_target, k_mask = jax.random.split(key, 8)

    def rollout(reset_key, act_key):
        _, env = reset(reset_key, params)
        for action_key in jax.random.split(act_key, steps):
            actions = jax.random.uniform(action_key, (params.num_rovers, ACTION_SIZE), minval=-1.0, maxval=1.0)
            env = step_env(env, actions, params)[1]
        return nets.observe(env, params)

    views = jax.jit(jax.vmap(rollout))(jax.random.split(k_reset, envs), jax.random.split(k_act, envs))  # [E, N, ...]
    per_rover = lambda x: x.reshape(-1, *x.shape[2:])  # noqa: E731  [E, N, ...] -> [B, ...]: one per rover
    inputs = per_rover(nets.actor_inputs(views))  # [B, 148]
    critic_inputs = per_rover(nets.critic_inputs(views))  # [B, 297]: the swarm's part from its own rovers
    size = inputs.shape[0]
    state = init_ppo(k_state, config, params.num_rovers, observation_size(params))
    mean, log_std = nets.policy(state.actor, inputs)
    actions = mean + jnp.exp(log_std) * jax.random.normal(k_noise, mean.shape)
    log_probs = gaussian_log_prob(actions, mean, log_std) + 0.1 * jax.random.normal(k_old, (size,))
    return Batch(
        actor_inputs=inputs,
        critic_inputs=critic_inputs,
        actions=actions,
        log_probs=log_probs,
        advantages=jax.random.normal(k_adv, (size,)),
        targets=jax.random.normal(k_target, (size,)),
        values=jnp.zeros((size,)),
        mask=(jax.random.uniform(k_mask, (size,)) < 0.9).astype(jnp.float32),
    )


def timed(update, state, batch, calls: int) -> float:
    """Seconds per call of ``update(state, batch)`` over ``calls`` calls."""
    start = time.perf_counter()
    for _ in range(calls):
        out = update(state, batch)
    jax.block_until_ready(out)
    return (time.perf_counter() - start) / calls


def largest_diff(a, b) -> float:
    """Largest absolute difference between two pytrees of the same structure."""
    return max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=21, help="back-to-back pairs timed per size")
    parser.add_argument("--calls", type=int, default=10, help="updates per timed half of a pair")
    parser.add_argument("--steps", type=int, default=5, help="random environment steps before the views")
    parser.add_argument("--warmup", type=int, default=3, help="updates before the compared one")
    args = parser.parse_args()

    print(f"anysize preset's PPO update (one minibatch), ours vs a jax.numpy reference, {jax.devices()[0].platform}")
    columns = ("ours ms", 8), ("ref ms", 8), ("ours / ref", 20), ("max |param diff|", 16), ("max |step|", 10)
    columns += (("max |loss part diff|", 20),)
    print(f"{'N':>3} {'B':>5}  " + "  ".join(f"{name:>{width}}" for name, width in columns))
    for n in (5, 10):
        config, params = anysize_config(n)
        batch = make_batch(jax.random.PRNGKey(n), config, params, args.steps)
        ours = jax.jit(partial(update_minibatch, config))
        ref = jax.jit(partial(ref_update, config))
        state = init_ppo(jax.random.PRNGKey(0), config, params.num_rovers, observation_size(params))
        for _ in range(args.warmup):
            state, _ = ours(state, batch)
        (state_o, parts_o), (state_r, parts_r) = ours(state, batch), ref(state, batch)  # also compiles
        assert jax.tree.structure(state_o) == jax.tree.structure(state_r)
        param_diff = largest_diff((state_o.actor, state_o.critic), (state_r.actor, state_r.critic))
        step = largest_diff((state_o.actor, state_o.critic), (state.actor, state.critic))
        parts_diff = largest_diff(parts_o, parts_r)

        pairs = []
        for repeat in range(args.repeats):  # the order within a pair alternates
            if repeat % 2:
                ref_time = timed(ref, state, batch, args.calls)
                pairs.append((timed(ours, state, batch, args.calls), ref_time))
            else:
                ours_time = timed(ours, state, batch, args.calls)
                pairs.append((ours_time, timed(ref, state, batch, args.calls)))
        ours_s, ref_s = zip(*pairs)
        ratio, low, high = paired_ratio(ref_s, ours_s)
        print(
            f"{n:>3} {batch.mask.shape[0]:>5}  {1e3 * median(ours_s):>8.2f}  {1e3 * median(ref_s):>8.2f}  "
            f"{f'{ratio:.3f} [{low:.2f}, {high:.2f}]':>20}  "
            f"{param_diff:>16.2e}  {step:>10.2e}  {parts_diff:>20.2e}"
        )


if __name__ == "__main__":
    main()
