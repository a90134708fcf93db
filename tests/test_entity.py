"""The entity networks (:mod:`roverswarm.algos.entity`): invariances, padding, sizes, and a
plain NumPy reference.

Views are built here from small worlds (rovers, POIs, traps) by a NumPy loop that follows the
entity view's definition, with garbage (large random values; NaN and inf in the appended
tokens) in every padded slot. The tests check that

* outputs do not change when each rover's tokens are permuted (with their mask), nor when
  masked garbage tokens are appended; they permute with the rovers when the world's rovers
  are permuted (and its POIs and traps shuffled);
* a rover with no real token gets finite outputs, a zero pooled vector and finite gradients;
* one set of parameters serves N = 2, 5 and 10, and a swarm padded into a larger layout gets
  the same outputs as in its own;
* a NumPy reference written from the module's equations (loops over views, heads, queries,
  with the softmax over the real tokens only) gives the same encodings, actions and values
  within 1e-4, on the flax parameters (perturbed: no zero bias hides a mistake);
* the checks have teeth: unmasked inputs, the reference without masking or without the
  1/sqrt(d) scale, all disagree; the outputs differ from rover to rover.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from roverswarm.algos.entity import (
    OWN_FEATURES,
    TOKEN_FEATURES,
    EntityActor,
    EntityConfig,
    EntityEncoder,
    make_entity_networks,
)

# d = dim / heads = 4; two blocks with LayerNorm exercise every parameter of the encoder
CONFIG = EntityConfig(dim=16, heads=4, layers=2, layer_norm=True, hidden=(16,))
N, P, T = 4, 3, 2  # the layout of the main batch: M = 3 + 3 + 2 = 8 tokens
M = (N - 1) + P + T
RADII = dict(rover=0.15, poi=0.05, trap=0.1)
TOL = dict(atol=1e-5, rtol=0)


# ---------------------------------------------------------------------------------------
# Worlds and their entity views (NumPy, one rover and one token at a time)
# ---------------------------------------------------------------------------------------


def make_world(rng: np.random.Generator, n: int, p: int, t: int, active: tuple[int, int, int]) -> dict:
    """A world laid out for n rovers, p POIs, t traps, of which the first ``active`` are real."""
    return dict(
        rover_pos=rng.uniform(-1, 1, (n, 2)),
        rover_vel=rng.normal(0, 0.3, (n, 2)),
        failed=rng.random(n) < 0.3,
        rover_on=np.arange(n) < active[0],
        poi_pos=rng.uniform(-1, 1, (p, 2)),
        observed=rng.random(p) < 0.5,
        poi_on=np.arange(p) < active[1],
        trap_pos=rng.uniform(-1, 1, (t, 2)),
        trap_on=np.arange(t) < active[2],
    )


def permute_world(world: dict, rovers: np.ndarray, pois: np.ndarray, traps: np.ndarray) -> dict:
    """The same world with its rovers, POIs and traps renumbered (new index k = old ``order[k]``)."""
    group = dict(rover_pos=rovers, rover_vel=rovers, failed=rovers, rover_on=rovers, poi_pos=pois, observed=pois)
    group.update(poi_on=pois, trap_pos=traps, trap_on=traps)
    return {key: value[group[key]] for key, value in world.items()}


def entity_view(world: dict, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """own [N, 4], tokens [N, M, 11], mask [N, M] of ``world``, written from the definition;
    every padded slot (an inactive entity's token, an inactive rover's own row) is garbage."""
    n, p, t = len(world["rover_pos"]), len(world["poi_pos"]), len(world["trap_pos"])
    own = np.zeros((n, OWN_FEATURES), np.float32)
    tokens = np.zeros((n, n - 1 + p + t, TOKEN_FEATURES), np.float32)
    mask = np.zeros((n, n - 1 + p + t), bool)
    garbage = lambda size: rng.normal(0, 50, size)  # noqa: E731
    poi_gaps = lambda k: np.linalg.norm(world["poi_pos"] - world["rover_pos"][k], axis=-1)  # noqa: E731
    for i in range(n):
        pos, vel = world["rover_pos"][i], world["rover_vel"][i]
        own[i] = np.concatenate([vel, pos]) if world["rover_on"][i] else garbage(OWN_FEATURES)
        rows = []
        for j in range(n):
            if j != i:
                rel = [*(world["rover_pos"][j] - pos), *(world["rover_vel"][j] - vel)]
                rows.append((rel + [1, 0, 0, RADII["rover"], world["failed"][j], 0, 0], world["rover_on"][j]))
        for j in range(p):
            rel = [*(world["poi_pos"][j] - pos), 0, 0]
            gap = lambda k: np.linalg.norm(world["rover_pos"][k] - world["poi_pos"][j])  # noqa: E731
            others = [k for k in range(n) if k != i and world["rover_on"][k] and not world["failed"][k]]
            lead = np.clip(min(map(gap, others), default=np.inf) - gap(i), -2, 2)  # the nearest other's less mine
            nearest = lambda k: np.argmin(np.where(world["poi_on"], poi_gaps(k), np.inf))  # noqa: E731
            claims = [gap(k) for k in others if nearest(k) == j]  # the others whose nearest POI it is
            claim = np.clip(min(claims, default=np.inf) - gap(i), -2, 2)
            rows.append((rel + [0, 1, 0, RADII["poi"], world["observed"][j], lead, claim], world["poi_on"][j]))
        for j in range(t):
            rel = [*(world["trap_pos"][j] - pos), 0, 0]
            rows.append((rel + [0, 0, 1, RADII["trap"], 0, 0, 0], world["trap_on"][j]))
        for k, (features, on) in enumerate(rows):
            tokens[i, k] = features if on else garbage(TOKEN_FEATURES)
            mask[i, k] = on
    return own, tokens, mask


def stack_views(worlds: list[dict], rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """own [B, N, 4], tokens [B, N, M, 11], mask [B, N, M] of equally laid out worlds."""
    return tuple(np.stack(parts) for parts in zip(*(entity_view(w, rng) for w in worlds)))


# ---------------------------------------------------------------------------------------
# Fixtures: one compilation per network and shape
# ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def nets():
    return make_entity_networks(CONFIG)


@pytest.fixture(scope="module")
def params(nets):
    """Initialised, then every entry perturbed: at init the biases are zero and the LayerNorms
    the identity, which would hide a missing bias or a padded token's embedding."""
    keys = dict(zip(("actor", "value"), jax.random.split(jax.random.PRNGKey(0), 2)))
    inits = dict(actor=nets.init_actor, value=nets.init_value)
    rng = np.random.default_rng(0)
    perturb = lambda x: x + 0.2 * rng.normal(size=x.shape).astype(np.float32)  # noqa: E731
    return {name: jax.tree.map(perturb, jax.jit(init)(keys[name])) for name, init in inits.items()}


