"""Entity actor: forward + backward of the Flax network against a plain ``jax.numpy`` reference.

For N = 5 and 10 rovers (P = T = N, so M = 3N - 1 tokens per rover), on a batch of
``--batch`` samples x N rovers (random views, about a fifth of the tokens padded with
garbage), one jitted ``jax.value_and_grad`` of a mean squared error of the actor's output
against a random target, in one run:

* ``flax``: :class:`roverswarm.algos.entity.EntityActor` through
  :func:`~roverswarm.algos.entity.make_entity_networks`;
* ``reference``: the same network written below in plain ``jax.numpy`` (no Flax), reading
  the same parameter dict, so both compute the same numbers (checked: the loss and the
  largest gradient difference are printed);
* ``flax / ref``: the median over ``--repeats`` back-to-back pairs of each pair's ratio of
  times (smallest and largest pair in brackets), the order within a pair alternating, so
  load shared by both halves of a pair cancels. Target: within 1.2x (issue 44).

Run ``python benchmarks/entity_network.py`` (``--batch 256 --repeats 3`` for a quick look).
"""

from __future__ import annotations

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

from roverswarm.algos.entity import NEG, OWN_FEATURES, TOKEN_FEATURES, EntityConfig, make_entity_networks

# ---------------------------------------------------------------------------------------
# The reference: the entity actor in plain jax.numpy, on Flax's parameter dict
# ---------------------------------------------------------------------------------------


def ref_dense(p, x):
    return x @ p["kernel"] + p["bias"]


def ref_layer_norm(p, x, eps=1e-6):
    mean = x.mean(-1, keepdims=True)
    var = jnp.square(x - mean).mean(-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(var + eps) * p["scale"] + p["bias"]


def ref_attention(p, queries, keys, mask, heads, project):
    """Masked multi-head attention: queries [..., Q, D], keys [..., M, D], mask [..., M]."""
    dim = p["query"]["kernel"].shape[1]
    d = dim // heads
    q = ref_dense(p["query"], queries).reshape(*queries.shape[:-1], heads, d)
    k = ref_dense(p["key"], keys).reshape(*keys.shape[:-1], heads, d)
    v = ref_dense(p["value"], keys).reshape(*keys.shape[:-1], heads, d)
    logits = jnp.einsum("...qhd,...khd->...hqk", q, k) / jnp.sqrt(d)
    m = mask[..., None, None, :]
    weights = jax.nn.softmax(jnp.where(m, logits, NEG), axis=-1) * m
    out = jnp.einsum("...hqk,...khd->...qhd", weights, v).reshape(*queries.shape[:-1], dim)
    return ref_dense(p["out"], out) if project else out


def ref_actor(params, own, tokens, mask, config: EntityConfig):
    """The entity actor's pre-activation [..., 2] (module docstring of roverswarm.algos.entity)."""
    p, head = params["params"]["encoder"], params["params"]["head"]
    norm = (lambda name, x: ref_layer_norm(p[name], x)) if config.layer_norm else (lambda name, x: x)
    tokens = jnp.where(mask[..., None], tokens, 0.0)
    u = jax.nn.relu(ref_dense(p["embed_own"], own))
    h = jax.nn.relu(ref_dense(p["embed_token"], tokens))
    for layer in range(config.layers):
        z = norm(f"norm_attention_{layer}", h)
        h = h + ref_attention(p[f"attention_{layer}"], z, z, mask, config.heads, True)
        z = norm(f"norm_mlp_{layer}", h)
        h = h + ref_dense(p[f"mlp_out_{layer}"], jax.nn.relu(ref_dense(p[f"mlp_hidden_{layer}"], z)))
    pooled = ref_attention(p["pool"], u[..., None, :], norm("norm_pool", h), mask, config.heads, False)
    x = jnp.concatenate([u, pooled[..., 0, :]], axis=-1)
    for layer in range(len(config.hidden)):
        x = ref_dense(head[f"Dense_{layer}"], x)
        if config.layer_norm:
            x = ref_layer_norm(head[f"LayerNorm_{layer}"], x)
        x = jax.nn.relu(x)
    return ref_dense(head[f"Dense_{len(config.hidden)}"], x)


# ---------------------------------------------------------------------------------------
# Timing
# ---------------------------------------------------------------------------------------


def make_batch(key, batch: int, n: int):
    """Random views [batch, N, ...] of N rovers, N POIs, N traps and a target [batch, N, 2]."""
    m = 3 * n - 1
    k_own, k_tok, k_mask, k_target = jax.random.split(key, 4)
    own = jax.random.normal(k_own, (batch, n, OWN_FEATURES))
    tokens = jax.random.normal(k_tok, (batch, n, m, TOKEN_FEATURES))
    mask = jax.random.uniform(k_mask, (batch, n, m)) < 0.8
    return own, tokens, mask, jax.random.normal(k_target, (batch, n, 2))


def timed(step, params, data) -> float:
    start = time.perf_counter()
    jax.block_until_ready(step(params, *data))
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=1024, help="samples per batch (each of N rovers)")
    parser.add_argument("--repeats", type=int, default=7, help="back-to-back pairs timed per size")
    args = parser.parse_args()

    config = EntityConfig()
    nets = make_entity_networks(config)
    params = nets.init_actor(jax.random.PRNGKey(0))

    def mse(forward):
        return lambda p, own, tokens, mask, target: jnp.mean(jnp.square(forward(p, own, tokens, mask) - target))

    flax_step = jax.jit(jax.value_and_grad(mse(nets.actor)))
    ref_step = jax.jit(jax.value_and_grad(mse(lambda *a: ref_actor(*a, config))))

    print(f"entity actor {config}, batch {args.batch} x N, value_and_grad of an MSE, {jax.devices()[0].platform}")
    columns = ("flax ms", 8), ("ref ms", 8), ("flax / ref", 20), ("|loss diff|", 11), ("max |grad diff|", 15)
    print(f"{'N':>3} {'M':>3}  " + "  ".join(f"{name:>{width}}" for name, width in columns))
    for n in (5, 10):
        data = make_batch(jax.random.PRNGKey(n), args.batch, n)
        (loss_f, grad_f), (loss_r, grad_r) = flax_step(params, *data), ref_step(params, *data)  # compile
        grad_diff = max(float(jnp.abs(a - b).max()) for a, b in zip(jax.tree.leaves(grad_f), jax.tree.leaves(grad_r)))
        pairs = []
        for repeat in range(args.repeats):  # the order within a pair alternates: neither always goes first
            if repeat % 2:
                ref_time = timed(ref_step, params, data)
                pairs.append((timed(flax_step, params, data), ref_time))
            else:
                pairs.append((timed(flax_step, params, data), timed(ref_step, params, data)))
        ratios = sorted(f / r for f, r in pairs)
        flax_ms = 1e3 * statistics.median(f for f, _ in pairs)
        ref_ms = 1e3 * statistics.median(r for _, r in pairs)
        ratio = f"{statistics.median(ratios):.3f} [{ratios[0]:.2f}, {ratios[-1]:.2f}]"
        print(
            f"{n:>3} {3 * n - 1:>3}  {flax_ms:>8.1f}  {ref_ms:>8.1f}  {ratio:>20}  "
            f"{abs(float(loss_f - loss_r)):>11.2e}  {grad_diff:>15.2e}"
        )


if __name__ == "__main__":
    main()
