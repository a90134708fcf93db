"""The learner's parts that acting and training share: its config, its state, its networks
and what they see.

Shape legend: N agents, K sub-policies per agent, B batch, O observation size, A action size (2).
Parameters are stacked on a leading group axis ([N * K] actors, [N] critics; [1] shared);
:mod:`roverswarm.algos.maddpg` holds the update and its equations.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass
from typing import Any, Literal

import jax
import jax.numpy as jnp
import optax
from flax import struct

from roverswarm.algos.inference import gaussian_policies
from roverswarm.algos.networks import MLP, actor_forward, critic_forward
from roverswarm.algos.normalize import ObsNorm, init_obs_norm, normalize, update_obs_norm
from roverswarm.buffers.base import Transition
from roverswarm.env.entities import nearest_width
from roverswarm.env.mars import ACTION_SIZE, OWN_POSITION, EnvParams, observation_size, other_rovers

Algo = Literal["maddpg", "ddpg", "mappo", "ippo"]
"""The ``--algo`` choices; :data:`roverswarm.learners.FAMILIES` maps each to its learner family."""

Network = Literal["mlp", "entity", "nearest"]
NETWORKS = typing.get_args(Network)
"""The ``--network`` choices (:attr:`AlgoConfig.network`), checked by :func:`roverswarm.config.validate`."""


@dataclass(frozen=True)
class AlgoConfig:
    """Learner hyper-parameters. Defaults are tuned to learn with continuous actions (wider
    networks, smaller learning rates than the reference code's 2x64 and 1e-2; see
    ``roverswarm.presets.REFERENCE``)."""

    algo: Algo = "maddpg"
    """`maddpg`: centralised critics Q_i(x, a_1..a_N); `ddpg`: local critics Q_i(o_i, a_i);
    `mappo` / `ippo`: PPO with one shared actor and a centralised / local value (start from
    --preset mappo or ippo)."""
    actor_lr: float = 1e-3
    """Adam learning rate of the actors."""
    critic_lr: float = 1e-3
    """Adam learning rate of the critics."""
    gamma: float = 0.95
    """Discount factor."""
    tau: float = 0.01
    """Soft target update rate."""
    grad_clip: float = 0.5
    """Global gradient-norm clip of each network's update (the twin critics of
    ``twin_critics``, stacked, are clipped together: one norm over both)."""
    hidden: tuple[int, ...] = (128, 128)
    """Hidden layer widths of actors and critics (ReLU)."""
    action_penalty: float = 1e-3
    """Weight of the mean squared pre-tanh actor output in the actor loss."""
    ensemble: int = 1
    """Sub-policies per agent (policy ensembles, eq. 9-11): one drawn per agent per episode,
    each learning from its own replay partition; 1 = plain MADDPG."""
    infer_policies: bool = False
    """MADDPG only: each agent learns Gaussian approximations of the other agents' policies
    from the replay and uses them in its critic's target instead of their true policies (eq. 7-8)."""
    infer_entropy: float = 1e-3
    """lambda: weight of the entropy bonus in the approximations' loss (--infer-policies)."""
    infer_window: int = 10_000
    """--infer-policies: the approximations fit batches drawn from the newest this many
    transitions of the replay, so they follow the others' current policies."""
    share_parameters: bool = False
    """One actor and one critic for all rovers, with the rover's one-hot index as an input (not
    over --network nearest, which serves any swarm size) and the critic's view ordered
    own-first; every update learns from all rovers' batches (one batch for all with
    --one-batch). Not with --ensemble > 1 or --infer-policies."""
    one_batch: bool = False
    """With --share-parameters (uniform replay): each update draws one batch of transitions and
    learns from every rover in it, instead of one batch per rover; the compact replay then
    rebuilds N times fewer observations per update (what makes training across sizes fast)."""
    critic_neighbors: int = 0
    """MADDPG: each critic sees its own rover and only the nearest this many other rovers
    (their observations and actions, nearest first by the positions in the observations it is
    given, per transition) instead of every rover; 0 = every rover (the paper's centralised critic)."""
    twin_critics: bool = False
    """Two critics per agent; the target takes the smaller of their estimates (TD3/MATD3)."""
    target_noise: float = 0.0
    """Std of the clipped Gaussian noise added to target actions (target-policy smoothing); 0 = off."""
    target_noise_clip: float = 0.5
    """Target-policy smoothing noise is clipped to [-this, this]."""
    actor_delay: int = 1
    """Critic updates per update of the actors and the target networks (TD3's delay; 1 = every time)."""
    layer_norm: bool = False
    """LayerNorm after every hidden layer of actors and critics."""
    normalize_obs: bool = False
    """Standardise observations by a running mean and variance (kept in checkpoints)."""
    reward_scale: float = 1.0
    """Rewards are multiplied by this before the critic's targets."""
    network: Network = "mlp"
    """`mlp`: networks on the flat view, tied to the swarm size they trained on; `entity`:
    attention over the entity view (other rovers, POIs, traps as tokens, no rover ids);
    `nearest`: an MLP over the --entity-nearest K nearest of each type, nearest first. The last
    two serve any swarm size (MAPPO and IPPO; `nearest` also MADDPG and DDPG with
    --share-parameters)."""
    entity_dim: int = 64
    """--network entity: width of the entity embeddings (the encoder's output is twice this)."""
    entity_heads: int = 4
    """--network entity: attention heads (must divide --entity-dim)."""
    entity_layers: int = 1
    """--network entity: self-attention blocks among the tokens before the pooling (0: embed and pool)."""
    entity_nearest: int = 0
    """--network entity: each rover sees only the nearest this many other rovers, POIs and traps
    (each type), which keeps the cost of a step per rover constant in the swarm's size; 0 =
    every entity (a cost that grows with it).
    --network nearest: how many of each type it sees (>= 1)."""
    poi_order: Literal["nearest", "free", "matched"] = "nearest"
    """With a view of the K nearest of each type (--network nearest, or entity with
    --entity-nearest), the order of the K POI slots. `nearest`: nearest first. `free`: the POIs
    that no nearer rover claims as its nearest (claim lead > 0) first, each part nearest first,
    so that a rover whose nearest POIs are taken sees an open one however far it is (the
    nearest K alone hide it from N = K + 1 POIs). `matched`: the POI that a greedy matching of
    the working rovers to the POIs (the nearest pair first, recomputed every step; two rovers'
    POIs swapped while that shortens their sum, so routes do not cross) gives the rover first,
    then the rest nearest first; a POI not yet observed that the matching leaves
    to no working rover (its rover failed, or more POIs than rovers) goes to a rover whose POI
    is observed, as the oracle reassigns; the POI tokens' claim feature holds that matching
    (1 on the rover's POI, else 0) instead of the claim lead. A POI observed earlier
    counts as any other: the coverage reward charges its distance too."""
    trap_shaping: float = 0.0
    """Reward shaping: the learner trains on the environment's reward less this much more per
    trap a rover touches per step (the environment charges 1); what it reports, and every
    evaluation, stays the environment's reward. MADDPG, DDPG, MAPPO and IPPO."""
    trap_margin: float = 0.0
    """With --trap-shaping: charge the shaping from this far off a trap, not only on contact. A
    rover whose gap to a trap (centre distance less both radii) is g pays --trap-shaping x
    clip(1 - g / M, 0, 1) per trap and step: the full amount on contact, nothing at M or
    farther, a ramp between that tells the learner which way is clear before it touches. 0
    (default): per contact only. Evaluations stay the environment's. MADDPG, DDPG, MAPPO, IPPO."""
    collision_shaping: float = 0.0
    """Reward shaping: as --trap-shaping, for the other rovers: the learner trains on the
    environment's reward less this much more per other rover a rover touches per step (the
    environment charges 1); reports and evaluations stay the environment's reward. MADDPG,
    DDPG, MAPPO and IPPO."""
    observe_bonus: float = 0.0
    """Reward shaping: the learner trains on the environment's reward plus this much for every
    rover each time a POI is observed for the first time in the episode (a reason to visit
    every POI, not only to cover them); reports and evaluations stay the environment's
    reward. MADDPG, DDPG, MAPPO and IPPO."""
    unobserved_shaping: float = 0.0
    """Reward shaping: the learner trains on the environment's reward less this much times, per
    step and for every rover, the sum over the POIs not yet observed of the nearest working
    rover's distance. The paper's coverage counts observed POIs too, so two rovers left with
    three POIs are best placed between them; this pays for visiting the last one. Reports and
    evaluations stay the environment's reward. MADDPG, DDPG, MAPPO and IPPO."""
    shield: bool = False
    """Train and act behind the safety layer (roverswarm.steering): where the velocity a
    rover's action asks for would carry it, within a few steps, into a trap's or another
    rover's keep-out circle, the environment gets the action turned along the circle's tangent
    (the policy learns from its own action, the layer being part of the world it acts in).
    Every evaluation and mission of the run keeps the layer, and its export holds it (in NumPy,
    beside the ONNX model). MADDPG, DDPG, MAPPO and IPPO."""


