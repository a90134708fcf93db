"""Checking an :class:`~roverswarm.env.mars.EnvParams` a user built: every field a number the
program can represent, counts and radii in range, fixed layouts of the right shapes."""

from __future__ import annotations

import dataclasses

import numpy as np

from roverswarm.env.mars import EnvParams
from roverswarm.errors import require

_FLOAT32_MAX = float(np.finfo(np.float32).max)


def validate_params(params: EnvParams) -> EnvParams:
    """Check user-settable values; raise :class:`UserError` naming the bad field. Returns params."""
    for f in dataclasses.fields(params):  # numbers the program can represent, whatever the field
        value = getattr(params, f.name)
        if isinstance(value, bool) or value is None:
            continue
        if not f.metadata.get("pytree_node", True):  # static sizes: Python ints, used as int32 counts
            require(abs(value) < 2**31, f"{f.name} must be below 2^31, got {value}")
            continue
        x = np.asarray(value, dtype=float)
        require(
            bool(np.all(np.abs(x) <= _FLOAT32_MAX)),
            f"{f.name} must be a finite number representable as float32 (|x| <= {_FLOAT32_MAX:.3g}), got {value}",
        )
    require(params.num_rovers >= 1, f"num_rovers must be >= 1, got {params.num_rovers}")
    # at least one POI: a swarm with nothing to observe has no task (and the views' matching no rows)
    require(params.num_pois >= 1, f"num_pois must be >= 1, got {params.num_pois}")
    require(params.num_traps >= 0, f"num_traps must be >= 0, got {params.num_traps}")
    require(params.max_steps >= 1, f"max_steps must be >= 1, got {params.max_steps}")
    for name in ("map_size", "rover_radius", "poi_radius", "dt", "mass"):
        value = float(getattr(params, name))
        require(value > 0, f"{name} must be positive, got {value}")
    for name, count, what in (("trap_radius", params.num_traps, "trap"), ("observe_radius", params.num_pois, "POI")):
        radius = np.asarray(getattr(params, name), dtype=float)
        require(
            radius.ndim == 0 or radius.shape == (count,),
            f"{name} must be a number or one value per {what} ({count}), got shape {radius.shape}",
        )
        require(bool(np.all(radius > 0)), f"{name} must be positive, got {radius}")
    for name, rows in (
        ("fixed_pois", params.num_pois),
        ("fixed_traps", params.num_traps),
        ("fixed_starts", params.num_rovers),
        ("start_zone", 2),
    ):
        value = getattr(params, name)
        require(
            value is None or np.shape(value) == (rows, 2),
            f"{name} must be None or an array of shape ({rows}, 2), got shape {np.shape(value)}",
        )
    require(0 <= params.damping < 1, f"damping must be in [0, 1), got {params.damping}")
    for name, size in (
        ("active_rovers", params.num_rovers),
        ("active_pois", params.num_pois),
        ("active_traps", params.num_traps),
    ):
        value = getattr(params, name)
        low = 1 if name == "active_rovers" else 0
        require(
            value is None or bool(np.all((np.asarray(value) >= low) & (np.asarray(value) <= size))),
            f"{name} must be in [{low}, {size}] (the layout's maximum), got {value}",
        )
    require(
        params.fail_rate is None
        or bool(np.all((np.asarray(params.fail_rate) >= 0) & (np.asarray(params.fail_rate) <= 1))),
        f"fail_rate must be in [0, 1] (a probability per episode), got {params.fail_rate}",
    )
    if params.fail_rate is not None and bool(np.any(np.asarray(params.fail_rate) > 0)):
        rovers = params.num_rovers if params.active_rovers is None else np.min(params.active_rovers)
        require(
            rovers >= 2,
            f"fail_rate above 0 needs at least 2 rovers in every episode (a failure would lose the only one), "
            f"got {rovers}",
        )
    require(
        isinstance(params.fail_count, int) and params.fail_count >= 1,
        f"fail_count must be an integer >= 1 (rovers failing at most per failure episode), got {params.fail_count}",
    )
    return params
