"""Shared test setup: XLA flags for fast compilation, the compilation cache, compiled programs released
when they crowd the memory mappings, small shared configurations, a signal fixture, the CLI into a
closed pipe."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import warnings

import pytest

FAST_COMPILE_FLAGS = ("--xla_backend_optimization_level=1", "--xla_cpu_use_fusion_emitters=false")
"""XLA flags of the tests: the suite is mostly XLA compilation. At optimisation level 1 (of
0-3; 3 is XLA's default) it took a quarter less CPU time from a cold cache, and training ran
no slower (a learning test, 3000 episodes: 64 s against 81 s; level 0 took 123 s). XLA's
older CPU emitters instead of its fusion emitters took another 31% less CPU time, compiling
without a cache, in three compile-heavy modules (300 s -> 207 s, jaxlib 0.10.2; see
docs/performance.md). The CLI processes the tests start inherit them."""

CHECKED = "ROVERSWARM_TEST_XLA_FLAGS"
"""Environment variable holding the flags once decided: the xdist workers inherit it from the
controller and check nothing again."""


def _known_to_xla(flags: str) -> bool:
    """Whether this jaxlib accepts ``flags`` (XLA aborts a process on a flag it does not know,
    and a later jaxlib may drop the emitters' flag)."""
    probe = "import jax.numpy as jnp; jnp.zeros(1).block_until_ready()"
    env = {**os.environ, "XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"}
    try:
        return subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, timeout=120).returncode == 0
    except subprocess.TimeoutExpired:
        return False


def _test_xla_flags(flags: str) -> str:
    """``flags`` with those of :data:`FAST_COMPILE_FLAGS` it does not set and the jaxlib knows;
    a warning names any left out."""
    given = {token.split("=")[0] for token in flags.split()}
    missing = [flag for flag in FAST_COMPILE_FLAGS if flag.split("=")[0] not in given]
    if not missing or _known_to_xla(" ".join([flags, *missing])):
        return " ".join([flags, *missing]).strip()
    known = [flag for flag in missing if _known_to_xla(f"{flags} {flag}")]
    left_out = sorted(set(missing) - set(known))
    warnings.warn(f"XLA_FLAGS without {', '.join(left_out)}: this jaxlib does not accept it (tests compile slower)")
    return " ".join([flags, *known]).strip()


# before JAX starts its backend
if CHECKED not in os.environ:
    os.environ[CHECKED] = _test_xla_flags(os.environ.get("XLA_FLAGS", ""))
os.environ["XLA_FLAGS"] = os.environ[CHECKED]

from roverswarm.jaxcache import enable_compilation_cache, release_compiled_programs  # noqa: E402

enable_compilation_cache()


HEAVIEST_FIRST = (
    "test_reproduce.py",
    "test_train.py",
    "test_maddpg_update.py",
    "test_anysize.py",
    "test_ensembles.py",
    "test_sweep.py",
)
"""Test modules by their CPU time from an empty cache (most first; the rest keep their order).
Each module runs whole on one of the two xdist workers (``--dist loadfile``), handed out in
this order as workers free up (``--no-loadscope-reorder`` keeps it): started last, the
slowest module left one worker idle for minutes at the end."""


FORKING_FIRST = ("test_runs.py",)
"""Modules that fork the test process many times (``os.fork``), handed out before the heaviest:
a fork copies the worker's page tables, and a worker grows to gigabytes over the heavy modules
(3.6 GB resident at most in a cold run; 4.8 GB once programs were kept across modules). Last,
after them, ``test_runs.py``'s 240 forks took 31 s; on a fresh worker 4 s."""


def pytest_collection_modifyitems(items):
    """The forking modules first, then the heaviest (a stable sort: each module's own order is kept)."""
    rank = {name: i for i, name in enumerate(FORKING_FIRST + HEAVIEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """After each module the compiled programs are released if they crowd the memory mappings:
    kept for the whole session they exceeded Linux's 65,530 and crashed XLA (see
    release_compiled_programs). Released after every module, the next module traced and
    lowered again what it shared with the earlier ones (the tiny configurations, the random and
    oracle rollouts): a warm suite took 802 s of pytest, 729 s with them kept (CPU 24.1 -> 21.2
    minutes, the same commit, idle, one run each)."""
    yield
    release_compiled_programs(only_if_crowded=True)


@pytest.fixture(scope="session")
def paper3():
    from roverswarm.env import get_scenario

    return get_scenario("paper-3")


@pytest.fixture(scope="session")
def tiny_config():
    """A small, fast training configuration shared by the trainer tests (one compilation)."""
    from roverswarm.algos.learner import AlgoConfig
    from roverswarm.buffers.base import ReplayConfig
    from roverswarm.config import TrainConfig

    return TrainConfig(
        scenario="paper-2",
        learner=AlgoConfig(hidden=(32, 32)),
        episodes=400,
        seeds=2,
        num_envs=4,
        buffer=ReplayConfig(batch_size=64, buffer_size=4000),
        warmup=500,
        log_every=100,
        checkpoint_every=1,
    )


@pytest.fixture(scope="session")
def tiny_ppo_config():
    """A small, fast MAPPO configuration (the mappo preset, shrunk) shared by the PPO tests."""
    import dataclasses

    from roverswarm.config import with_options
    from roverswarm.presets import MAPPO

    return dataclasses.replace(
        with_options(MAPPO, {"hidden": (16,), "epochs": 2, "minibatches": 2}),
        scenario="paper-2",
        episodes=400,
        seeds=2,
        num_envs=4,
        log_every=100,
        checkpoint_every=1,
    )


@pytest.fixture(scope="session")
def tiny_anysize():
    """The anysize preset with attention over every entity, shrunk: sizes 2 to 4, small
    networks, few episodes."""
    import dataclasses

    from configs import SMALL_ENTITY  # tests/configs.py

    from roverswarm.config import with_options
    from roverswarm.presets import ANYSIZE

    return dataclasses.replace(
        with_options(ANYSIZE, {**SMALL_ENTITY, "hidden": (16,), "epochs": 2, "minibatches": 2}),
        scenario="paper-2..4",
        size_curriculum=0,  # every size from the start (the preset's curriculum starts at 2 rovers)
        episodes=200,
        seeds=2,
        num_envs=4,
        log_every=100,
        checkpoint_every=1,
    )


@pytest.fixture
def signal_at_chunk(monkeypatch):
    """``arm(signum, chunk, times)`` makes the next training send ``signum`` to this process
    ``times`` times just before its chunk number ``chunk`` (as Ctrl-C or a scheduler would);
    it returns a function that restores the trainer (every learner family's chunk)."""
    import dataclasses

    from roverswarm.learners import FAMILIES

    real = dict(FAMILIES)

    def arm(signum: int = signal.SIGINT, chunk: int = 2, times: int = 1):
        calls = []

        def signalled(run_chunk):
            def run(*args):
                calls.append(1)
                if len(calls) == chunk:
                    for _ in range(times):
                        os.kill(os.getpid(), signum)
                return run_chunk(*args)

            return run

        for algo, family in real.items():
            monkeypatch.setitem(FAMILIES, algo, dataclasses.replace(family, run_chunk=signalled(family.run_chunk)))
        return lambda: FAMILIES.update(real)

    return arm


@pytest.fixture
def cli_into_closed_pipe():
    """``run(*argv)``: ``roverswarm ARGV | head -0`` in a child process, its stdout a pipe whose
    reader is gone before the first line (a shell would report SIGPIPE); returns the finished
    process, stderr as text."""

    def run(*argv: str) -> subprocess.CompletedProcess:
        read, write = os.pipe()
        os.close(read)
        with os.fdopen(write, "wb") as stdout:
            command = [sys.executable, "-m", "roverswarm.cli", *argv]
            return subprocess.run(command, stdout=stdout, stderr=subprocess.PIPE, text=True)

    return run