@struct.dataclass
class LearnerState:
    """Every agent's networks, targets and optimiser states, stacked on a leading group axis:
    [N * K] for the actors (sub-policy k of agent i at i * K + k), [N] for the critics; [1]
    for both with shared parameters. Twin critics add an axis of 2 after the group axis."""

    actor: Any  # [N * K, ...]: sub-policy k of agent i at i * K + k
    critic: Any  # [N, ...] or [N, 2, ...]
    target_actor: Any  # [N * K, ...]
    target_critic: Any  # [N, ...] or [N, 2, ...]
    actor_opt: Any  # [N * K, ...]
    critic_opt: Any  # [N, ...]
    approx: Any = None  # [N, N, ...]: agent i's approximation of agent j's policy (inferred policies)
    approx_opt: Any = None  # [N, N, ...]
    target_approx: Any = None  # [N, N, ...]: the approximations' targets (eq. 8), soft-updated as the target actors
    obs_norm: ObsNorm | None = None  # --normalize-obs
    updates: jax.Array | None = None  # [] int32 updates so far (--actor-delay > 1)


def observation_width(config: AlgoConfig, params: EnvParams) -> int:
    """The width of one rover's observation as ``config``'s networks read it: the --network
    nearest view's (one width for any swarm size), else the flat view's of ``params``."""
    return nearest_width(config.entity_nearest) if config.network == "nearest" else observation_size(params)


