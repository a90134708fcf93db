"""roverswarm: multi-agent reinforcement learning of rover swarms exploring a planetary surface."""

__version__ = "0.1.0"
