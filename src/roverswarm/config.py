"""Training configuration: :class:`TrainConfig`, validation and JSON.

A config is frozen, typed data (its field docstrings are the command line's ``--help``);
the named presets are configs too (:mod:`roverswarm.presets`), not code branches.
:func:`validate` is the one place a run's settings are checked: the command line and
:func:`roverswarm.train` call it alike.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import tyro

from roverswarm.algos.learner import NETWORKS, AlgoConfig
from roverswarm.algos.ppo import PPOConfig
from roverswarm.buffers.base import ReplayConfig
from roverswarm.env.entities import POI_ORDERS
from roverswarm.env.mars import EnvParams
from roverswarm.env.missions import load_mission, parse_mission_text, read_mission_text
from roverswarm.env.scenarios import get_scenario, padded_scenario
from roverswarm.episodes import sizes_of
from roverswarm.errors import UserError, require
from roverswarm.errors import require_finite as _finite
from roverswarm.errors import require_positive as _positive
from roverswarm.learners import ALGOS, FAMILY_OPTIONS, learner_family
from roverswarm.typed import check_types

DEFAULT_SCENARIO = "paper-3"


@dataclass(frozen=True)
class TrainConfig:
    """A training run. Defaults are tuned to learn with continuous actions: four times as many
    updates per environment step as the reference code, on batches a quarter the size (the
    same compute), noise 0.2; :data:`roverswarm.presets.REFERENCE` holds the reference values."""

    scenario: str = DEFAULT_SCENARIO
    """Scenario (see `roverswarm scenarios`): a preset, paper-N, or a range paper-A..B (or list
    paper-A,B,C) whose every episode draws its swarm size (needs --network nearest, or entity with
    --algo mappo or ippo)."""
    mission: str | None = None
    """Mission file (YAML/JSON) to train on instead of --scenario (give one of them): its
    POIs and traps fixed, rover starts drawn anywhere in the map, fixed-length episodes.
    Training stores its absolute path and its content: evaluation and resume need not find the
    file, and resume refuses a file that changed since."""
    mission_text: tyro.conf.Suppress[str | None] = None
    """The mission file's content, kept by training (not an option)."""
    nearest_first: bool = False
    """Each rover observes the POIs, traps and other rovers nearest first instead of in index
    order: the same view for every numbering of a layout."""
    learner: AlgoConfig = field(default_factory=AlgoConfig)
    buffer: ReplayConfig = field(default_factory=ReplayConfig)
    ppo: PPOConfig = field(default_factory=PPOConfig)
    episodes: int = 60_000
    """Training episodes per seed (a multiple of --log-every)."""
    seeds: int = 1
    """Independent seeds, trained together (vmapped) in one program."""
    seed: int = 0
    """Base random seed; seed s of the run uses a key derived from (seed, s)."""
    num_envs: int = 20
    """Parallel environments per seed. Does not change the updates per environment step."""
    update_every: int = 25
    """Environment steps (summed over parallel environments) per update of every agent."""
    warmup: int = 1024 * 25
    """Transitions stored before the first update."""
    noise_std: float = 0.2
    """Standard deviation of the Gaussian exploration noise added to actions (then clipped)."""
    noise_final: float = 0.2
    """Noise standard deviation after --noise-decay-episodes (linear decay from --noise-std)."""
    noise_decay_episodes: int = 0
    """Episodes over which the noise decays linearly to --noise-final; 0 keeps --noise-std."""
    log_every: int = 1000
    """Episodes per metrics row (and per jitted chunk)."""
    checkpoint_every: int = 10
    """Chunks (of --log-every episodes) between checkpoints; one is always written at the end."""
    fail_rate: float = 0.0
    """Probability per training episode that one rover, drawn uniformly, fails at a uniform
    step (it stops where it is; see docs/environment.md#rover-failures). Evaluation has none."""
    fail_count: int = 1
    """With --fail-rate: up to this many rovers fail in a failure episode, k drawn uniformly in
    [1, min(K, rovers - 1)] (one keeps working), each rover uniform and at its own uniform step;
    1: one. ``mission stress --failures K`` measures K failures."""
    fail_max_rovers: int = 0
    """With a range scenario and --fail-rate: failures, and --unobserved-shaping with them, only
    in episodes of at most this many rovers (the rover-loss lesson where a failure leaves fewer
    rovers than POIs to visit; the paper's reward elsewhere); 0: every size."""
    stop_when_complete: bool = False
    """A training episode ends once every POI has been observed (a mission file's
    ``stop_when_complete``): no reward after, so finishing sooner pays and a swarm that lost a
    rover must still visit every POI. Evaluation keeps the scenario's fixed-length episodes."""
    size_curriculum: int = 0
    """With a range scenario: the largest swarm size drawn grows linearly from the range's
    smallest to its largest over this many episodes; 0 draws every size from the start."""
    size_draw_power: float = 0.0
    """With a range scenario: a swarm of N rovers is drawn with probability proportional to
    N^-p (0: every size alike; 1: a swarm of 2 five times as often as one of 10)."""
    checkpoint_minutes: float = 10.0
    """A checkpoint is also written at the end of the first chunk that finishes this many
    minutes after the last one, so a killed long run loses at most about that much training;
    0 leaves checkpoints to --checkpoint-every alone. Never changes the run's numbers."""
    budget_minutes: float = 0.0
    """Wall-time budget: the run ends with the first chunk that finishes after this many
    minutes of training (summed over resumes, compilation included), or at --episodes, whichever
    comes first. Schedules count episodes, not minutes, so the episodes reached depend on the
    machine; the numbers up to them do not. A resume may raise it. 0: no budget."""

    def env_name(self) -> str:
        """What the run trains on: the scenario, or the mission file's name."""
        return self.scenario if self.mission is None else f"mission {Path(self.mission).stem}"


