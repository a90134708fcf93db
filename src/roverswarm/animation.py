"""Animations of a policy's episodes: ``roverswarm render`` and the mission command's GIF/MP4.

:func:`episode_frames` draws one episode of a rollout with :class:`~roverswarm.env.render.FrameRenderer`;
:func:`render_episode` is the ``roverswarm render`` command as a function.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np

from roverswarm.env.mars import EnvParams
from roverswarm.env.render import FrameRenderer, check_animation_path, save_animation
from roverswarm.limits import check_seed
from roverswarm.policies import Policy
from roverswarm.rollout import Rollout, rollout


@dataclass(frozen=True)
class RenderConfig:
    """Draw one episode of a policy to a GIF or MP4, plus a PNG of the last frame."""

    scenario: str | None = None
    """Scenario preset (see `roverswarm scenarios`); default: a trained run's own environment,
    else paper-3."""
    policy: str = "oracle"
    """`oracle`, `random`, or a run folder of `roverswarm train` (any learner; deterministic)."""
    out: Path = Path("episode.gif")
    """Output animation, .gif or .mp4; the last frame is also written beside it as .png."""
    seed: int = 0
    """Random seed of the episode layout and of the random policy."""
    policy_seed: int = 0
    """Which of a trained run's seeds drives the rovers."""
    shield: bool = False
    """Drive the policy behind the safety layer (see `roverswarm evaluate --help`)."""


@dataclass(frozen=True)
class EpisodeFrames:
    """The frames of one episode and its total reward."""

    frames: list[np.ndarray]
    episode_reward: float


def episode_frames(data: Rollout, params: EnvParams, episode: int = 0, label: str = "") -> EpisodeFrames:
    """Frames of episode ``episode`` of a rollout, one per step
    (the start included), titled with the step and the reward so far."""
    renderer = FrameRenderer(params)
    rewards = data.rewards[episode].sum(axis=-1)  # [T]
    frames = []
    for t in range(data.rover_pos.shape[1]):
        title = f"{label}  step {t}/{params.max_steps}  reward {rewards[:t].sum():.1f}".strip()
        frames.append(
            renderer.frame(
                data.rover_pos[episode, : t + 1],
                data.poi_pos[episode],
                data.trap_pos[episode],
                data.observed[episode, t],
                title,
                (data.rover_exists[episode], data.poi_exists[episode], data.trap_exists[episode]),
            )
        )
    return EpisodeFrames(frames, float(rewards.sum()))


def render_episode(params: EnvParams, policy: Policy, out: Path, seed: int = 0, label: str = "") -> Path:
    """Run one episode of ``policy`` and write it to ``out`` (GIF/MP4) plus a PNG of the last
    frame. Returns the PNG path."""
    check_animation_path(Path(out))
    check_seed(seed)
    episode = rollout(policy, jax.random.PRNGKey(seed), params, num_episodes=1)
    return save_animation(episode_frames(episode, params, 0, label).frames, Path(out))
