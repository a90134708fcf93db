"""The trainer's compact replay: what a transition's observations are made of, each stored once.

Shape legend: C capacity (transitions), E episodes added at once (parallel environments),
T steps per episode, L = E * ceil(C / (T * E)) episode slots, N rovers, P POIs, X = P + traps,
O observation size, A action size.

A rover's observation (:func:`~roverswarm.env.mars.observe`) lists every POI, trap and other
rover relative to it, so a step's N observations hold N * O numbers, O = 4 + 2X + 2(N - 1),
where the environment itself has only every rover's velocity and position (4N
numbers) and the episode's layout (2X, the same for all T steps); and a transition's next
observation is the next transition's observation. The replay therefore stores:

* per transition (:class:`Step`, in the ring of C): every rover's velocity and position
  before the step, the actions, rewards, ``terminated``, the sub-policies of policy ensembles,
  and ``where``: the episode's slot in the episode table and the step's index in it;
* per episode (:class:`Episodes`, a ring of L slots): the layout (POIs, then traps) and the
  rovers after the episode's last step (and, as the replay is asked below, which slots exist
  and when rovers fail).

The trainer adds whole episodes, E at a time, time-major (transition ``t * E + e`` of an add is
step t of episode e), so the next step of the transition in slot j is in slot ``(j + E) mod C``,
written in the same add and overwritten only after j; the last step's next state is the
episode's. The transitions still stored come from the newest ``ceil(C / (T * E))`` adds, whose
episodes the table of L slots holds. :func:`expand` rebuilds the
:class:`~roverswarm.buffers.base.Transition` a learner reads, inside the jitted update and for
the sampled transitions only, with the environment's own observation function. The flat view
depends on nothing else (not on time, failures or what was observed; of padded layouts, also
the masks), so the batches are the
stored ones bit for bit (``tests/test_compact_replay.py`` checks this against a replay of
full observations for every replay kind). Bytes per transition: 151 instead of 1,341 at N = 5,
298 instead of 5,081 at N = 10 (``benchmarks/replay_memory.py``). A view that also shows which
POIs were observed (the nearest view of ``--network nearest``) needs those too: with
``init(..., observed=True)`` every step keeps its [P] flags and every episode its last ones,
and :func:`expand` rebuilds the view from them (``tests/test_offpolicy_nearest.py``). Swarm
sizes mixed in one replay (``padded=True``) keep each episode's masks (which rover, POI and
trap slots exist) in the episode table, and training with failures (``failures=True``) each
episode's failure steps; :func:`expand` rebuilds both, a failure at each step's time
(``tests/test_offpolicy_anysize.py``).

The buffers store any record with a ``policy`` field, so every replay kind (uniform, ranked,
partitioned for policy ensembles) keeps ``Step`` unchanged; the episode table rides in
:attr:`~roverswarm.buffers.base.BufferState.episodes`.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import jax
import jax.numpy as jnp
from flax import struct

from roverswarm.buffers.base import Buffer, BufferState, Transition, gather
from roverswarm.env.layouts import Masks
from roverswarm.env.mars import ACTION_SIZE, NEVER, EnvParams, EnvState, observe_positions


@struct.dataclass
class Step:
    """One stored transition (leading axes as the context says)."""

    rovers: jax.Array  # [..., N, 4] every rover's velocity and position before the step
    actions: jax.Array  # [..., N, A]
    rewards: jax.Array  # [..., N]
    terminated: jax.Array  # [...] bool; a truncation is not a termination
    where: jax.Array  # [...] int32, episode slot * T + step index in the episode
    policy: Any = None  # [..., N] int32 sub-policy each agent ran (policy ensembles only)
    observed: Any = None  # [..., P] bool POIs observed before the step (a view that shows them only)


@struct.dataclass
class Episodes:
    """The episode table: what every step of an episode shares."""

    layout: jax.Array  # [L, X, 2] the episode's POIs, then its traps
    final: jax.Array  # [L, N, 4] every rover's velocity and position after the last step
    position: jax.Array  # [] int32, the slot of the next episode added
    final_observed: Any = None  # [L, P] bool POIs observed after the last step (a view that shows them)
    masks: Masks | None = None  # [L, ...] the slots that exist (mixed swarm sizes only)
    fail_step: Any = None  # [L, N] int32 each rover's failure step (training with failures only)


@struct.dataclass
class Collected:
    """E episodes of T steps as collected (time-major), before they are stored."""

    rovers: jax.Array  # [T, E, N, 4] before each step
    actions: jax.Array  # [T, E, N, A]
    rewards: jax.Array  # [T, E, N]
    terminated: jax.Array  # [T, E]
    layout: jax.Array  # [E, X, 2]
    final: jax.Array  # [E, N, 4] after the last step
    policy: Any = None  # [E, N] int32 (policy ensembles only)
    observed: Any = None  # [T, E, P] bool before each step (a view that shows them only)
    final_observed: Any = None  # [E, P] bool after the last step
    masks: Masks | None = None  # [E, ...] the slots that exist (mixed swarm sizes only)
    fail_step: Any = None  # [E, N] int32 (training with failures only)


def rovers_of(state: EnvState) -> jax.Array:
    """[..., N, 4]: every rover's velocity and position."""
    return jnp.concatenate([state.rover_vel, state.rover_pos], axis=-1)


