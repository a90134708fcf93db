"""Drawing the environment: rovers with their trails, POIs (filled once observed) and traps.

One :class:`FrameRenderer` (a reused off-screen matplotlib figure) turns positions into an
RGB array; :func:`save_animation` writes frames as GIF or MP4. Episodes of a policy are
drawn by :mod:`roverswarm.animation` (above the environment: it runs policies).
"""

from __future__ import annotations

import tempfile
import warnings
from pathlib import Path

import imageio.v3 as imageio
import numpy as np

from roverswarm.env.mars import EnvParams, observe_radii, trap_radii
from roverswarm.errors import UserError, require, unwritable

ANIMATION_SUFFIXES = (".gif", ".mp4")
_ROVER_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#d62728", "#e377c2", "#17becf", "#bcbd22")


class FrameRenderer:
    """Draws one frame at a time on an off-screen figure of ``pixels`` x ``pixels``."""

    def __init__(self, params: EnvParams, pixels: int = 480):
        # matplotlib here, not at the top: half a second that every command but a render skips
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.params = params
        self.figure = Figure(figsize=(pixels / 80, pixels / 80), dpi=80)
        self.canvas = FigureCanvasAgg(self.figure)
        self.ax = self.figure.add_axes((0.02, 0.02, 0.96, 0.9))

    def frame(
        self,
        trail: np.ndarray,
        poi_pos: np.ndarray,
        trap_pos: np.ndarray,
        observed: np.ndarray,
        title: str = "",
        exists: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> np.ndarray:
        """RGB uint8 ``[H, W, 3]`` of the rovers at ``trail[-1]`` with their paths ``trail``
        ``[t + 1, N, 2]``, POIs ``[P, 2]`` (filled where ``observed`` [P]) and traps ``[T, 2]``;
        with ``exists`` (rovers [N], POIs [P], traps [T] bool: a padded layout), only those that exist."""
        from matplotlib.patches import Circle

        p, ax = self.params, self.ax
        if exists is not None:
            rovers, pois, traps = exists
            trail, poi_pos, observed, trap_pos = trail[:, rovers], poi_pos[pois], observed[pois], trap_pos[traps]
            trap_radius, observe_radius = np.asarray(trap_radii(p))[traps], np.asarray(observe_radii(p))[pois]
        else:
            trap_radius, observe_radius = np.asarray(trap_radii(p)), np.asarray(observe_radii(p))
        ax.clear()
        size = float(p.map_size)
        ax.set_xlim(-size * 1.1, size * 1.1)
        ax.set_ylim(-size * 1.1, size * 1.1)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_facecolor("#f3e2cf")  # Martian regolith
        ax.plot([-size, size, size, -size, -size], [-size, -size, size, size, -size], color="#b08060", lw=1)
        for (x, y), r in zip(trap_pos, trap_radius):
            ax.add_patch(Circle((x, y), r, color="#5a3a22", alpha=0.85))
        for (x, y), seen, radius in zip(poi_pos, observed, observe_radius):
            ax.add_patch(Circle((x, y), float(radius), fill=False, ls="--", color="#2e7d32", lw=0.8))
            ax.add_patch(Circle((x, y), float(p.poi_radius), color="#2e7d32", fill=bool(seen), lw=1.5))
        for i in range(trail.shape[1]):
            color = _ROVER_COLORS[i % len(_ROVER_COLORS)]
            ax.plot(trail[:, i, 0], trail[:, i, 1], color=color, lw=1.2, alpha=0.7)
            ax.add_patch(Circle(tuple(trail[-1, i]), float(p.rover_radius), color=color, alpha=0.8))
        ax.set_title(title, fontsize=10)
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()


def check_animation_path(path: Path) -> None:
    """Raise :class:`UserError` unless ``path`` ends in .gif or .mp4 and can be written: neither
    it nor its last frame's .png beside it a folder, and its folder (or the nearest one of its
    folders that exists: the others are made when writing) one that takes a new file. Checked
    before an episode is drawn."""
    path = Path(path)
    if path.suffix.lower() not in ANIMATION_SUFFIXES:
        raise UserError(f"--out must end in {' or '.join(ANIMATION_SUFFIXES)}, got '{path.name}'")
    require(not path.is_dir(), f"--out '{path}' is a folder; give a file ending in {' or '.join(ANIMATION_SUFFIXES)}")
    still = path.with_suffix(".png")  # the last frame, written beside it
    require(not still.is_dir(), f"--out '{path}': its last frame's '{still}' is a folder; choose another --out")
    folder = next(p for p in path.absolute().parents if p.exists())
    require(folder.is_dir(), f"--out '{path}': '{folder}' is a file, not a folder; choose another --out")
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=f".{path.name}."):
            pass
    except OSError as error:
        raise UserError(
            f"--out '{path}': folder '{folder}' cannot be written ({unwritable(error)}); choose another --out"
        ) from error


def encode_animation(frames: list[np.ndarray], suffix: str, fps: int = 8) -> bytes:
    """The bytes of ``frames`` as a ``suffix`` (.gif or .mp4) file, encoded in memory: imageio's
    writer never opens the output, so a path that cannot be written cannot leave it half closed
    (a writer whose file failed retries it when collected, and prints a traceback)."""
    if suffix == ".gif":
        return imageio.imwrite("<bytes>", frames, extension=suffix, duration=1000 / fps, loop=0)
    with warnings.catch_warnings():
        # imageio-ffmpeg starts ffmpeg with subprocess: a fork immediately followed by exec, the
        # child running no Python and taking no lock of JAX's threads, so the deadlock JAX's
        # fork warning foresees cannot happen
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        return imageio.imwrite("<bytes>", frames, extension=suffix, fps=fps, macro_block_size=1)


def save_animation(frames: list[np.ndarray], path: Path, fps: int = 8) -> Path:
    """Write ``frames`` to ``path`` (.gif or .mp4) and the last frame to ``path`` with .png,
    each atomically (encoded in memory, then written beside it and renamed).

    Returns the PNG's path.
    """
    from roverswarm.storage import atomic_write  # the trainer's modules, loaded only when writing

    path = Path(path)
    check_animation_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    png = path.with_suffix(".png")
    files = {
        path: encode_animation(frames, path.suffix.lower(), fps),
        png: imageio.imwrite("<bytes>", frames[-1], extension=".png"),
    }
    for target, content in files.items():
        atomic_write(target, lambda f, c=content: f.write(c), binary=True)
    return png
