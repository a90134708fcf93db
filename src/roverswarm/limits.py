"""Limits on what the package reads and allocates, checked before the work starts.

- Names a file or option gives become paths only through :func:`safe_name`: one path
  component of a safe character set, never absolute, never ``..``.
- Files are read through :func:`read_limited` / :func:`open_limited`, which refuse a file
  larger than its limit without reading more than the limit (:data:`FILE_LIMITS`).
- Seeds of episodes are checked by :func:`check_seed` (a PRNG key takes 32 bits).
- :func:`check_memory` estimates, from shapes only (nothing is allocated), the memory a run
  or an evaluation needs (networks with their optimisers, replay, rollouts, minibatches,
  evaluation batches) and refuses one past 80% of the memory this process may use, naming
  the option that sets the largest part.

docs/limits.md lists every limit and what its error says.
"""

from __future__ import annotations

import contextlib
import io
import math
import numbers
import os
import re
from dataclasses import dataclass, replace
from pathlib import Path
from typing import IO, TYPE_CHECKING, Iterator

from roverswarm.errors import UserError, require

if TYPE_CHECKING:
    from roverswarm.config import TrainConfig
    from roverswarm.env.mars import EnvParams

# ----------------------------------------------------------------------------- names

NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]{0,99}")
"""A name that may become a folder: a letter or digit, then up to 99 letters, digits, ``. _ + -``."""


def safe_name(value: object, where: str) -> str:
    """``value`` if it can be one path component (see :data:`NAME_PATTERN`; no ``..``), else
    :class:`UserError` naming ``where``."""
    ok = isinstance(value, str) and NAME_PATTERN.fullmatch(value) is not None and ".." not in value
    require(
        ok,
        f"{where}: {value!r} cannot name a folder; use 1-100 letters, digits, '.', '_', '+' or '-', "
        "starting with a letter or digit (no '/', no '..')",
    )
    return str(value)


# ----------------------------------------------------------------------------- files

KiB, MiB, GiB = 2**10, 2**20, 2**30

FILE_LIMITS: dict[str, int] = {
    "config.json": 1 * MiB,  # a training config is about 2 KB (a mission's content included: at most 1 MB)
    "sweep file": 1 * MiB,  # a sweep of dozens of settings is a few KB
    "metrics.csv": 1 * GiB,  # 500 bytes per row: 2 million rows (e.g. 100 seeds x 20,000 chunks)
    "evaluation table": 64 * MiB,
}
"""Largest file of each kind the package reads, in bytes (mission files:
:data:`roverswarm.env.missions.MAX_BYTES`)."""


def _too_large(path: Path, kind: str, size: int | str) -> UserError:
    limit = FILE_LIMITS[kind]
    return UserError(f"{kind} '{path}' has {size} bytes; at most {limit} ({limit / MiB:g} MiB) are read")


@contextlib.contextmanager
def open_limited(path: Path, kind: str) -> Iterator[IO[str]]:
    """``path`` opened as UTF-8 text for streaming (e.g. a CSV reader), refused with
    :class:`UserError` if it is larger than ``FILE_LIMITS[kind]``; a file that grows past the
    limit while it is read is refused too, and never read beyond it."""
    limit = FILE_LIMITS[kind]
    with open(path, "rb") as raw:
        size = os.fstat(raw.fileno()).st_size
        if size > limit:
            raise _too_large(path, kind, size)
        text = _Capped(raw, limit, lambda: _too_large(path, kind, f"more than {limit}"))
        yield io.TextIOWrapper(text, encoding="utf-8", newline="")  # type: ignore[arg-type]


class _Capped:
    """A binary reader that raises after ``limit`` bytes (for :func:`open_limited`)."""

    def __init__(self, raw, limit: int, error):
        self.raw, self.left, self.error, self.closed = raw, limit, error, False

    def readable(self) -> bool:
        return True

    def writable(self) -> bool:
        return False

    def seekable(self) -> bool:
        return False

    def flush(self) -> None:
        pass

    def close(self) -> None:
        self.closed = True

    def read1(self, n: int = -1) -> bytes:
        return self.read(n)

    def readinto(self, buffer) -> int:
        data = self.read(len(buffer))
        buffer[: len(data)] = data
        return len(data)

    def read(self, n: int = -1) -> bytes:
        want = self.left + 1 if n is None or n < 0 else min(n, self.left + 1)
        data = self.raw.read(want)
        self.left -= len(data)
        if self.left < 0:
            raise self.error()
        return data


def read_limited(path: str | os.PathLike, kind: str) -> str:
    """The UTF-8 text of ``path``, at most ``FILE_LIMITS[kind]`` bytes (never reading more);
    :class:`UserError` if it is larger or not text."""
    path, limit = Path(path), FILE_LIMITS[kind]
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size > limit:
            raise _too_large(path, kind, size)
        data = f.read(limit + 1)  # never more, even if the file grew since
    if len(data) > limit:
        raise _too_large(path, kind, f"more than {limit}")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as error:
        raise UserError(f"{kind} '{path}' is not UTF-8 text ({error})") from None


def read_config(path: str | os.PathLike) -> TrainConfig:
    """The training config in ``path`` (a run's ``config.json``), read within its limit and checked
    for types (:func:`roverswarm.config.config_from_json`)."""
    from roverswarm.config import config_from_json

    return config_from_json(read_limited(path, "config.json"))


# ----------------------------------------------------------------------------- seeds


def check_seed(seed: object, flag: str = "--seed") -> int:
    """``seed`` if it is an integer in [0, 2^32) (what a PRNG key holds), else :class:`UserError`."""
    ok = isinstance(seed, numbers.Integral) and not isinstance(seed, bool) and 0 <= seed < 2**32  # NumPy's too
    require(ok, f"{flag} must be an integer in [0, 2^32), got {seed!r}")
    return int(seed)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- memory