def layout_of(state: EnvState) -> jax.Array:
    """[..., X, 2]: the POIs, then the traps."""
    return jnp.concatenate([state.poi_pos, state.trap_pos], axis=-2)


def episode_slots(capacity: int, num_envs: int, max_steps: int) -> int:
    """L: episode slots that cover every transition a ring of ``capacity`` can still hold."""
    return num_envs * math.ceil(capacity / (num_envs * max_steps))


def init(
    buffer: Buffer,
    params: EnvParams,
    num_envs: int,
    observed: bool = False,
    padded: bool = False,
    failures: bool = False,
) -> BufferState:
    """An empty compact replay of ``buffer``'s kind for ``params``'s swarm; with ``observed``,
    it also keeps which POIs were observed (for a view that shows them, such as
    :func:`~roverswarm.env.entities.observe_nearest`); with ``padded``, which slots exist in
    each episode (swarm sizes mixed in one replay); with ``failures``, each episode's
    failure steps."""
    n, p, x = params.num_rovers, params.num_pois, params.num_pois + params.num_traps
    example = Step(
        rovers=jnp.zeros((n, 4)),
        actions=jnp.zeros((n, ACTION_SIZE)),
        rewards=jnp.zeros((n,)),
        terminated=jnp.zeros((), bool),
        where=jnp.zeros((), jnp.int32),
        policy=jnp.zeros((n,), jnp.int32) if buffer.num_policies > 1 else None,
        observed=jnp.zeros((p,), bool) if observed else None,
    )
    slots = episode_slots(buffer.capacity, num_envs, params.max_steps)
    flags = lambda *shape: jnp.zeros((slots, *shape), bool)  # noqa: E731
    episodes = Episodes(
        layout=jnp.zeros((slots, x, 2)),
        final=jnp.zeros((slots, n, 4)),
        position=jnp.zeros((), jnp.int32),
        final_observed=flags(p) if observed else None,
        masks=Masks(flags(n), flags(p), flags(params.num_traps)) if padded else None,
        fail_step=jnp.full((slots, n), NEVER, jnp.int32) if failures else None,
    )
    return buffer.init(example).replace(episodes=episodes)


