"""The named starting points of ``roverswarm train --preset``: each a :class:`TrainConfig`.

Options given beside ``--preset`` change the preset (:func:`roverswarm.config.with_options`).
``docs/training.md#presets`` says which preset is for what.
"""

from __future__ import annotations

import dataclasses

from roverswarm.algos.learner import AlgoConfig
from roverswarm.buffers.base import ReplayConfig
from roverswarm.config import TrainConfig

REFERENCE = TrainConfig(
    learner=AlgoConfig(
        actor_lr=1e-2, critic_lr=1e-2, gamma=0.95, tau=0.01, grad_clip=0.5, hidden=(64, 64), action_penalty=1e-3
    ),
    buffer=ReplayConfig(batch_size=1024, buffer_size=1_000_000, refresh_every=250),
    update_every=100,
    warmup=1024 * 25,
    noise_std=0.1,
    noise_final=0.1,
    noise_decay_episodes=0,
)
"""The reference MADDPG code's hyper-parameters (openai/maddpg). The paper states only its
networks (2 x 64); the rest are the reference code's, not the paper's."""

SWARM = TrainConfig(
    nearest_first=True,
    learner=AlgoConfig(share_parameters=True, twin_critics=True, target_noise=0.2, actor_delay=2),
)
"""Homogeneous rovers learning together: one shared actor and critic (with the rover's id),
twin critics with target smoothing and delayed actor updates (MATD3), on the nearest-first
view. The best settings of the paper-5 sweeps (``docs/results/swarm/``): MATD3 over shared
networks 0.10 / 0.16 after 20,000 episodes, with the nearest-first view 0.35 / 0.37; layer
norm and observation normalisation made it worse. Its critic is the paper's centralised one,
the better at N <= 3; from N = 4 on, DDPG's local critic Q(o_i, a_i, i) learns more
(``--preset swarm --algo ddpg``: 0.40-0.59 against 0.26-0.38 at N = 5 after 20,000 episodes,
0.60-0.80 against 0.47-0.67 after 60,000, 5 seeds)."""

MAPPO = TrainConfig(
    nearest_first=True,
    num_envs=100,
    learner=AlgoConfig(algo="mappo", actor_lr=1e-3, critic_lr=1e-3, gamma=0.95, grad_clip=0.5, hidden=(64, 64)),
)
"""MAPPO (:mod:`roverswarm.algos.ppo`): one shared actor, a centralised value, 100 parallel
environments, tanh 2 x 64 networks, on the nearest-first view."""

IPPO = dataclasses.replace(MAPPO, learner=dataclasses.replace(MAPPO.learner, algo="ippo"))
"""IPPO: as :data:`MAPPO` with a local value V(o_i, i)."""

ANYSIZE = dataclasses.replace(
    MAPPO,
    scenario="paper-2..10",
    episodes=80_000,
    size_curriculum=15_000,
    learner=dataclasses.replace(
        MAPPO.learner, network="nearest", entity_nearest=4, hidden=(128, 128), poi_order="matched"
    ),
    ppo=dataclasses.replace(MAPPO.ppo, balance_sizes=True, anneal_episodes=80_000, swarm_value=True),
)
"""One policy for every swarm size: MAPPO whose 2 x 128 actor and value see each rover's 4
nearest other rovers, POIs and traps (no rover ids), the POI that a greedy matching of the
rovers to the POIs (crossing routes swapped, a failed rover's open POI handed over) gives
the rover first (``--poi-order matched``; a POI's token carries the rover's lead on it and
that matching), the value also the whole swarm's mean view and size (``--swarm-value``),
trained on swarms of 2 to 10 rovers, a size drawn per episode, the largest size drawn growing
from 2 to 10 over the first 15,000 episodes, each episode weighing the same in the loss
whatever its size (``--balance-sizes``); 80,000 episodes, the learning rates decaying
linearly to 0 over them (``--anneal-episodes``: give it with ``--episodes``, or the rates stop
short of 0 or reach it early), 53 minutes for 5 seeds on 2 cores (``docs/results/any-size/``).
Attention over the entities (``--network entity``) is the other encoder; one update cost 13 to
43 times as much here (docs/results/any-size/README.md), too slow for a 5-seed run so far."""

ANYSIZE_DDPG = dataclasses.replace(
    SWARM,
    scenario="paper-2..10",
    episodes=60_000,
    size_curriculum=5_000,
    learner=dataclasses.replace(SWARM.learner, algo="ddpg", network="nearest", entity_nearest=4, one_batch=True),
)
"""One policy for every swarm size from the off-policy family: the :data:`SWARM` preset's DDPG
(a local critic Q(o_i, a_i), shared 2 x 128 networks, twin critics) over the nearest view of
:data:`ANYSIZE` (4 of each type, no rover ids), trained on swarms of 2 to 10 rovers, the
largest size drawn growing to 10 over the first 5,000 episodes, every rover learning from one
draw of transitions per update (``--one-batch``); 60,000 episodes, about 117 minutes for 5
seeds on 2 cores. It scores 0.14 to 0.23 below :data:`ANYSIZE` at every size from 2 to 10 (0.03
to 0.13 below the earlier 250,000-episode any-size run) but touches traps
at most twice as often as the oracle from N = 5 up (``docs/results/any-size/``). ``--algo
maddpg --critic-neighbors 2`` gives MATD3's centralised critic over each rover's 2 nearest others."""

PRESETS: dict[str, TrainConfig] = {
    "default": TrainConfig(),
    "reference": REFERENCE,
    "swarm": SWARM,
    "mappo": MAPPO,
    "ippo": IPPO,
    "anysize": ANYSIZE,
    "anysize-ddpg": ANYSIZE_DDPG,
}
"""Named starting points of `roverswarm train --preset`; other options change them."""