MEMORY_SHARE = 0.8
"""Share of the memory this process may use that a run's estimate may take."""


def memory_limit() -> int:
    """Bytes this process may use: the machine's physical memory, lowered by a cgroup (container)
    limit or an address-space rlimit if either is smaller."""
    limits = [os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")]
    for name in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        with contextlib.suppress(OSError, ValueError):
            limits.append(int(Path(name).read_text().split()[0]))
    with contextlib.suppress(ImportError, ValueError, OSError):
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft != resource.RLIM_INFINITY:
            limits.append(soft)
    return min(limits)


@dataclass(frozen=True)
class Part:
    """One part of a memory estimate: what it holds, its bytes, and the options that set it."""

    what: str
    bytes: int
    options: str


def _tree_bytes(tree) -> int:
    import jax

    return sum(math.prod(x.shape) * x.dtype.itemsize for x in jax.tree.leaves(tree))


def network_bytes(config: TrainConfig, params: EnvParams) -> int:
    """Bytes of every seed's networks with their targets and optimiser states, from their shapes
    (``jax.eval_shape``: nothing is allocated)."""
    import jax

    from roverswarm.learners import learner_family

    family = learner_family(config.learner.algo)
    return _tree_bytes(jax.eval_shape(lambda: family.learners(family.configure(config, params), params)))


def _options(config: TrainConfig, *names: str) -> str:
    from roverswarm.config import fields_by_name

    values = fields_by_name(config)
    return ", ".join(f"--{n.replace('_', '-')} {values[n]}" for n in names)


def training_parts(config: TrainConfig, params: EnvParams) -> list[Part]:
    """The memory a training run of ``config`` needs, part by part (bytes of float32 arrays;
    activations counted forward and backward)."""
    from roverswarm.algos.learner import observation_width
    from roverswarm.env.mars import ACTION_SIZE
    from roverswarm.learners import learner_family

    obs = observation_width(config.learner, params)
    seeds, n = config.seeds, params.num_rovers
    steps, width = params.max_steps, sum(config.learner.hidden)
    networks = networks_part(config, params)
    parts = [replace(networks, bytes=3 * networks.bytes)]  # the state, its gradients and the updated copy
    family = learner_family(config.learner.algo)
    length = f", the mission's episode_length {steps}" if config.mission else ""  # what else sets the rollouts
    if not family.replay:  # on-policy: the iteration's rollouts and minibatches
        samples = steps * config.num_envs * n  # per seed and iteration
        value_in = obs * (n if config.learner.algo == "mappo" else 1)
        stored = seeds * samples * (obs + value_in + 2 * ACTION_SIZE + 8) * 4
        parts.append(Part("rollouts", stored, _options(config, "num_envs", "seeds") + length))
        batch = seeds * samples // config.ppo.minibatches * (obs + value_in + 4 * width) * 4 * 3
        options = _options(config, "minibatches", "num_envs", "hidden", "seeds") + length
        parts.append(Part("minibatches", batch, options))
    else:
        parts.append(
            Part("replay", family.replay_bytes(config, params)[0], _options(config, "buffer_size", "ensemble", "seeds"))
        )
        k = config.learner.ensemble
        rollout = seeds * steps * config.num_envs * n * (obs + k * width + ACTION_SIZE) * 4
        parts.append(Part("rollouts", rollout, _options(config, "num_envs", "ensemble", "seeds") + length))
        seen = 1 + config.learner.critic_neighbors if config.learner.critic_neighbors else n  # rovers a critic sees
        critic_in = seen * (obs + ACTION_SIZE)
        batch = seeds * n * k * config.buffer.batch_size * (critic_in + 4 * width) * 4 * 3
        parts.append(Part("minibatches", batch, _options(config, "batch_size", "ensemble", "hidden", "seeds")))
    return parts


def networks_part(config: TrainConfig, params: EnvParams) -> Part:
    """Every seed's networks of ``config`` as a run folder holds them (:func:`network_bytes` at
    ``params``, the run's own environment), naming the options that set them."""
    return Part("networks", network_bytes(config, params), _options(config, "hidden", "ensemble", "seeds"))


def batch_part(params: EnvParams, episodes: int, width: int, options: str) -> Part:
    """The memory of running ``episodes`` deterministic episodes of ``params`` at once: the paths,
    observations and activations (hidden layers ``width`` wide in total; 0 for random and the
    oracle) :func:`roverswarm.rollout.rollout` keeps. ``options`` name what sets it in the error."""
    from roverswarm.env.mars import observation_size

    n, obs, steps = params.num_rovers, observation_size(params), params.max_steps + 1
    per_episode = steps * (n * (obs + 4 * width + 4) + params.num_pois + 2) * 4
    return Part("evaluation batch", episodes * per_episode, options)


def check_memory(parts: list[Part], what: str) -> None:
    """Refuse (:class:`UserError`, one line) an estimate past :data:`MEMORY_SHARE` of
    :func:`memory_limit`, naming the largest part and the options that set it."""
    need, have = sum(p.bytes for p in parts), memory_limit()
    if need <= MEMORY_SHARE * have:
        return
    top = max(parts, key=lambda p: p.bytes)
    which = "it" if "," not in top.options else "one of them"
    raise UserError(
        f"{what} needs about {need / GiB:,.1f} GiB, {top.bytes / GiB:,.1f} GiB of it for the {top.what} "
        f"({top.options}), and this process may use {have / GiB:,.1f} GiB; lower {which}"
    )


def check_training_memory(config: TrainConfig, params: EnvParams) -> None:
    """:func:`check_memory` of a training run of ``config`` (before anything is allocated)."""
    check_memory(training_parts(config, params), "this run")