def _algo_options(config: TrainConfig) -> None:
    """Options of another learner family must stay at their defaults: the replay, exploration
    noise and MADDPG options with --algo mappo/ippo, the PPO options otherwise."""
    family = learner_family(config.learner.algo)
    defaults = fields_by_name(TrainConfig())
    for name, value in fields_by_name(config).items():
        if name in FAMILY_OPTIONS and name not in family.options:
            require(
                value == defaults[name],
                f"--{name.replace('_', '-')} {value} does not apply: {family.misfit.format(algo=config.learner.algo)}; "
                f"leave it at {defaults[name]}",
            )


def _representable(config: TrainConfig) -> None:
    """Every number can be represented where it is used: floats finite, counts below 2^31
    (int32 counters), the seed below 2^32 (a PRNG key keeps only its low 32 bits), widths
    between 1 and 2^16."""
    for name, value in fields_by_name(config).items():
        flag = f"--{name.replace('_', '-')}"
        if isinstance(value, bool) or value is None or isinstance(value, str):
            continue
        if isinstance(value, float):
            require(math.isfinite(value), f"{flag} must be a finite number, got {value}")
        elif name == "seed":  # as limits.check_seed says it (which config cannot import: a cycle)
            require(0 <= value < 2**32, f"{flag} must be an integer in [0, 2^32), got {value}")
        elif name == "hidden":
            require(
                len(value) >= 1 and all(1 <= w <= 2**16 for w in value),
                f"{flag} needs 1 or more widths in [1, 65536], got {value}",
            )
        else:
            require(abs(value) < 2**31, f"{flag} must be below 2^31, got {value}")


