"""A learner family as one record of pure functions, and the state training carries.

A *family* (off-policy: MADDPG, DDPG and the MATD3 options; on-policy: MAPPO, IPPO) is one
frozen :class:`Family` record, built like the replay's :class:`~roverswarm.buffers.base.Buffer`:
the host loop (:func:`roverswarm.trainer.train`), the run folder (:class:`roverswarm.runs.Run`)
and the trained policies call its functions and never ask which family they hold. The
registry :mod:`roverswarm.learners` maps ``--algo`` to its family; a new family is one module
that builds a record, plus one line there.

What is compiled and what is data: ``configure(config, params)`` returns the family's own
config (a frozen, hashable dataclass) holding exactly what shapes the compiled chunk: the
learner's options and network sizes, the replay's, the seeds vmapped, the parallel
environments and the episodes per chunk. The base seed, the run's episode count and its
output folder are not in it: the seed goes to ``init`` and the episode count to
``run_chunk`` as traced data, so a second run with another seed or length compiles nothing
new (a replay capped at a short run's transitions is a new shape, though).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Hashable

import jax
import jax.numpy as jnp
from flax import struct

from roverswarm.buffers.base import BufferState
from roverswarm.env.mars import EnvParams
from roverswarm.jaxcache import stored_jit


@struct.dataclass
class Runner:
    """Everything training carries from chunk to chunk, and what a checkpoint holds (leading [S]
    where per seed)."""

    learner: Any  # [S, ...] the family's learner state: networks, optimisers, statistics
    buffer: BufferState | None  # [S, C, ...] the replay (None on-policy)
    key: jax.Array  # [S] PRNG keys
    episodes: jax.Array  # [] int32, episodes per seed so far (shared by all seeds)
    updates: jax.Array  # [] int32, updates of every network per seed so far (shared)


def _derived_keys(base: jax.Array, seeds: int) -> jax.Array:
    """[S, 2, 2] per seed s of the base seed's key ``base``: (init key, run key), from (seed, s)."""
    keys = jax.vmap(lambda s: jax.random.fold_in(base, s))(jnp.arange(seeds))
    return jax.vmap(jax.random.split)(keys)


def start_runner(
    seed: int,
    program: Program,
    params: EnvParams,
    init_seed: Callable[[Program, EnvParams, jax.Array], Any],
    replays: Callable[[Program, EnvParams], Any] | None = None,
) -> Runner:
    """Every seed's fresh state: ``init_seed(program, params, key)`` builds one seed's learner,
    from keys derived from (``seed``, s) for seed s of ``program.seeds`` (:func:`_derived_keys`);
    ``replays(program, params)`` the seeds' empty replays (None on-policy). Both functions are
    module-level (they key the compiled program with ``program``).

    One compiled program builds it all, kept for the next run of the same shapes (another seed
    compiles nothing new): run operation by operation, the initialisers compiled one small
    program per operation and shape, over a quarter of what a short run compiled (the same
    numbers either way)."""
    return _build(program, init_seed, replays, params, jax.random.PRNGKey(seed))


@stored_jit(static_argnums=(0, 1, 2))
def _build(
    program: Program, init_seed: Callable, replays: Callable | None, params: EnvParams, base: jax.Array
) -> Runner:
    keys = _derived_keys(base, program.seeds)
    counter = jnp.zeros((), jnp.int32)  # two outputs, two arrays (the runner is donated)
    learner = jax.vmap(lambda key: init_seed(program, params, key))(keys[:, 0])
    buffers = None if replays is None else replays(program, params)
    return Runner(learner=learner, buffer=buffers, key=keys[:, 1], episodes=counter, updates=counter)


Program = Any
"""A family's own config (its ``configure``'s result): frozen, hashable, the chunk's static key."""


@dataclass(frozen=True)
class Family:
    """A learner family as pure functions; see the module docstring. ``config`` below is a
    :class:`~roverswarm.config.TrainConfig`, ``program`` the family's own config."""

    name: str
    configure: Callable[[Any, EnvParams], Program]
    """(config, params) -> program: what of the run shapes the compiled chunk."""
    check: Callable[[Any, EnvParams], None]
    """(config, params) -> None: the family's own options are in range, else :class:`UserError`."""
    init: Callable[[Program, EnvParams, int], Runner]
    """(program, params, seed) -> every seed's fresh :class:`Runner` (the checkpoint's template)."""
    run_chunk: Callable[[Program, EnvParams, Runner, jax.Array], tuple[Runner, dict[str, jax.Array]]]
    """Jitted, keyed on the program: (program, params, runner, run episodes) -> (runner, per-seed
    metrics [S, ...]) after ``log_every`` more episodes per seed."""
    learners: Callable[[Program, EnvParams], Any]
    """(program, params) -> every seed's learner state [S, ...]: the template of a checkpoint's
    ``learner/`` arrays, without the replay."""
    acting: Callable[[Any], Hashable]
    """config -> what acting reads of it (hashable: rollouts of new weights reuse their programs)."""
    act: Callable[[Hashable, Any, jax.Array, Any], jax.Array]
    """(acting, weights, obs [..., N, O], plan) -> deterministic actions [..., N, A]; ``plan``:
    with ensembles, every agent's sub-policy [..., N]."""
    view: Callable[[Hashable], Callable[[Any, EnvParams], Any] | None]
    """acting -> the observation function :attr:`act` needs, (state, params) -> obs, when it is
    not the environment's flat view; such a policy serves any swarm size (None: the flat
    view, tied to the sizes it was trained on)."""
    weights: Callable[[Any], tuple[Any, Any]]
    """Learner state -> the ``weights`` of :attr:`act`: (actor parameters, observation
    normaliser or None)."""
    metric_names: Callable[[Any], tuple[str, ...]]
    """config -> the learner's per-update metrics in ``metrics.csv``."""
    replay: bool
    """Whether the family learns from a replay (its runner carries one)."""
    replay_buffer: Callable[[Program, EnvParams], Any]
    """(program, params) -> the replay's :class:`~roverswarm.buffers.base.Buffer` (None
    without a replay): what a resumed run's checkpoint is loaded into."""
    replay_bytes: Callable[[Any, EnvParams], tuple[int, int, int]]
    """(config, params) -> (bytes, transitions, bytes per transition) of every seed's replay."""
    options: frozenset[str]
    """The options (leaf field names of the config) only some families read, that this one reads."""
    misfit: str
    """Why another family's option does not apply to this one's ``{algo}``, for the error."""
    check_training: Callable[[Any], None] = lambda config: None
    """config -> None: what training refuses, else :class:`UserError`, beyond :attr:`check`:
    a run folder written before the rule may hold it, and must still load (nothing by default)."""
    idle: Callable[[Any, EnvParams], str | None] = lambda config, params: None
    """(run config, params) -> why a run of ``config`` would end without one update (``train``
    says so before it starts), or None (by default)."""


def no_replay(config: Any, params: EnvParams) -> tuple[int, int, int]:
    """:attr:`Family.replay_bytes` of a family that keeps no replay."""
    return 0, 0, 0
