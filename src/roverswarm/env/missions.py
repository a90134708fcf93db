"""Mission files: the points of interest and traps scientists picked, as a fixed layout.

A mission file is YAML or JSON (see ``examples/mission.yaml``)::

    name: jezero-delta            # optional
    map_size: 1.0                 # half-width: the map is [-map_size, map_size]^2 (default 1)
    episode_length: 25            # steps (default 25)
    stop_when_complete: true      # end the episode once every POI is observed (default true)
    rovers:                       # either fixed starts ...
      start: [[-0.8, -0.8], [0.0, -0.8], [0.8, -0.8]]
    # rovers: {count: 3, release_zone: {low: [-1, -1], high: [1, -0.6]}}   # ... or a zone
    pois:
      - {name: olivine-outcrop, position: [-0.5, 0.6], radius: 0.1}   # radius: observation radius (default 0.1)
    traps:
      - {position: [0.0, 0.1], radius: 0.12}                          # radius default 0.1

Every mistake is one :class:`~roverswarm.errors.UserError` that names the entry: a missing
or unknown field, a POI, trap or start outside the map, a non-positive radius, a start that
overlaps a trap or another rover, a release zone mostly covered by craters. The environment
itself is unchanged: a mission is :class:`~roverswarm.env.mars.EnvParams` with
``fixed_pois``, ``fixed_traps`` and ``fixed_starts`` or ``start_zone`` set.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from roverswarm.env.layouts import LAYOUT_CANDIDATES
from roverswarm.env.mars import EnvParams, count_text
from roverswarm.env.validation import validate_params
from roverswarm.errors import UserError, require
from roverswarm.parsing import load_text

MAX_BYTES = 1_000_000
"""Largest mission file read (a mission of hundreds of POIs is a few tens of kB)."""
MAX_ENTRIES = 1000
"""Most POIs, traps or rovers in one mission."""
_TOP_FIELDS = {"name", "map_size", "episode_length", "stop_when_complete", "rovers", "pois", "traps"}
_DEFAULT_RADIUS = {"pois": 0.1, "traps": 0.1}


@dataclass(frozen=True)
class Mission:
    """A validated mission: its name, the environment with its layout, and the POIs' names."""

    name: str
    params: EnvParams
    poi_names: tuple[str, ...]

    def training_params(self) -> EnvParams:
        """The layout to train on: POIs and traps fixed, rover starts drawn anywhere in the
        map clear of the traps (so the policy learns to reach the POIs from anywhere), and
        fixed-length episodes as in the paper."""
        return self.params.replace(fixed_starts=None, start_zone=None, terminate_on_complete=False)

    def counts(self) -> str:
        return count_text(self.params)


def _fields(entry: Any, where: str, required: set[str], optional: set[str]) -> dict[str, Any]:
    require(
        isinstance(entry, dict), f"{where}: expected a mapping with fields {sorted(required | optional)}, got {entry!r}"
    )
    for name in sorted(required - entry.keys()):
        raise UserError(f"{where}: missing field '{name}'")
    for name in sorted(entry.keys() - required - optional, key=str):
        raise UserError(f"{where}: unknown field '{name}'; allowed: {', '.join(sorted(required | optional))}")
    return entry


def _point(value: Any, where: str, size: float) -> tuple[float, float]:
    ok = isinstance(value, (list, tuple)) and len(value) == 2 and all(_number(v) is not None for v in value)
    require(ok, f"{where}: expected a position [x, y] of two numbers, got {value!r}")
    x, y = float(value[0]), float(value[1])
    require(abs(x) <= size and abs(y) <= size, f"{where}: ({x:g}, {y:g}) is outside the map [-{size:g}, {size:g}]^2")
    return x, y