def networks(config: AlgoConfig) -> tuple[MLP, MLP]:
    """The (actor, critic) modules of ``config``."""
    return MLP(config.hidden, ACTION_SIZE, config.layer_norm), MLP(config.hidden, 1, config.layer_norm)


def optimizers(config: AlgoConfig) -> tuple[optax.GradientTransformation, optax.GradientTransformation]:
    """Adam with global-norm clipping, for (actors, critics)."""
    clip = optax.clip_by_global_norm(config.grad_clip)
    return optax.chain(clip, optax.adam(config.actor_lr)), optax.chain(clip, optax.adam(config.critic_lr))


def groups(config: AlgoConfig, num_agents: int) -> int:
    """Critics (and actors per sub-policy) in the learner state: 1 if shared, else N."""
    return 1 if config.share_parameters else num_agents


def _indexed(config: AlgoConfig) -> bool:
    """Whether shared networks see the rover's one-hot index: over the flat view only (the
    nearest view has no rover order to tell apart, and its width serves any swarm size)."""
    return config.share_parameters and config.network == "mlp"


def actor_inputs(config: AlgoConfig, obs: jax.Array) -> jax.Array:
    """What the actors see of [..., N, O] observations: the observation, and with shared
    parameters over the flat view the rover's one-hot index after it ([..., N, O + N])."""
    if not _indexed(config):
        return obs
    n = obs.shape[-2]
    return jnp.concatenate([obs, jnp.broadcast_to(jnp.eye(n, dtype=obs.dtype), (*obs.shape[:-2], n, n))], axis=-1)


