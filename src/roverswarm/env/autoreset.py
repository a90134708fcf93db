"""Draw a fresh episode only for the environments whose episode ended, also under ``jax.vmap``.

A gymnax-style auto-reset draws ``reset(key)`` and keeps it where the episode ended. Under
``jax.vmap`` a ``lax.cond`` on a batched predicate turns into a select that runs both branches
for every environment, so the reset would be drawn at every step of every environment and
thrown away 24 times in 25. :func:`where_done` is a ``jax.custom_batching.custom_vmap`` function
that sees the whole batch instead: it gathers the rows whose predicate holds (``jnp.nonzero``),
runs the reset on them in chunks of a fixed size inside a ``lax.while_loop`` (none, and no
search, at a step where no episode ends) and scatters the results back. Row i still gets exactly what
``fn`` gives for row i's arguments, so layouts and key schedule are those of a plain per-row
``fn``.

The chunk holds twice the rows expected to end per step when episodes are staggered
(``size / every``, ``every`` being the episode length): one chunk then serves a batch whose
episodes end at different steps, and a batch whose episodes end together takes ``every / 2``
chunks once per episode. Each pass of the loop has a fixed cost (a vmapped reset of 11 rows
cost 8.9 us a row at N = 5, of 82 rows 3.2 us), so a smaller second chunk size for the last rows
paid off only at N = 2 (staggered episodes 1.3x the cost of ``step_env`` instead of 1.5x) and
cost more from N = 5 on (1.6x instead of 1.3x), measured in one run. Under nested ``vmap`` the
outer axis batches the while loop, which then runs as many chunks as the busiest row needs.

The rows that did not end get placeholder values (zeros); the caller selects. Reverse-mode
differentiation through ``step`` with respect to the actions works, as the reset depends on no
action; with respect to params that the layout reads (``map_size``, radii, fixed positions) it
does not under ``vmap``: JAX cannot reverse-differentiate a while loop of dynamic length.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap


def where_done(done: jax.Array, fn: Callable[..., Any], every: int, *args: Any) -> Any:
    """``fn(*args)`` where ``done`` ([] bool) is true; where it is not, values of the same
    shapes that the caller must not use (it selects, e.g. ``jnp.where(done, fresh, old)``).

    Under ``jax.vmap`` ``fn`` runs only for the rows whose ``done`` is true (see the module
    docstring). ``fn`` must be a hashable module-level function of arrays returning arrays;
    ``every`` (static) is how many calls a row takes on average between two true ``done``.
    """
    return _sparse(fn, every)(done, *args)


def _zeros(shapes: Any, leading: tuple[int, ...] = ()) -> Any:
    return jax.tree.map(lambda s: jnp.zeros((*leading, *s.shape), s.dtype), shapes)


@functools.cache
def _sparse(fn: Callable[..., Any], every: int):
    """The ``custom_vmap`` version of ``fn`` behind :func:`where_done` (one per ``fn`` and ``every``)."""

    # jitted, one trace of ``fn`` serves both the zeros' shapes and the call (XLA inlines it)
    once = jax.jit(fn)

    @custom_vmap
    def sparse(done, *args):
        return jax.lax.cond(done, lambda: once(*args), lambda: _zeros(jax.eval_shape(once, *args)))

    @sparse.def_vmap
    def sparse_batched(size: int, in_batched: list, done, *args):
        done_batched, *args_batched = in_batched
        if not any(jax.tree.leaves(args_batched)):  # every row would compute the same thing
            out = jax.tree.map(lambda x: jnp.broadcast_to(x, (size, *x.shape)), once(*args))
        else:
            done = done if done_batched else jnp.broadcast_to(done, (size,))
            out = _fresh_rows(once, done, args, args_batched, min(size, 2 * math.ceil(size / every)))
        return out, jax.tree.map(lambda _: True, out)

    return sparse


def _fresh_rows(fn: Callable[..., Any], done: jax.Array, args: list, args_batched: list, chunk: int) -> Any:
    """``fn`` of each row where ``done`` [size] is true, ``chunk`` rows at a time; zeros elsewhere.
    ``args_batched`` says, leaf by leaf, which leaves of ``args`` have the leading row axis."""
    size = done.shape[0]
    axes = [jax.tree.map(lambda b: 0 if b else None, batched) for batched in args_batched]

    def take(rows):
        return [jax.tree.map(lambda x, b: x[rows] if b else x, a, batched) for a, batched in zip(args, args_batched)]

    count = jnp.sum(done)

    def run_chunks(out):
        order = jnp.nonzero(done, size=math.ceil(size / chunk) * chunk, fill_value=size)[0]

        def run_chunk(carry):
            start, out = carry
            rows = jax.lax.dynamic_slice(order, (start,), (chunk,))  # `size` past the last done row: dropped
            fresh = jax.vmap(fn, in_axes=axes)(*take(jnp.minimum(rows, size - 1)))
            return start + chunk, jax.tree.map(lambda o, f: o.at[rows].set(f, mode="drop"), out, fresh)

        return jax.lax.while_loop(lambda carry: carry[0] < count, run_chunk, (jnp.int32(0), out))[1]

    out = _zeros(jax.eval_shape(fn, *take(0)), (size,))
    # no row search at a step where no episode ends: 2.8x faster at E = 1
    return jax.lax.cond(count > 0, run_chunks, lambda out: out, out)