@pytest.fixture(scope="module")
def jitted(nets):
    """The jitted networks, and the actor's encoder on its parameters (``encoder(params, ...)``)."""
    encoder = EntityEncoder(CONFIG.dim, CONFIG.heads, CONFIG.layers, CONFIG.layer_norm)
    return dict(
        actor=jax.jit(nets.actor),
        value=jax.jit(nets.value),
        encoder=jax.jit(lambda p, *view: encoder.apply({"params": p["params"]["encoder"]}, *view)),
    )


@pytest.fixture(scope="module")
def apply(params, jitted):
    """``apply(own, tokens, mask)`` -> dict of the jitted actor and value outputs on the
    module's parameters, as NumPy arrays."""

    def run(own, tokens, mask):
        return dict(
            actor=np.asarray(jitted["actor"](params["actor"], own, tokens, mask)),
            value=np.asarray(jitted["value"](params["value"], own, tokens, mask)),
        )

    return run


@pytest.fixture(scope="module")
def worlds():
    """Two worlds in the N, P, T layout: one full, one with a rover, a POI and a trap padded."""
    rng = np.random.default_rng(3)
    return [make_world(rng, N, P, T, (N, P, T)), make_world(rng, N, P, T, (N - 1, P - 1, T - 1))]


@pytest.fixture(scope="module")
def batch(worlds):
    """The worlds' views [B = 2, N, ...]."""
    own, tokens, mask = stack_views(worlds, np.random.default_rng(4))
    return dict(own=own, tokens=tokens, mask=mask)


def run_batch(apply, batch, **changes):
    b = {**batch, **changes}
    return apply(b["own"], b["tokens"], b["mask"])


def assert_outputs_close(got: dict, want: dict, **tol):
    for name in want:
        np.testing.assert_allclose(got[name], want[name], **(tol or TOL), err_msg=name)


def largest_difference(got: dict, want: dict) -> float:
    return max(float(np.nanmax(np.abs(got[name] - want[name]))) for name in want)


# ---------------------------------------------------------------------------------------
# Invariances
# ---------------------------------------------------------------------------------------