def add(buffer: Buffer, state: BufferState, batch: Collected) -> BufferState:
    """Store E whole episodes: their steps in the ring, their layouts and last states in the table."""
    steps, envs = batch.rewards.shape[:2]
    table = state.episodes
    slots = (table.position + jnp.arange(envs)) % table.layout.shape[0]  # [E]
    where = slots[None, :] * steps + jnp.arange(steps)[:, None]  # [T, E]
    policy = None if batch.policy is None else jnp.broadcast_to(batch.policy, (steps, *batch.policy.shape))
    records = Step(batch.rovers, batch.actions, batch.rewards, batch.terminated, where, policy, batch.observed)
    state = buffer.add(state, jax.tree.map(lambda x: x.reshape(steps * envs, *x.shape[2:]), records))
    per_episode = {"final_observed": batch.final_observed, "masks": batch.masks, "fail_step": batch.fail_step}
    kept = {}
    for name, new in per_episode.items():
        old = getattr(table, name)
        if (new is None) != (old is None):
            raise ValueError(f"compact.add: the episodes must carry {name} exactly when the replay keeps it")
        kept[name] = None if new is None else jax.tree.map(lambda o, v: o.at[slots].set(v), old, new)
    table = Episodes(
        layout=table.layout.at[slots].set(batch.layout),
        final=table.final.at[slots].set(batch.final),
        position=(table.position + envs) % table.layout.shape[0],
        **kept,
    )
    return state.replace(episodes=table)


def expand(
    state: BufferState, indices: jax.Array, params: EnvParams, num_envs: int, view: Callable | None = None
) -> Transition:
    """The transitions at ring ``indices`` (any shape), observations rebuilt: the flat view,
    or ``view`` (state, params) -> [N, O] of a replay that keeps the observed POIs (``init(...,
    observed=True)``). A replay that keeps each episode's masks (mixed sizes) rebuilds them
    and returns which rovers exist (:attr:`~roverswarm.buffers.base.Transition.rovers`); one
    that keeps failure steps rebuilds the failures at each step's time."""
    step = gather(state, indices)
    table = state.episodes
    capacity = state.data.rovers.shape[0]
    slot, t = jnp.divmod(step.where, params.max_steps)
    following = (indices + num_envs) % capacity  # the episode's next step
    last = t == params.max_steps - 1
    next_rovers = jnp.where(last[..., None, None], table.final[slot], state.data.rovers[following])
    lead = indices.shape
    flat = lambda x: x.reshape(-1, *x.shape[len(lead) :])  # noqa: E731  [*lead, ...] -> [M, ...]
    layout = flat(table.layout[slot])
    masks = None if table.masks is None else jax.tree.map(lambda m: flat(m[slot]), table.masks)
    fails = jnp.full((*lead, params.num_rovers), NEVER, jnp.int32) if table.fail_step is None else table.fail_step[slot]

    def observations(rovers: jax.Array, observed: jax.Array | None, time: jax.Array) -> jax.Array:
        rovers, poi, trap = flat(rovers), layout[:, : params.num_pois], layout[:, params.num_pois :]
        if view is None:
            obs = jax.vmap(observe_positions, in_axes=(0, 0, 0, 0, None, 0))(
                rovers[..., 2:], rovers[..., :2], poi, trap, params, masks
            )
        else:
            states = jax.vmap(EnvState)(
                rovers[..., 2:],
                rovers[..., :2],
                poi,
                trap,
                flat(observed),
                flat(time),
                flat(fails),
                *((None,) * 3 if masks is None else (masks.rovers, masks.pois, masks.traps)),
            )
            obs = jax.vmap(view, in_axes=(0, None))(states, params)
        return obs.reshape(*lead, *obs.shape[-2:])

    next_observed = None
    if view is not None:
        next_observed = jnp.where(last[..., None], table.final_observed[slot], state.data.observed[following])
    return Transition(
        obs=observations(step.rovers, step.observed, t),
        actions=step.actions,
        rewards=step.rewards,
        next_obs=observations(next_rovers, next_observed, t + 1),
        terminated=step.terminated,
        policy=step.policy,
        rovers=None if table.masks is None else table.masks.rovers[slot],
    )


def nbytes(tree: Any) -> int:
    """Bytes of every array of ``tree`` (arrays or :func:`jax.eval_shape` shapes)."""
    return sum(math.prod(x.shape) * jnp.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree))