def critic_inputs(
    config: AlgoConfig, obs: jax.Array, actions: jax.Array, agent: jax.Array, rovers: jax.Array | None = None
) -> jax.Array:
    """What agent ``agent``'s critic sees: [B, N, O] observations and [B, N, A] actions -> [B, D].
    Shared parameters: own-first order and, over the flat view, the one-hot index appended.
    ``critic_neighbors`` K > 0: the agent and its K nearest other rovers, nearest first, in each
    transition; of mixed swarm sizes (``rovers`` [B, N] bool: the rovers that exist), the
    nearest that exist, then zeros where a swarm has fewer than K others. The distances are
    those of ``obs`` as given: with --normalize-obs the standardised positions, x and y each
    divided by its own running standard deviation (nearly equal on layouts symmetric in x and
    y, as the paper-N layouts are; a mission stretched along one axis orders by the other)."""
    batch, n = obs.shape[:2]
    if config.algo == "ddpg":
        inputs = [obs[:, agent], actions[:, agent]]
    elif config.critic_neighbors:
        pos = obs[..., OWN_POSITION]  # [B, N, 2]
        dist = jnp.sum(jnp.square(pos - pos[:, agent, None]), axis=-1)
        if rovers is not None:
            dist = jnp.where(rovers, dist, jnp.inf)
        dist = dist.at[:, agent].set(-1.0)  # own first
        order = jnp.argsort(dist, axis=1, stable=True)[:, : 1 + config.critic_neighbors, None]  # ties: lower index
        present = True if rovers is None else jnp.take_along_axis(rovers[..., None], order, axis=1)

        def seen(x: jax.Array) -> jax.Array:  # [B, 1 + K, ...] flattened, zero where no rover is
            return jnp.where(present, jnp.take_along_axis(x, order, axis=1), 0.0).reshape(batch, -1)

        inputs = [seen(obs), seen(actions)]
    elif config.share_parameters:
        order = jnp.concatenate([agent[None], jnp.asarray(other_rovers(n))[agent]])
        inputs = [obs[:, order].reshape(batch, -1), actions[:, order].reshape(batch, -1)]
    else:
        inputs = [obs.reshape(batch, -1), actions.reshape(batch, -1)]
    if _indexed(config):
        inputs.append(jnp.broadcast_to(jax.nn.one_hot(agent, n, dtype=obs.dtype), (batch, n)))
    return jnp.concatenate(inputs, axis=-1)


def critic_values(config: AlgoConfig, params, inputs: jax.Array) -> jax.Array:
    """Q [C, B] of critic inputs [B, D]: C = 2 with twin critics, else 1."""
    _, critic_net = networks(config)
    if config.twin_critics:
        return jax.vmap(lambda p: critic_forward(critic_net, p, inputs))(params)
    return critic_forward(critic_net, params, inputs)[None]