def test_token_permutation_changes_nothing(apply, batch):
    """Each rover's M tokens permuted at random (tokens and mask together)."""
    rng = np.random.default_rng(5)
    order = np.argsort(rng.random(batch["mask"].shape), axis=-1)  # [B, N, M], one per rover
    moved = {
        "tokens": np.take_along_axis(batch["tokens"], order[..., None], axis=-2),
        "mask": np.take_along_axis(batch["mask"], order, axis=-1),
    }
    assert not np.array_equal(moved["tokens"], batch["tokens"])
    assert_outputs_close(run_batch(apply, batch, **moved), run_batch(apply, batch))


def test_masked_garbage_tokens_change_nothing(apply, batch):
    """Seven tokens appended (M -> M + 7) with random values, NaN and inf, all masked."""
    rng = np.random.default_rng(6)
    extra = rng.normal(0, 100, (*batch["mask"].shape[:-1], 7, TOKEN_FEATURES)).astype(np.float32)
    extra[..., 0, 0], extra[..., 1, 3], extra[..., 2, 5] = np.nan, np.inf, -np.inf
    padded = {
        "tokens": np.concatenate([batch["tokens"], extra], axis=-2),
        "mask": np.concatenate([batch["mask"], np.zeros(extra.shape[:-1], bool)], axis=-1),
    }
    assert_outputs_close(run_batch(apply, batch, **padded), run_batch(apply, batch))


def test_outputs_permute_with_the_rovers(apply, worlds, batch):
    """The worlds' rovers renumbered (POIs and traps shuffled too): every real rover's action
    and value move with it, whatever the order in which it sees the others and whatever
    garbage fills the padded slots."""
    rng = np.random.default_rng(7)
    orders = [(rng.permutation(N), rng.permutation(P), rng.permutation(T)) for _ in worlds]
    own, tokens, mask = stack_views([permute_world(w, *o) for w, o in zip(worlds, orders)], rng)
    got = apply(own, tokens, mask)
    want = run_batch(apply, batch)
    for b, (world, (rovers, _, _)) in enumerate(zip(worlds, orders)):
        real = world["rover_on"][rovers]  # outputs of padded rover rows are not defined
        assert real.sum() >= N - 1 and not np.array_equal(rovers, np.arange(N))
        for name in want:
            np.testing.assert_allclose(got[name][b][real], want[name][b][rovers][real], **TOL, err_msg=name)


def test_outputs_differ_between_rovers(apply, batch):
    """The invariance tests have teeth: the outputs are not (nearly) constant."""
    out = run_batch(apply, batch)
    for name in out:
        assert np.std(out[name][0], axis=0).min() > 1e-2, name


def test_unmasked_garbage_changes_the_outputs(apply, batch):
    """Masking is what makes garbage harmless: the same garbage tokens marked real (the padded
    slots of the batch; seven appended tokens) change every network's outputs."""
    assert not batch["mask"].all()
    assert largest_difference(run_batch(apply, batch, mask=np.ones_like(batch["mask"])), run_batch(apply, batch)) > 0.1
    extra = np.random.default_rng(6).normal(0, 1, (*batch["mask"].shape[:-1], 7, TOKEN_FEATURES)).astype(np.float32)
    unmasked = {
        "tokens": np.concatenate([batch["tokens"], extra], axis=-2),
        "mask": np.concatenate([batch["mask"], np.ones(extra.shape[:-1], bool)], axis=-1),
    }
    got, want = run_batch(apply, batch, **unmasked), run_batch(apply, batch)
    for name in want:
        assert np.abs(got[name] - want[name]).max() > 1e-2, name


# ---------------------------------------------------------------------------------------
# No real token, any swarm size, jit and vmap
# ---------------------------------------------------------------------------------------


def test_a_rover_with_no_real_token(nets, params, jitted, apply, batch):
    """A rover that sees nothing: finite outputs, a zero pooled vector (the encoder's second
    half), finite gradients of every parameter, even with NaN in its padded tokens."""
    mask = batch["mask"].copy()
    mask[1, 0] = False
    tokens = batch["tokens"].copy()
    tokens[1, 0, :, 2] = np.nan
    out = run_batch(apply, batch, mask=mask, tokens=tokens)
    for name in out:
        assert np.isfinite(out[name]).all(), name
    encoded = jitted["encoder"](params["actor"], batch["own"], tokens, mask)
    np.testing.assert_array_equal(np.asarray(encoded)[1, 0, CONFIG.dim :], 0.0)
    assert np.abs(np.asarray(encoded)[0, :, CONFIG.dim :]).max() > 1e-2  # the others' are not zero
    grads = jax.jit(jax.grad(lambda p: jnp.sum(nets.actor(p, batch["own"], tokens, mask) ** 2)))(params["actor"])
    assert all(np.isfinite(g).all() for g in jax.tree.leaves(grads))