def validate(config: TrainConfig) -> EnvParams:
    """Check ``config``; raise :class:`UserError` naming the bad field. Returns the env params."""
    check_types(config, "config")
    _representable(config)
    require(
        config.mission is None or config.scenario == DEFAULT_SCENARIO,
        f"--scenario {config.scenario} (given, or set by --preset) and --mission: the mission file sets the "
        "layout and the number of rovers; give one of them",
    )
    sizes = sizes_of(config)
    if sizes is not None:
        require(
            config.learner.network in ("entity", "nearest"),
            f"--scenario {config.scenario} draws a swarm size per episode: it needs --network nearest, or entity with "
            "--algo mappo or ippo (networks that serve any size; start from --preset anysize)",
        )
        params = padded_scenario(config.scenario)
    elif config.mission is None:
        params = get_scenario(config.scenario)
    elif config.mission_text is None:
        params = load_mission(config.mission).training_params()
    else:
        params = parse_mission_text(config.mission_text, config.mission).training_params()
    params = params.replace(nearest_first=config.nearest_first)
    learner = config.learner
    require(learner.algo in ALGOS, f"--algo must be one of {', '.join(ALGOS)}, got '{learner.algo}'")
    _algo_options(config)
    _positive(config, ("episodes", "seeds", "num_envs", "log_every", "checkpoint_every"))
    _finite(config.checkpoint_minutes, 0, "checkpoint-minutes")
    _finite(config.budget_minutes, 0, "budget-minutes")
    require(
        0 <= config.fail_rate <= 1, f"--fail-rate must be in [0, 1] (a probability per episode), got {config.fail_rate}"
    )
    require(config.size_curriculum >= 0, f"--size-curriculum must be >= 0 episodes, got {config.size_curriculum}")
    _finite(config.size_draw_power, 0, "size-draw-power")
    require(
        config.fail_rate == 0 or params.num_rovers >= 2,
        f"--fail-rate needs at least 2 rovers (one fails, one keeps working), got {params.num_rovers}",
    )
    most = max(params.num_rovers - 1, 1)
    require(
        1 <= config.fail_count <= most,
        f"--fail-count must be in [1, {most}] (rovers lost per failure episode; of the largest swarm's "
        f"{params.num_rovers}, one keeps working), got {config.fail_count}",
    )
    require(
        config.fail_count == 1 or config.fail_rate > 0,
        f"--fail-count {config.fail_count} says how many rovers a failure episode loses; give --fail-rate p > 0",
    )
    require(config.fail_max_rovers >= 0, f"--fail-max-rovers must be >= 0 rovers, got {config.fail_max_rovers}")
    require(
        config.fail_max_rovers == 0 or config.fail_rate > 0,
        f"--fail-max-rovers {config.fail_max_rovers} limits --fail-rate to small swarms; give --fail-rate p > 0",
    )
    mixed = sizes is not None
    if mixed and config.fail_max_rovers:
        require(
            sizes[0] <= config.fail_max_rovers < sizes[-1],
            f"--fail-max-rovers {config.fail_max_rovers} must be in [{sizes[0]}, {sizes[-1] - 1}] for --scenario "
            f"{config.scenario}: below it no swarm fails, from {sizes[-1]} on every one may (0 says that)",
        )
    for option, on in (
        ("size-curriculum", config.size_curriculum != 0),
        ("balance-sizes", config.ppo.balance_sizes),
        ("size-draw-power", config.size_draw_power != 0),
        ("fail-max-rovers", config.fail_max_rovers != 0),
    ):
        require(not on or mixed, f"--{option} needs a range of swarm sizes, such as --scenario paper-2..10")
    entity = config.learner
    require(entity.network in NETWORKS, f"--network must be one of {', '.join(NETWORKS)}, got {entity.network!r}")
    require(entity.entity_dim >= 1, f"--entity-dim must be >= 1 (each token's width), got {entity.entity_dim}")
    require(
        entity.entity_heads >= 1 and entity.entity_dim % entity.entity_heads == 0,
        f"--entity-heads ({entity.entity_heads}) must be >= 1 and divide --entity-dim ({entity.entity_dim})",
    )
    require(entity.entity_layers >= 0, f"--entity-layers must be >= 0, got {entity.entity_layers}")
    require(entity.entity_nearest >= 0, f"--entity-nearest must be >= 0 (0: every entity), got {entity.entity_nearest}")
    require(
        entity.network != "nearest" or entity.entity_nearest >= 1,
        "--network nearest needs --entity-nearest K >= 1 (how many of each type a rover sees), got "
        f"{entity.entity_nearest}",
    )
    require(
        entity.poi_order in POI_ORDERS, f"--poi-order must be one of {', '.join(POI_ORDERS)}, got {entity.poi_order!r}"
    )
    require(
        entity.poi_order == "nearest" or (entity.network != "mlp" and entity.entity_nearest >= 1),
        f"--poi-order {entity.poi_order} orders the POIs of a view of the K nearest: give --network nearest (or "
        "entity) with --entity-nearest K >= 1 "
        f"(got --network {entity.network} --entity-nearest {entity.entity_nearest})",
    )
    require(
        config.log_every % config.num_envs == 0,
        f"--log-every ({config.log_every}) must be a multiple of --num-envs ({config.num_envs})",
    )
    require(
        config.episodes % config.log_every == 0,
        f"--episodes ({config.episodes}) must be a multiple of --log-every ({config.log_every})",
    )
    for name in ("actor_lr", "critic_lr", "grad_clip"):
        value = getattr(learner, name)
        require(value > 0, f"--{name.replace('_', '-')} must be positive, got {value}")
    for name in ("trap_shaping", "trap_margin", "collision_shaping", "observe_bonus", "unobserved_shaping"):
        _finite(getattr(learner, name), 0, name.replace("_", "-"))
    require(
        not learner.trap_margin or learner.trap_shaping > 0,
        f"--trap-margin {learner.trap_margin:g} sets where --trap-shaping starts; give --trap-shaping K > 0 with it",
    )
    require(0 <= learner.gamma <= 1, f"--gamma must be in [0, 1], got {learner.gamma}")
    learner_family(learner.algo).check(config, params)
    return params