def init_learner(key: jax.Array, config: AlgoConfig, num_agents: int, obs_size: int) -> LearnerState:
    """Fresh networks for ``num_agents`` agents; targets start equal to the online networks."""
    actor_net, critic_net = networks(config)
    actor_opt, critic_opt = optimizers(config)
    k_actor, k_critic = jax.random.split(key)
    obs = jnp.zeros((1, num_agents, obs_size))
    actions = jnp.zeros((1, num_agents, ACTION_SIZE))
    critic_in = critic_inputs(config, obs, actions, jnp.int32(0))
    g = groups(config, num_agents)
    actor = jax.vmap(actor_net.init, in_axes=(0, None))(
        jax.random.split(k_actor, g * config.ensemble), actor_inputs(config, obs)[:, 0]
    )
    critic_keys = jax.random.split(k_critic, g)
    if config.twin_critics:
        critic_keys = jax.vmap(lambda k: jax.random.split(k, 2))(critic_keys)
        critic = jax.vmap(jax.vmap(critic_net.init, in_axes=(0, None)), in_axes=(0, None))(critic_keys, critic_in)
    else:
        critic = jax.vmap(critic_net.init, in_axes=(0, None))(critic_keys, critic_in)
    approx = approx_opt = None
    if config.infer_policies:
        keys = jax.random.split(jax.random.fold_in(key, 2), num_agents * num_agents)
        flat = jax.vmap(gaussian_policies(config.hidden).init, in_axes=(0, None))(keys, obs[:, 0])
        approx = jax.tree.map(lambda x: x.reshape(num_agents, num_agents, *x.shape[1:]), flat)
        approx_opt = jax.vmap(jax.vmap(optimizers(config)[0].init))(approx)
    obs_norm = None
    if config.normalize_obs:
        obs_norm = init_obs_norm(obs_size)
    return LearnerState(
        approx=approx,
        approx_opt=approx_opt,
        target_approx=None if approx is None else jax.tree.map(jnp.copy, approx),
        actor=actor,
        critic=critic,
        # copies, not aliases: the training loop donates its state buffers
        target_actor=jax.tree.map(jnp.copy, actor),
        target_critic=jax.tree.map(jnp.copy, critic),
        actor_opt=jax.vmap(actor_opt.init)(actor),
        critic_opt=jax.vmap(critic_opt.init)(critic),
        obs_norm=obs_norm,
        updates=jnp.zeros((), jnp.int32) if config.actor_delay > 1 else None,
    )


def observe_batch(config: AlgoConfig, state: LearnerState, obs: jax.Array) -> LearnerState:
    """With --normalize-obs, fold collected observations [..., O] into the state's normaliser."""
    return state.replace(obs_norm=update_obs_norm(state.obs_norm, obs)) if config.normalize_obs else state


def prepare(config: AlgoConfig, state: LearnerState, batch: Transition) -> Transition:
    """A replay batch as the networks see it: observations standardised, rewards scaled."""
    return batch.replace(
        obs=normalize(state.obs_norm, batch.obs),
        next_obs=normalize(state.obs_norm, batch.next_obs),
        rewards=batch.rewards * config.reward_scale,
    )


# ----------------------------------------------------------------------------- acting


def act(
    config: AlgoConfig, actor_params, obs: jax.Array, policy: jax.Array | None = None, obs_norm: ObsNorm | None = None
) -> jax.Array:
    """Deterministic actions of all agents: [..., N, O] observations -> [..., N, A] actions;
    with ensembles (K > 1), of the sub-policies ``policy`` [..., N] the agents run;
    with ``obs_norm``, on observations standardised by it."""
    actor_net, _ = networks(config)
    forward = lambda p, o: actor_forward(actor_net, p, o)[0]  # noqa: E731
    inputs = actor_inputs(config, normalize(obs_norm, obs))
    if config.share_parameters:
        return forward(jax.tree.map(lambda x: x[0], actor_params), inputs)
    if config.ensemble == 1:
        return jax.vmap(forward, in_axes=(0, -2), out_axes=-2)(actor_params, inputs)
    params = jax.tree.map(lambda x: x.reshape(-1, config.ensemble, *x.shape[1:]), actor_params)  # [N, K, ...]
    every = jax.vmap(jax.vmap(forward, in_axes=(0, None), out_axes=-2), in_axes=(0, -2), out_axes=-3)(params, inputs)
    return jnp.take_along_axis(every, policy[..., None, None], axis=-2)[..., 0, :]  # [..., N, K, A] -> [..., N, A]


def smoothed(config: AlgoConfig, actions: jax.Array, key: jax.Array | None) -> jax.Array:
    """Target actions with target-policy smoothing noise (unchanged if --target-noise is 0)."""
    if config.target_noise == 0:
        return actions
    noise = config.target_noise * jax.random.normal(key, actions.shape)
    return jnp.clip(actions + jnp.clip(noise, -config.target_noise_clip, config.target_noise_clip), -1.0, 1.0)
