"""Replay buffers with one interface: uniform (reference MADDPG) and ranked (experience sample optimizer)."""

from roverswarm.buffers.ranked import ranked_buffer
from roverswarm.buffers.uniform import Buffer, BufferState, Draw, Sample, Transition, uniform_buffer

__all__ = ["Buffer", "BufferState", "Draw", "Sample", "Transition", "ranked_buffer", "uniform_buffer"]