def _number(value: Any) -> float | None:
    """``value`` as a finite float, or None if it is not a finite number."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if np.isfinite(number) else None


_FLOAT32_RANGE = (float(np.finfo(np.float32).tiny), float(np.finfo(np.float32).max))


MAX_MAP_SIZE = 1e4
"""The largest ``map_size`` (and radius): squared distances across it stay finite in float32
(past about 1.8e19 they overflow and the oracle's matching fails), and float32 still resolves
positions there to about 1e-3, well under a rover's radius."""


def _positive(value: Any, where: str, most: float = _FLOAT32_RANGE[1]) -> float:
    """A positive number that float32 (the environment's arrays) holds, neither 0 nor inf there,
    and at most ``most``."""
    number = _number(value)
    require(
        number is not None and _FLOAT32_RANGE[0] <= number <= most,
        f"{where}: must be a positive number from {_FLOAT32_RANGE[0]:.1e} to {most:.1e}, got {value!r}",
    )
    return number


def _name(value: Any, where: str) -> str:
    require(isinstance(value, str) and value.strip() != "", f"{where}: must be a non-empty string, got {value!r}")
    return value


def _entries(data: dict, key: str, size: float) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Names, positions [K, 2] and radii [K] of the ``pois`` or ``traps`` list."""
    entries = data.get(key, [])
    require(isinstance(entries, list), f"{key}: expected a list, got {entries!r}")
    require(len(entries) <= MAX_ENTRIES, f"{key}: at most {MAX_ENTRIES} entries, got {len(entries)}")
    names, positions, radii, index = [], [], [], {}
    for i, entry in enumerate(entries):
        label = f"{key}[{i}]"
        _fields(entry, label, {"position"}, {"name", "radius"})
        name = _name(entry["name"], f"{label} name") if "name" in entry else f"{key[:-1]}-{i}"
        if name in index:
            raise UserError(f"{label}: the name '{name}' is already used by {key}[{index[name]}]")
        label += f" '{name}'" if "name" in entry else ""
        index[name] = i
        names.append(name)
        positions.append(_point(entry["position"], f"{label} position", size))
        radii.append(_positive(entry.get("radius", _DEFAULT_RADIUS[key]), f"{label} radius", MAX_MAP_SIZE))
    return names, np.array(positions, np.float32).reshape(-1, 2), np.array(radii, np.float32)


def _rovers(data: dict, size: float) -> tuple[int, np.ndarray | None, np.ndarray | None]:
    """Rover count, fixed starts [N, 2] (or None) and release zone [2, 2] (or None)."""
    rovers = _fields(data["rovers"], "rovers", set(), {"start", "count", "release_zone"})
    require(
        ("start" in rovers) != ("release_zone" in rovers),
        "rovers: give either 'start' (a list of positions) or 'release_zone' (with 'count')",
    )
    if "start" in rovers:
        starts = rovers["start"]
        require(
            isinstance(starts, list) and len(starts) > 0,
            f"rovers.start: expected a non-empty list of positions, got {starts!r}",
        )
        require(len(starts) <= MAX_ENTRIES, f"rovers.start: at most {MAX_ENTRIES} positions, got {len(starts)}")
        count = rovers.get("count", len(starts))
        require(type(count) is int, f"rovers.count: must be an integer (the number of starts), got {count!r}")
        require(count == len(starts), f"rovers.count ({count}) differs from the {len(starts)} start positions")
        points = [_point(p, f"rovers.start[{i}]", size) for i, p in enumerate(starts)]
        return len(points), np.array(points, np.float32), None
    count = rovers.get("count")
    require(
        isinstance(count, int) and not isinstance(count, bool) and 1 <= count <= MAX_ENTRIES,
        f"rovers.count: must be an integer in [1, {MAX_ENTRIES}] with a release_zone, got {count!r}",
    )
    zone = _fields(rovers["release_zone"], "rovers.release_zone", {"low", "high"}, set())
    low, high = (_point(zone[k], f"rovers.release_zone.{k}", size) for k in ("low", "high"))
    require(
        low[0] < high[0] and low[1] < high[1], f"rovers.release_zone: low {low} must be below and left of high {high}"
    )
    require(
        (high[0] - low[0]) * (high[1] - low[1]) >= _room(count),
        f"rovers.release_zone: {count} rovers of radius {EnvParams().rover_radius:g} need an area of at least "
        f"{_room(count):g} to start apart, got {(high[0] - low[0]) * (high[1] - low[1]):g}",
    )
    return count, None, np.array([low, high], np.float32)


def _room(count: int) -> float:
    """The area a release zone needs for ``count`` rovers to start apart: twice their squares."""
    return 2 * count * (2 * EnvParams().rover_radius) ** 2


ZONE_GRID = 64
"""Points per side of the grid on which a release zone's part clear of the traps is measured."""
CLEAR_SHARE = 1 - 0.001 ** (1 / LAYOUT_CANDIDATES)
"""The least share of a release zone clear of the traps (0.35): each drawn rover takes the first
of :data:`~roverswarm.env.layouts.LAYOUT_CANDIDATES` uniform candidates clear of them (the
first if none is), so at most 1 rover in 1000 starts in a crater."""


def _check_zone_clear(zone: np.ndarray, count: int, traps: np.ndarray, trap_radii: np.ndarray, rover_radius: float):
    """Refuse a release zone whose part where a rover's centre is clear of every trap is less
    than :data:`CLEAR_SHARE` of it, or smaller than the room its rovers need (:func:`_room`);
    measured on a grid of :data:`ZONE_GRID` x :data:`ZONE_GRID` points, one array operation per trap."""
    if not len(traps):
        return
    (x0, y0), (x1, y1) = zone.astype(np.float64)
    t = (np.arange(ZONE_GRID) + 0.5) / ZONE_GRID
    xs, ys = np.meshgrid(x0 + t * (x1 - x0), y0 + t * (y1 - y0))
    points = np.stack([xs.ravel(), ys.ravel()], axis=1)
    clear = np.ones(len(points), bool)
    for trap, reach in zip(traps.astype(np.float64), trap_radii.astype(np.float64) + rover_radius):
        clear &= np.sum(np.square(points - trap), axis=1) >= reach**2
    share, area = float(clear.mean()), (x1 - x0) * (y1 - y0)
    require(
        share >= CLEAR_SHARE and share * area >= _room(count),
        f"rovers.release_zone: {share:.0%} of it (an area of {share * area:.3g}) is clear of the traps for a "
        f"rover's centre; {count} rovers need at least {CLEAR_SHARE:.0%} of it clear and an area of "
        f"{_room(count):g}: enlarge the zone or move it off the craters",
    )


def _check_clear(starts: np.ndarray, traps: np.ndarray, trap_radii: np.ndarray, rover_radius: float) -> None:
    """Refuse a start inside a trap or overlapping an earlier start. Linear in the starts: traps
    are compared in one array operation per start, and starts only with the earlier ones in
    their own and the neighbouring cells of a grid of cells as wide as a rover."""
    side = 2 * rover_radius
    cells: dict[tuple[int, int], list[int]] = {}
    for i, start in enumerate(starts):
        if len(traps):
            gaps = np.linalg.norm(traps - start, axis=1) - trap_radii.astype(np.float64) - rover_radius
            j = int(np.argmax(gaps < 0))
            require(
                gaps[j] >= 0,
                f"rovers.start[{i}] overlaps traps[{j}]: a rover (radius {rover_radius:g}) there "
                "would start in the crater",
            )
        cx, cy = int(np.floor(start[0] / side)), int(np.floor(start[1] / side))
        near = [k for dx in (-1, 0, 1) for dy in (-1, 0, 1) for k in cells.get((cx + dx, cy + dy), ())]
        for k in sorted(near):
            gap = float(np.linalg.norm(start - starts[k])) - side
            require(gap >= 0, f"rovers.start[{i}] overlaps rovers.start[{k}]: starts must be at least {side:g} apart")
        cells.setdefault((cx, cy), []).append(i)


def _check_observable(
    names: list[str],
    pois: np.ndarray,
    observe: np.ndarray,
    traps: np.ndarray,
    trap_radii: np.ndarray,
    rover_radius: float,
) -> None:
    """Refuse a POI that no rover can observe without touching a trap: every point within its
    observation radius is closer to the trap's centre than trap radius + rover radius."""
    if not len(traps):
        return
    for i, (poi, reach) in enumerate(zip(pois, observe)):  # one array operation per POI over the traps
        clears = trap_radii.astype(np.float64) + rover_radius - float(reach)  # the POI must be farther than this
        blocked = np.linalg.norm(traps - poi, axis=1) <= clears
        if blocked.any():
            j = int(np.argmax(blocked))
            clear = float(clears[j])
            raise UserError(
                f"pois[{i}] '{names[i]}' cannot be observed without touching traps[{j}]: a rover "
                f"(radius {rover_radius:g}) "
                f"within {float(reach):g} of it would be in the crater; move it more than {clear:g} "
                "from the trap's centre "
                "or give it a larger radius",
            )


def parse_mission(data: Any, name: str = "mission") -> Mission:
    """A :class:`Mission` from the parsed content of a mission file (raises :class:`UserError`)."""
    _fields(data, "mission file", {"rovers", "pois"}, _TOP_FIELDS - {"rovers", "pois"})
    size = _positive(data.get("map_size", 1.0), "map_size", MAX_MAP_SIZE)
    steps = data.get("episode_length", 25)
    require(
        isinstance(steps, int) and not isinstance(steps, bool) and 1 <= steps < 2**31,
        f"episode_length: must be an integer from 1 to 2^31 - 1 (steps), got {steps!r}",
    )
    stop = data.get("stop_when_complete", True)
    require(isinstance(stop, bool), f"stop_when_complete: must be true or false, got {stop!r}")
    poi_names, pois, observe = _entries(data, "pois", size)
    require(len(pois) > 0, "pois: a mission needs at least one POI")
    _, traps, trap_radius = _entries(data, "traps", size)
    count, starts, zone = _rovers(data, size)
    defaults = EnvParams()
    _check_observable(poi_names, pois, observe, traps, trap_radius, defaults.rover_radius)
    if starts is not None:
        _check_clear(starts, traps, trap_radius, defaults.rover_radius)
    else:
        _check_zone_clear(zone, count, traps, trap_radius, defaults.rover_radius)
    params = EnvParams(
        num_rovers=count,
        num_pois=len(pois),
        num_traps=len(traps),
        max_steps=steps,
        terminate_on_complete=stop,
        map_size=size,
        trap_radius=trap_radius if len(traps) else defaults.trap_radius,
        observe_radius=observe,
        fixed_pois=pois,
        fixed_traps=traps,
        fixed_starts=starts,
        start_zone=zone,
    )
    name = _name(data["name"], "name") if "name" in data else name
    return Mission(name=name, params=validate_params(params), poi_names=tuple(poi_names))


def read_mission_text(path: str | Path) -> str:
    """The text of mission file ``path`` (at most :data:`MAX_BYTES`), checked to exist."""
    path = Path(path)
    require(path.exists(), f"mission file '{path}' does not exist")
    require(path.is_file(), f"mission file '{path}' is not a file")
    size = path.stat().st_size
    require(size <= MAX_BYTES, f"mission file '{path}' has {size} bytes; at most {MAX_BYTES} are read")
    with open(path, "rb") as f:
        data = f.read(MAX_BYTES + 1)  # never more, even if the file grew since
    require(
        len(data) <= MAX_BYTES, f"mission file '{path}' has more than {MAX_BYTES} bytes; at most {MAX_BYTES} are read"
    )
    try:
        # as read_text: universal newlines; a byte-order mark (some Windows editors write one) dropped
        return data.decode("utf-8-sig").replace("\r\n", "\n").replace("\r", "\n")
    except UnicodeDecodeError as error:
        raise UserError(f"mission file '{path}' is not valid UTF-8: {error}") from None


def parse_mission_text(text: str, path: str | Path) -> Mission:
    """The mission in ``text``, the content of mission file ``path`` (its suffix says JSON or
    YAML, its stem is the default name), read by :func:`~roverswarm.parsing.load_text`: a key
    given twice is refused, and YAML aliases before anything is built, so a small file cannot
    expand into a huge document."""
    path = Path(path)
    kind = "JSON" if path.suffix.lower() == ".json" else "YAML"
    require(len(text) <= MAX_BYTES, f"mission file '{path}' has {len(text)} characters; at most {MAX_BYTES} are read")
    data = load_text(text, kind, f"mission file '{path}'", aliases=False)
    return parse_mission(data, name=path.stem)


def load_mission(path: str | Path) -> Mission:
    """Read and validate the mission file ``path`` (.yaml, .yml or .json)."""
    return parse_mission_text(read_mission_text(path), path)