def validate_training(config: TrainConfig) -> EnvParams:
    """:func:`validate`, and what training refuses besides (the family's
    :attr:`~roverswarm.learners.base.Family.check_training`), which a run folder written
    before may hold and still load and evaluate. Returns the env params."""
    params = validate(config)
    learner_family(config.learner.algo).check_training(config)
    return params


# ----------------------------------------------------------------------------- options and JSON


def with_mission_text(config: TrainConfig) -> TrainConfig:
    """``config`` with the mission file's absolute path and its content; :class:`UserError` if
    the file changed since ``config`` kept its content (a run resumed on an edited file)."""
    path = Path(config.mission).resolve()
    text = config.mission_text
    if text is None or path.exists():
        current = read_mission_text(path)
        require(
            text is None or current == text,
            f"mission file '{path}' changed since this run was trained on it; restore it, or train a new run",
        )
        text = current
    return dataclasses.replace(config, mission=str(path), mission_text=text)


def fields_by_name(config) -> dict[str, object]:
    """Every leaf field of a (nested) config dataclass, by name (names are unique across the nesting)."""
    flat: dict[str, object] = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        flat.update(fields_by_name(value) if dataclasses.is_dataclass(value) else {f.name: value})
    return flat


_NESTED = {"learner": AlgoConfig, "buffer": ReplayConfig, "ppo": PPOConfig}


def with_options(base: TrainConfig, options: dict[str, object], where: str = "options") -> TrainConfig:
    """``base`` with ``options`` replaced, each named by its leaf field name (as on the command
    line, with underscores); :class:`UserError` naming an unknown option."""
    owner = {f.name: part for part, cls in _NESTED.items() for f in dataclasses.fields(cls)}
    known = set(fields_by_name(base))
    shown = sorted(known - {"mission_text"})  # kept by the program beside --mission, not an option to give
    changes: dict[str, dict[str, object]] = {"": {}, **{part: {} for part in _NESTED}}
    for name, value in options.items():
        require(name in known, f"{where}: unknown option '{name}'; known: {', '.join(shown)}")
        changes[owner.get(name, "")][name] = tuple(value) if isinstance(value, list) else value  # type: ignore[arg-type]
    try:
        nested = {part: dataclasses.replace(getattr(base, part), **changes[part]) for part in _NESTED}
        config = dataclasses.replace(base, **changes[""], **nested)
    except TypeError as error:
        raise UserError(f"{where}: {error}") from error
    check_types(config, where)
    return config


RESUME_CHANGES = ("episodes", "budget_minutes")
"""The options a resumed run may change: ``--episodes`` and ``--budget-minutes``, to extend a
finished or interrupted run (docs/training.md#extending-a-run). Every other one is the run's own."""


def resumed_config(given: TrainConfig, saved: TrainConfig) -> TrainConfig:
    """The config a resume of the run trained with ``saved`` trains: its own, with ``given``'s
    :data:`RESUME_CHANGES`; :class:`UserError` naming the first other option in which
    ``given`` differs from the run."""
    values, kept = fields_by_name(given), fields_by_name(saved)
    for name, value in values.items():
        require(
            name in RESUME_CHANGES or value == kept[name], f"--resume: the run has {name}={kept[name]!r}, not {value!r}"
        )
    return dataclasses.replace(saved, **{name: values[name] for name in RESUME_CHANGES})


def config_to_json(config: TrainConfig) -> str:
    return json.dumps(dataclasses.asdict(config), indent=2)


def config_from_json(text: str) -> TrainConfig:
    """A config written by :func:`config_to_json`, also one from before the replay settings
    moved into ``buffer`` (they were top-level fields then) or from before ``--poi-order``
    (``free_pois_first: true`` is ``poi_order="free"``); :class:`UserError` if unreadable."""
    try:
        raw = json.loads(text)
        learner = raw.pop("learner")
        if learner.pop("free_pois_first", False):  # runs from before --poi-order
            learner["poi_order"] = "free"
        learner["hidden"] = tuple(learner["hidden"]) if isinstance(learner["hidden"], list) else learner["hidden"]
        replay = raw.pop("buffer", {})
        for f in dataclasses.fields(ReplayConfig):
            if f.name in raw:
                replay[f.name] = raw.pop(f.name)
        ppo = PPOConfig(**raw.pop("ppo", {}))
        config = TrainConfig(**raw, learner=AlgoConfig(**learner), buffer=ReplayConfig(**replay), ppo=ppo)
    except (ValueError, KeyError, TypeError, AttributeError, RecursionError) as error:
        raise UserError(f"config.json is not a roverswarm training config ({type(error).__name__}: {error})") from error
    check_types(config, "config.json")
    return config
