"""What the off-policy family reads of a run (``--algo maddpg`` or ``ddpg``): its own config, the
checks of its options, and the replay capped at the run's own transitions.
:mod:`roverswarm.learners.offpolicy` builds the family's chunk from these."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from roverswarm.algos.learner import AlgoConfig
from roverswarm.buffers.base import ReplayConfig
from roverswarm.env.mars import EnvParams
from roverswarm.episodes import EpisodeOptions, sizes_of
from roverswarm.errors import require, require_finite, require_positive

RUN_OPTIONS = ("update_every", "warmup", "noise_std", "noise_final", "noise_decay_episodes")
"""The run options of learning from a replay with exploration noise."""


@dataclass(frozen=True)
class OffPolicyConfig(EpisodeOptions):
    """What shapes the off-policy chunk: the fields of the run's
    :class:`~roverswarm.config.TrainConfig` of the same names (so a ``TrainConfig`` serves
    wherever one is read), the episodes' among them (``stop_when_complete`` is always False
    here, see :func:`check`), with the replay capped at the run's own transitions."""

    learner: AlgoConfig
    buffer: ReplayConfig
    seeds: int
    num_envs: int
    update_every: int
    warmup: int
    noise_std: float
    noise_final: float
    noise_decay_episodes: int
    log_every: int


def run_replay(config, params: EnvParams) -> ReplayConfig:
    """The replay of run ``config`` (a ``TrainConfig``). It never holds more than the run's own
    transitions (``--episodes`` x episode length per seed), whatever ``--buffer-size`` says: a
    replay that never fills draws what a larger one would, so a short run gets the same
    numbers from a fraction of the memory."""
    capacity = min(config.buffer.buffer_size, config.episodes * params.max_steps)
    return dataclasses.replace(config.buffer, buffer_size=capacity)


