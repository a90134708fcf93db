"""Replay buffers with one interface (:mod:`roverswarm.buffers.base`): uniform (reference MADDPG)
and ranked (the paper's experience sample optimizer)."""

from roverswarm.buffers.base import Buffer, BufferState, Draw, ReplayConfig, Sample, Transition
from roverswarm.buffers.ranked import ranked_buffer
from roverswarm.buffers.uniform import uniform_buffer


def make_buffer(config: ReplayConfig, num_agents: int, num_policies: int = 1) -> Buffer:
    """The replay ``config`` describes, for ``num_agents`` agents with ``num_policies``
    sub-policies each (one partition per sub-policy of every agent if > 1)."""
    if config.replay == "ranked":
        return ranked_buffer(
            config.buffer_size, config.batch_size, num_agents, config.alpha, config.beta, num_policies, config.reading
        )
    return uniform_buffer(config.buffer_size, config.batch_size, num_agents, num_policies)


__all__ = [
    "Buffer",
    "BufferState",
    "Draw",
    "ReplayConfig",
    "Sample",
    "Transition",
    "make_buffer",
    "ranked_buffer",
    "uniform_buffer",
]