@pytest.mark.parametrize("n", [2, 5, 10])
def test_same_parameters_for_every_swarm_size(apply, n):
    """A swarm of n rovers, n POIs and n traps in its own layout and padded into the layout of
    10 (garbage in the padded slots): the same parameters, the same outputs for its rovers."""
    rng = np.random.default_rng(n)
    world = make_world(rng, 10, 10, 10, (n, n, n))
    own_world = {key: value[:n] for key, value in world.items()}
    alone, padded = apply(*stack_views([own_world], rng)), apply(*stack_views([world], rng))
    assert alone["actor"].shape == (1, n, 2) and padded["actor"].shape == (1, 10, 2)
    for name in alone:
        assert np.isfinite(alone[name]).all()
        np.testing.assert_allclose(padded[name][:, :n], alone[name], **TOL, err_msg=name)


def test_parameter_shapes_do_not_depend_on_the_view(params):
    """Initialised on 29 tokens of a [3, 10] batch, the actor has the shapes of the default init."""
    actor = EntityActor(CONFIG.dim, CONFIG.heads, CONFIG.layers, CONFIG.layer_norm, CONFIG.hidden)
    view = (jnp.zeros((3, 10, 4)), jnp.zeros((3, 10, 29, TOKEN_FEATURES)), jnp.ones((3, 10, 29), bool))
    big = jax.eval_shape(actor.init, jax.random.PRNGKey(1), *view)
    assert jax.tree.map(jnp.shape, big) == jax.tree.map(jnp.shape, params["actor"])


def test_vmap_over_views_and_over_seeds(nets, params, jitted, batch):
    """vmap over the batch axis equals the batched call; vmap over stacked parameters (seeds)
    equals each seed's call, and different seeds give different actions."""
    view = (batch["own"], batch["tokens"], batch["mask"])
    batched = jitted["actor"](params["actor"], *view)
    mapped = jax.jit(jax.vmap(nets.actor, in_axes=(None, 0, 0, 0)))(params["actor"], *view)
    np.testing.assert_allclose(mapped, batched, **TOL)
    # two seeds' parameters stacked, as ``jax.vmap(train)(keys)`` holds them
    seeds = jax.tree.map(lambda *x: jnp.stack(x), params["actor"], jax.jit(nets.init_actor)(jax.random.PRNGKey(2)))
    per_seed = jax.jit(jax.vmap(nets.actor, in_axes=(0, None, None, None)))(seeds, *view)
    for s in range(2):
        np.testing.assert_allclose(per_seed[s], jitted["actor"](jax.tree.map(lambda x: x[s], seeds), *view), **TOL)
    assert np.abs(per_seed[0] - per_seed[1]).max() > 1e-2


# ---------------------------------------------------------------------------------------
# A plain NumPy reference, written from the module docstring's equations
# ---------------------------------------------------------------------------------------


def np_dense(p, x):
    return x @ np.asarray(p["kernel"], np.float64) + np.asarray(p["bias"], np.float64)


def np_layer_norm(p, x, eps=1e-6):
    mean = x.mean(axis=-1, keepdims=True)
    var = ((x - mean) ** 2).mean(axis=-1, keepdims=True)
    return (x - mean) / np.sqrt(var + eps) * np.asarray(p["scale"], np.float64) + np.asarray(p["bias"], np.float64)


def np_attention(p, queries, keys, mask, heads, project, masked=True, scaled=True):
    """Each query's softmax over the real keys only (all keys if not ``masked``), head by head."""
    q, k, v = np_dense(p["query"], queries), np_dense(p["key"], keys), np_dense(p["value"], keys)
    dim = q.shape[-1]
    d = dim // heads
    real = [kk for kk in range(len(keys)) if mask[kk] or not masked]
    out = np.zeros((len(queries), dim))
    for c in range(heads):
        cols = slice(c * d, (c + 1) * d)
        for j in range(len(queries)):
            if not real:
                continue  # nothing to attend to: a zero vector
            logits = np.array([q[j, cols] @ k[kk, cols] for kk in real]) / (np.sqrt(d) if scaled else 1.0)
            weights = np.exp(logits - logits.max())
            weights /= weights.sum()
            out[j, cols] = sum(w * v[kk, cols] for w, kk in zip(weights, real))
    return np_dense(p["out"], out) if project else out