def check(config, params: EnvParams) -> None:
    """The replay, exploration and MADDPG options of run ``config`` (a ``TrainConfig``) are in
    range and compose; else :class:`UserError` naming the option."""
    learner, replay = config.learner, config.buffer
    steps = config.num_envs * params.max_steps
    length = "the mission's episode_length" if config.mission else "episode length"
    require(
        learner.network != "entity",
        f"--network entity: --algo {learner.algo} has the flat view's and --network nearest's networks; use --algo "
        "mappo or ippo for attention over the entities",
    )
    require(
        not config.stop_when_complete,
        f"--stop-when-complete: --algo {learner.algo} learns from fixed-length episodes; use --algo mappo or ippo",
    )
    nearest = learner.network == "nearest"
    require(
        not nearest or learner.share_parameters,
        f"--network nearest with --algo {learner.algo} needs --share-parameters: one actor and one critic for "
        "every rover, without its index, so that the actor drives any swarm size",
    )
    require(
        not nearest or learner.algo == "ddpg" or learner.critic_neighbors >= 1,
        "--network nearest with --algo maddpg needs --critic-neighbors C >= 1: the critic sees the rover and its C "
        "nearest other rovers, nearest first, the same under any order of the rovers",
    )
    require(
        not nearest or not learner.normalize_obs,
        "--normalize-obs with --network nearest: the view's constant entries (masks, types, radii) would be "
        "standardised by a spread of 0 and saturate on swarms of other sizes; leave it off",
    )
    require(
        not learner.one_batch or learner.share_parameters,
        "--one-batch needs --share-parameters: one draw of transitions for every rover of one shared network",
    )
    require(
        not learner.one_batch or replay.replay == "uniform",
        f"--one-batch needs --replay uniform (got '{replay.replay}'): the ranked replay draws by each rover's own TD "
        "loss",
    )
    require(
        not replay.importance_weights or sizes_of(config) is None,
        f"--importance-weights with --scenario {config.scenario}: the weights are scaled by each batch's largest, "
        "which a rover absent from a smaller swarm would set; leave them off when sizes mix",
    )
    require(replay.replay in ("uniform", "ranked"), f"--replay must be 'uniform' or 'ranked', got '{replay.replay}'")
    require(replay.reading in ("paper", "schaul"), f"--reading must be 'paper' or 'schaul', got '{replay.reading}'")
    require(replay.alpha >= 0, f"--alpha must be >= 0, got {replay.alpha}")
    require(
        0 <= replay.importance_exponent <= 1,
        f"--importance-exponent must be in [0, 1], got {replay.importance_exponent}",
    )
    require(0 <= replay.beta <= 1, f"--beta must be in [0, 1], got {replay.beta}")
    require_positive(config, ("update_every",))
    require_positive(replay, ("batch_size", "buffer_size", "refresh_every"))
    require(config.warmup >= 0, f"--warmup must be >= 0, got {config.warmup}")
    require(
        replay.batch_size <= replay.buffer_size,
        f"--batch-size ({replay.batch_size}) must not exceed --buffer-size ({replay.buffer_size})",
    )
    require(
        steps % config.update_every == 0,
        f"--num-envs x episode length ({steps}) must be a multiple of --update-every ({config.update_every})",
    )
    require(learner.tau > 0, f"--tau must be positive, got {learner.tau}")
    require(learner.tau <= 1, f"--tau must be in (0, 1] (the share of the new weights per update), got {learner.tau}")
    require(learner.ensemble >= 1, f"--ensemble must be >= 1 (sub-policies per agent), got {learner.ensemble}")
    require(learner.infer_entropy >= 0, f"--infer-entropy must be >= 0, got {learner.infer_entropy}")
    require(learner.infer_window >= 1, f"--infer-window must be >= 1 transition, got {learner.infer_window}")
    require(
        not learner.infer_policies or learner.algo == "maddpg",
        "--infer-policies needs --algo maddpg: a DDPG critic never sees the other agents' actions",
    )
    require(
        not learner.infer_policies or params.num_rovers >= 2,
        "--infer-policies needs at least 2 rovers: there is no other agent to infer",
    )
    require(
        not learner.share_parameters or (learner.ensemble == 1 and not learner.infer_policies),
        "--share-parameters does not compose with --ensemble > 1 or --infer-policies (they need one network per agent)",
    )
    require(
        0 <= learner.critic_neighbors < params.num_rovers,
        f"--critic-neighbors must be in [0, {params.num_rovers - 1}]: the other rovers each critic sees besides its "
        f"own, of {params.num_rovers} (0 = all), got {learner.critic_neighbors}",
    )
    require(
        not learner.critic_neighbors or learner.algo == "maddpg",
        "--critic-neighbors needs --algo maddpg: a DDPG critic sees no other rover",
    )
    require(learner.actor_delay >= 1, f"--actor-delay must be >= 1, got {learner.actor_delay}")
    require_finite(learner.target_noise, 0, "target-noise")
    require_finite(learner.target_noise_clip, 0, "target-noise-clip")
    require_finite(learner.reward_scale, 0, "reward-scale", strict=True)
    require_finite(learner.action_penalty, 0, "action-penalty")
    require(
        replay.buffer_size >= steps,
        f"--buffer-size ({replay.buffer_size}) must hold one iteration's transitions (--num-envs "
        f"{config.num_envs} x {length} {params.max_steps} = {steps})",
    )
    for name in ("noise_std", "noise_final", "noise_decay_episodes"):
        value = getattr(config, name)
        require(value >= 0, f"--{name.replace('_', '-')} must be >= 0, got {value}")


def configure(config, params: EnvParams) -> OffPolicyConfig:
    """The off-policy config of run ``config`` (a ``TrainConfig``)."""
    fields = {f.name: getattr(config, f.name) for f in dataclasses.fields(OffPolicyConfig)}
    return OffPolicyConfig(**{**fields, "buffer": run_replay(config, params)})