def np_encoder(p, own, tokens, mask, config: EntityConfig, **variant):
    """One rover's encoding [2D] from own [G], tokens [M, F], mask [M]."""
    norm = (lambda name, x: np_layer_norm(p[name], x)) if config.layer_norm else (lambda name, x: x)
    if variant.get("masked", True):
        tokens = np.where(mask[:, None], tokens, 0.0)
    u = np.maximum(np_dense(p["embed_own"], own.astype(np.float64)), 0)
    h = np.maximum(np_dense(p["embed_token"], tokens.astype(np.float64)), 0)
    for layer in range(config.layers):
        z = norm(f"norm_attention_{layer}", h)
        h = h + np_attention(p[f"attention_{layer}"], z, z, mask, config.heads, True, **variant)
        z = norm(f"norm_mlp_{layer}", h)
        h = h + np_dense(p[f"mlp_out_{layer}"], np.maximum(np_dense(p[f"mlp_hidden_{layer}"], z), 0))
    pooled = np_attention(p["pool"], u[None], norm("norm_pool", h), mask, config.heads, False, **variant)[0]
    return np.concatenate([u, pooled])


def np_head(p, x, config: EntityConfig):
    for layer in range(len(config.hidden)):
        x = np_dense(p[f"Dense_{layer}"], x)
        if config.layer_norm:
            x = np_layer_norm(p[f"LayerNorm_{layer}"], x)
        x = np.maximum(x, 0)
    return np_dense(p[f"Dense_{len(config.hidden)}"], x)


def np_networks(params, batch, config: EntityConfig, **variant) -> dict:
    """Encodings [B, N, 2D] (the actor's encoder), actions [B, N, 2] and values [B, N], one
    rover's view at a time."""
    out = {name: [] for name in ("encoder", "actor", "value")}
    for b, i in np.ndindex(*batch["mask"].shape[:2]):
        own, tokens, mask = batch["own"][b, i], batch["tokens"][b, i], batch["mask"][b, i]
        for name in ("actor", "value"):
            p = params[name]["params"]
            x = np_encoder(p["encoder"], own, tokens, mask, config, **variant)
            out[name].append(np_head(p["head"], x, config)[: 2 if name == "actor" else 1])
            if name == "actor":
                out["encoder"].append(x)
    shape = batch["mask"].shape[:2]
    return dict(
        encoder=np.reshape(out["encoder"], (*shape, -1)),
        actor=np.reshape(out["actor"], (*shape, 2)),
        value=np.reshape(out["value"], shape),
    )


@pytest.fixture(scope="module")
def flax_outputs(params, jitted, apply, batch):
    encoded = jitted["encoder"](params["actor"], batch["own"], batch["tokens"], batch["mask"])
    return {**run_batch(apply, batch), "encoder": np.asarray(encoded)}


def test_numpy_reference_agrees(params, batch, flax_outputs):
    """Encodings, actions and values of every rover of both worlds within 1e-4."""
    want = np_networks(params, batch, CONFIG)
    assert_outputs_close(flax_outputs, want, atol=1e-4, rtol=0)


@pytest.mark.parametrize("variant", [dict(masked=False), dict(scaled=False)], ids=["unmasked", "unscaled"])
def test_numpy_reference_has_teeth(params, batch, flax_outputs, variant):
    """The reference without masking (garbage attended to) or without the 1/sqrt(d) scale
    disagrees with the network: the comparison above would catch either mistake."""
    assert largest_difference(np_networks(params, batch, CONFIG, **variant), flax_outputs) > 1e-2


def test_networks_first_made_inside_a_trace_serve_later_calls():
    """Regression: the on-policy family caches its networks, and they were first made inside
    the memory check's jax.eval_shape, keeping that trace's arrays; initialising them after
    it (`roverswarm train --network entity` in a fresh process) raised UnexpectedTracerError."""
    from roverswarm.algos.ppo_networks import policy_networks
    from roverswarm.config import validate, with_options
    from roverswarm.limits import network_bytes
    from roverswarm.presets import ANYSIZE

    config = with_options(
        ANYSIZE, {"network": "entity", "swarm_value": False, "entity_dim": 8, "entity_heads": 2, "hidden": (8,)}
    )
    policy_networks.cache_clear()
    assert network_bytes(config, validate(config)) > 0  # traces the networks' sizes first
    actor, value = policy_networks(config.learner, config.ppo).init(jax.random.PRNGKey(0), 3, 0)
    assert np.isfinite(actor["log_std"]).all() and jax.tree.leaves(value)
