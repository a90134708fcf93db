"""The paper's experience sample optimizer (section III.C, eq. 12-15): rank-based replay.

Shape legend: C capacity, N agents, K sub-policies per agent, G = N * K sampling groups,
B batch size per group, F = 32 fan-out of the sampling table, C' = C rounded up to a
multiple of F^2, NB = 2**14 loss bins.

Every agent i keeps, for every stored transition, the latest TD loss ``(Q_i(s, a) - y)^2``
of its own critic (eq. 14-15) and samples transition j with probability

    P_i(j) = (1 - beta) * p_j^alpha / sum_k p_k^alpha + beta / M                (eq. 12)

where ``p_j`` is the rank of j's loss among the M stored transitions (eq. 13): 1 for the
smallest loss, M for the largest. With policy ensembles, each sub-policy k of agent i
samples its own partition D_i^(k) (:mod:`roverswarm.buffers.partitions`) by this formula:
M and the ranks are those of the partition's transitions. The paper writes ``p^a / sum p^a + beta``, which sums to
``1 + M * beta``; this is its normalised reading: ``beta`` is the share of samples drawn
uniformly, ``alpha`` how sharply the rest favour large losses (alpha = 0 or beta = 1 is
uniform replay; with alpha = 1 the largest loss is drawn twice as often as the average one,
with alpha = 2 three times). Equal losses share their average rank, as in
``scipy.stats.rankdata(method="average")``. A new transition has not been evaluated yet, so
its loss is +inf: it enters at the top. After each update the losses of the sampled
transitions are written back (:meth:`Buffer.set_priorities`).

A second reading, ``reading="schaul"``, is the rank-based prioritised replay of Schaul et al.
(2016, sec. 3.3): priority ``1 / rank`` with rank 1 the *largest* loss, so

    P_i(j) = (1 - beta) * d_j^-alpha / sum_k d_k^-alpha + beta / M,    d_j = M + 1 - p_j

(Schaul: alpha about 0.7, no uniform share, importance weights with an annealed exponent,
:func:`~roverswarm.buffers.base.importance_weights`). Its head is far sharper: with alpha = 0.7
and M = 1e6 the largest loss is drawn about 4,800 times as often as the average transition
(the paper reading with alpha = 1: twice).
New transitions get the largest priority, as in Schaul's algorithm: tied at the top, each
has their average rank (n + 1) / 2 among the n of them, as a refresh ranks them (before
2026-12-02 each had weight 1, as rank 1: n new ones weighed n, so between refreshes most draws
went to them, 83% for the newest 1000 of 1e6 transitions at alpha 0.7).

Ranks are refreshed lazily, every ``--refresh-every`` updates (:meth:`Buffer.refresh`),
because ranking 1e6 losses costs several updates. A refresh bins every loss by its float32
bit pattern (a log scale with 64 bins per octave, so losses within ~1% of each other tie),
counts the bins, gives each transition the average rank of its bin, and stores the rank part
of ``P`` as a three-level table of running sums (slots in groups of F, groups in blocks of F,
then the blocks), so a draw is a binary search over the blocks and two reads of F
neighbouring values: a few cache lines instead of a binary search through C values.
Between refreshes:

* transitions added since the refresh are tied at the top (their loss is unknown), above
  every ranked one, which is exactly eq. 12 while the buffer is not full (with the
  ``schaul`` reading each has the weight of their average rank at the top, ((n + 1) / 2)^-alpha,
  beside the ranked ones' weights of the last refresh, which the next refresh lowers, ranking
  them below the n new ones: little for most, much at the head; at M = 1e6, alpha = 0.7 and
  n = 1000 the top 1000 ranked transitions draw 10.8% of all draws before and 2.9% after,
  the top one 120 times less, while the new ones' 5.8% becomes 11.4%);
* losses written back since the refresh wait for the next one;
* once the buffer is full, the slots overwritten since the refresh no longer hold the
  transitions that were ranked: a draw of the table that lands on one is redrawn among the
  group's fresh transitions (among all of the group's, if it has no fresh one), so their
  old share goes to the top too. :attr:`Draw.probabilities` is always the exact
  probability of the draw as made, so importance weights stay correct.
"""

from __future__ import annotations

import functools
from typing import Literal

import jax
import jax.numpy as jnp
from flax import struct

from roverswarm.buffers.base import Buffer, BufferState, Draw, Transition, empty_state, nth_stored, population, write

LOSS_BINS = 2**14
"""float32 bit pattern >> 17: sign-free exponent and top 6 mantissa bits, 64 bins per octave."""
_BIN_SHIFT = 17
FAN_OUT = 32

Reading = Literal["paper", "schaul"]
"""How a transition's loss rank becomes its sampling weight (module docstring): ``paper``,
``(rank / M)^alpha`` with rank 1 the smallest loss; ``schaul``, ``rank^-alpha`` with rank 1 the largest."""


@struct.dataclass
class RankState:
    """Losses and the sampling tables of the last refresh, per sampling group where [G, ...]."""

    loss: jax.Array  # [N, C] agent i's latest TD loss per slot; +inf until first sampled
    slot_sums: jax.Array  # [G, C'] running sums of the ranked share P_rank(j) within each row of F slots
    group_sums: jax.Array  # [G, C' / F] running sums of the rows' shares within each block of F rows
    block_cdf: jax.Array  # [G, C' / F^2] running sums of the blocks' shares
    ranked_size: jax.Array  # [] int32, transitions stored at the last refresh
    ranked_weight: jax.Array  # [G] sum of (rank / ranked)^alpha over the ranked transitions
    fresh: jax.Array  # [] int32, transitions added since the last refresh (<= C)
    fresh_start: jax.Array  # [] int32, ring position at the last refresh (the first fresh slot)
    group_ranked: jax.Array | None = None  # [G] int32, each partition's size at the last refresh (K > 1)
    group_head: jax.Array | None = None  # [G] int32, each partition's ring head at the last refresh (K > 1)


def loss_bins(loss: jax.Array) -> jax.Array:
    """Monotone log-scale bin in [0, LOSS_BINS) of each loss (>= 0; +inf in the top bins)."""
    return jax.lax.bitcast_convert_type(jnp.abs(loss).astype(jnp.float32), jnp.int32) >> _BIN_SHIFT


def average_ranks(loss: jax.Array, valid: jax.Array) -> jax.Array:
    """1-based ascending rank of each valid loss [G, C] within its row (ties: their average
    rank); 0 where invalid.

    The rows share one flat histogram (row g's bins offset by g * LOSS_BINS): XLA on CPU runs
    flat scatters and gathers several times faster than their batched (vmapped) forms."""
    rows = loss.shape[0]
    bins = loss_bins(loss) + jnp.arange(rows)[:, None] * LOSS_BINS
    counts = jnp.zeros(rows * LOSS_BINS, jnp.float32).at[bins.reshape(-1)].add(valid.reshape(-1).astype(jnp.float32))
    counts = counts.reshape(rows, LOSS_BINS)
    mid = jnp.cumsum(counts, axis=1) - (counts - 1.0) / 2.0  # average rank of each bin's members
    return jnp.where(valid, mid.reshape(-1)[bins], 0.0)


def _unit_float(bits: jax.Array) -> jax.Array:
    """Uniform floats in [0, 1) from the top 23 of 32 random bits, as ``jax.random.uniform``."""
    return jax.lax.bitcast_convert_type((bits >> 9) | jnp.uint32(0x3F800000), jnp.float32) - 1.0


def _padded(capacity: int) -> int:
    """C': the capacity rounded up to whole blocks of F^2 slots."""
    return -(-capacity // FAN_OUT**2) * FAN_OUT**2


def _running_sums(x: jax.Array) -> jax.Array:
    """Running sums along the last axis, added one entry at a time: non-decreasing wherever x
    is non-negative (a parallel scan's rounding need not be), and on CPU faster than
    ``jnp.cumsum``'s scan for rows of F."""
    sums = [x[..., 0]]
    for j in range(1, x.shape[-1]):
        sums.append(sums[-1] + x[..., j])
    return jnp.stack(sums, axis=-1)


def rank_weights(ranks: jax.Array, count: jax.Array, alpha: float, reading: Reading) -> jax.Array:
    """Sampling weight of each ascending average rank (0 = no transition) among ``count``:
    ``paper``, eq. 12's numerator scaled by the top rank, ``(rank / count)^alpha``; ``schaul``,
    ``(count + 1 - rank)^-alpha``. The largest possible weight is 1 in both, for any alpha."""
    if reading == "paper":
        weights = (ranks / jnp.maximum(count, 1)) ** alpha
    else:
        weights = jnp.maximum(count + 1.0 - ranks, 1.0) ** -alpha
    return jnp.where(ranks > 0, weights, 0.0)


def _tables(loss: jax.Array, valid: jax.Array, capacity: int, alpha: float, reading: Reading):
    """Every sampling group's table from the losses [G, C] of its ``valid`` slots:
    (slot_sums [G, C'], group_sums [G, C' / F], block_cdf [G, C' / F^2], total weight [G])."""
    groups = loss.shape[0]
    ranks = average_ranks(loss, valid)
    weights = rank_weights(ranks, valid.sum(axis=1, keepdims=True), alpha, reading)
    total = weights.sum(axis=1)
    share = jnp.pad(weights / jnp.maximum(total, 1e-30)[:, None], ((0, 0), (0, _padded(capacity) - capacity)))
    slot_sums = _running_sums(share.reshape(groups, -1, FAN_OUT))
    group_sums = _running_sums(slot_sums[:, :, -1].reshape(groups, -1, FAN_OUT)).reshape(groups, -1)
    return slot_sums.reshape(groups, -1), group_sums, _block_cdf(group_sums), total


def _block_cdf(group_sums: jax.Array) -> jax.Array:
    """[..., C' / F^2] running sums of the blocks' shares, from the rows' running sums
    within each block [..., C' / F] (each block's total is its last row's sum)."""
    return jnp.cumsum(group_sums.reshape(*group_sums.shape[:-1], -1, FAN_OUT)[..., -1], axis=-1)


def _descend(sums: jax.Array, row: jax.Array, target: jax.Array) -> tuple[jax.Array, jax.Array]:
    """In row ``row`` (of F running sums) of ``sums``: the first j with sum > target, and the
    target minus the sums before j (where the draw falls inside entry j)."""
    values = sums.reshape(-1, FAN_OUT)[row]  # [B, F]
    # below the row's total, so never past its last entry with a share (running sums differ
    # from the level above in the last float32 bits, so the target can reach the total)
    target = jnp.minimum(target, jnp.nextafter(values[:, -1], 0.0))
    # the sums are non-decreasing (:func:`_running_sums`), so the entries at most the target are the first j
    j = jnp.minimum(jnp.sum(values <= target[:, None], axis=1), FAN_OUT - 1)
    # a flat read of entry j - 1 (a reduction over the [B, F] rows costs several times more)
    before = jnp.where(j > 0, sums[row * FAN_OUT + jnp.maximum(j - 1, 0)], 0.0)
    return j, target - before


def _prefix(slot_sums: jax.Array, group_sums: jax.Array, block_cdf: jax.Array, end: jax.Array) -> jax.Array:
    """Sum of the table's shares of the slots before ``end`` (0 <= end <= C')."""
    block, row, slot = end // FAN_OUT**2, (end // FAN_OUT) % FAN_OUT, end % FAN_OUT
    blocks = jnp.where(block > 0, block_cdf[jnp.maximum(block - 1, 0)], 0.0)
    rows = jnp.where(row > 0, group_sums[jnp.maximum(block * FAN_OUT + row - 1, 0)], 0.0)
    slots = jnp.where(slot > 0, slot_sums[jnp.maximum((block * FAN_OUT + row) * FAN_OUT + slot - 1, 0)], 0.0)
    return blocks + rows + slots


def _region_share(slot_sums, group_sums, block_cdf, start: jax.Array, count: jax.Array, capacity: int) -> jax.Array:
    """Sum of the table's shares over the ``count`` ring slots from ``start`` (wrapping at C)."""
    prefix = functools.partial(_prefix, slot_sums, group_sums, block_cdf)
    end = start + count
    inside = prefix(jnp.minimum(end, capacity)) - prefix(start)
    wrapped = jnp.where(end > capacity, prefix(jnp.maximum(end - capacity, 0)), 0.0)
    return jnp.where(count >= capacity, 1.0, inside + wrapped)


def _fresh_share(
    fresh: jax.Array, live: jax.Array, ranked: jax.Array, ranked_weight: jax.Array, alpha: float, reading: Reading
) -> jax.Array:
    """[G] share of the ranked part that goes to the ``fresh`` transitions (tied at the top).

    Their weight is ``n * (top / M_r)^alpha`` (``paper``) or ``n * ((n + 1) / 2)^-alpha``
    (``schaul``: rank 1 the largest loss) beside the ``ranked`` ones' total: each has the
    average rank of the n tied at the top, as a refresh ranks them. Compared in logs so that no
    alpha overflows."""
    n = jnp.maximum(fresh, 1).astype(jnp.float32)
    top = ranked.astype(jnp.float32) + (n + 1.0) / 2.0
    if reading == "paper":
        log_each = alpha * jnp.log(top / jnp.maximum(ranked, 1))
    else:
        log_each = -alpha * jnp.log((n + 1.0) / 2.0)
    log_ratio = jnp.log(jnp.maximum(ranked_weight, 1e-30)) - jnp.log(n) - log_each
    share = jax.nn.sigmoid(-log_ratio)
    return jnp.where(fresh == 0, 0.0, jnp.where(fresh >= live, 1.0, share))


@functools.lru_cache(maxsize=None)
def ranked_buffer(
    capacity: int,
    batch_size: int,
    num_agents: int,
    alpha: float,
    beta: float,
    num_policies: int = 1,
    reading: Reading = "paper",
) -> Buffer:
    """The experience sample optimizer with amplification ``alpha`` and uniform share ``beta``,
    for ``num_policies`` sub-policies per agent, in the given ``reading`` of the rank.

    Cached like :func:`~roverswarm.buffers.uniform.uniform_buffer`, so jitted code that takes
    it as a static argument compiles once per setting."""
    padded = _padded(capacity)
    groups = num_agents * num_policies
    partitioned = num_policies > 1

    def init(example: Transition) -> BufferState:
        counts = lambda: jnp.zeros((groups,), jnp.int32) if partitioned else None  # noqa: E731
        extra = RankState(
            loss=jnp.full((num_agents, capacity), jnp.inf),
            slot_sums=jnp.zeros((groups, padded)),
            group_sums=jnp.zeros((groups, padded // FAN_OUT)),
            block_cdf=jnp.zeros((groups, padded // FAN_OUT**2)),
            ranked_size=jnp.zeros((), jnp.int32),
            ranked_weight=jnp.zeros((groups,)),
            fresh=jnp.zeros((), jnp.int32),
            fresh_start=jnp.zeros((), jnp.int32),
            group_ranked=counts(),
            group_head=counts(),
        )
        return empty_state(capacity, example, num_policies, extra)

    def add(state: BufferState, transitions: Transition) -> BufferState:
        state, indices = write(state, transitions)
        extra = state.extra
        extra = extra.replace(
            loss=extra.loss.at[:, indices].set(jnp.inf),
            fresh=jnp.minimum(extra.fresh + indices.shape[0], capacity),
        )
        return state.replace(extra=extra)

    def group_losses(extra: RankState, size: jax.Array, policy: jax.Array | None) -> tuple[jax.Array, jax.Array]:
        """[G, C] losses and valid slots of every sampling group (``policy`` [C, N] if K > 1)."""
        stored = jnp.arange(capacity) < size
        if not partitioned:
            return extra.loss, jnp.broadcast_to(stored, (groups, capacity))
        agent, sub_policy = jnp.divmod(jnp.arange(groups), num_policies)
        return extra.loss[agent], (policy.T[agent] == sub_policy[:, None]) & stored

    def rerank(extra: RankState, size: jax.Array, position: jax.Array, policy, parts) -> RankState:
        loss, valid = group_losses(extra, size, policy)
        slot_sums, group_sums, block_cdf, total = _tables(loss, valid, capacity, alpha, reading)
        return extra.replace(
            slot_sums=slot_sums,
            group_sums=group_sums,
            block_cdf=block_cdf,
            ranked_size=size,
            ranked_weight=total,
            fresh=jnp.zeros((), jnp.int32),
            fresh_start=position,
            group_ranked=parts.live if partitioned else None,
            group_head=parts.head if partitioned else None,
        )

    def refresh(state: BufferState, due: jax.Array) -> BufferState:
        # only the rank state and the sub-policies pass through the branch, so the replay
        # data is never copied
        keep = lambda extra, *_: extra  # noqa: E731
        extra = jax.lax.cond(
            due, rerank, keep, state.extra, state.size, state.position, state.data.policy, state.partitions
        )
        return state.replace(extra=extra)

    def ranked_draw(slot_sums, group_sums, block_cdf, first: jax.Array, second: jax.Array) -> jax.Array:
        """Slots drawn from the table: ``first`` picks the block, ``second`` the slot within it."""
        block = jnp.minimum(jnp.searchsorted(block_cdf, first * block_cdf[-1], side="right"), len(block_cdf) - 1)
        group_row = group_sums.reshape(-1, FAN_OUT)[block]
        group, rest = _descend(group_sums, block, second * group_row[:, -1])
        slot, _ = _descend(slot_sums, block * FAN_OUT + group, rest)
        return (block * FAN_OUT + group) * FAN_OUT + slot

    def snapshot_probability(slot_sums: jax.Array, index: jax.Array) -> jax.Array:
        previous = jnp.where(index % FAN_OUT == 0, 0.0, slot_sums[jnp.maximum(index - 1, 0)])
        return slot_sums[index] - previous

    def sample_group(state: BufferState, key, slot_sums, group_sums, block_cdf, fresh_share, live, fresh, ring, head):
        # three random words per draw: the first picks the part of P (uniform share, fresh
        # top, ranked) and, rescaled, the ranked block; the second the slot within the block;
        # the third an age in the partition for the uniform and fresh parts and redraws (by
        # its 32 bits: a float32 uniform has too few values to spread over 1e6 slots evenly)
        # (one call: every call of the counter-based generator is its own loop on CPU)
        pick_bits, slot_bits, age_bits = jax.random.bits(key, (3, batch_size), jnp.uint32)
        pick, within = _unit_float(pick_bits), _unit_float(slot_bits)
        stored = lambda count: nth_stored(
            state, (age_bits % jnp.maximum(count, 1).astype(jnp.uint32)).astype(jnp.int32), ring, head
        )  # noqa: E731
        extra = state.extra
        top = beta + (1.0 - beta) * fresh_share  # [0, beta): uniform, [beta, top): fresh
        rescaled = jnp.clip((pick - top) / jnp.maximum(1.0 - top, 1e-30), 0.0, 1.0)
        ranked_index = jnp.minimum(ranked_draw(slot_sums, group_sums, block_cdf, rescaled, within), capacity - 1)
        overwritten = lambda index: ((index - extra.fresh_start) % capacity) < extra.fresh  # noqa: E731
        uniform_index, fresh_index = stored(live), stored(fresh)
        # a table draw on a slot overwritten since the refresh is redrawn among the fresh ones
        redraw = jnp.where(fresh > 0, fresh_index, uniform_index)
        ranked_index = jnp.where(overwritten(ranked_index), redraw, ranked_index)
        index = jnp.where(pick < beta, uniform_index, jnp.where(pick < top, fresh_index, ranked_index))
        # the exact probability of this draw (a mixture of the ways to reach a slot)
        stale = _region_share(slot_sums, group_sums, block_cdf, extra.fresh_start, extra.fresh, capacity)
        is_fresh = overwritten(index)
        live_f, fresh_f = jnp.maximum(live, 1).astype(jnp.float32), jnp.maximum(fresh, 1).astype(jnp.float32)
        to_fresh = jnp.where(fresh > 0, fresh_share + (1.0 - fresh_share) * stale, 0.0)
        rank_part = (
            (1.0 - fresh_share) * jnp.where(is_fresh, 0.0, snapshot_probability(slot_sums, index))
            + is_fresh * to_fresh / fresh_f
            + jnp.where(fresh > 0, 0.0, (1.0 - fresh_share) * stale) / live_f
        )
        probability = beta / live_f + (1.0 - beta) * rank_part
        return index, probability

    def draw(state: BufferState, key: jax.Array) -> Draw:
        extra = state.extra
        live = population(state, groups)
        if partitioned:
            ranked, ring, head = extra.group_ranked, state.partitions.ring, state.partitions.head
            fresh = jnp.minimum(head - extra.group_head, live)
        else:
            ranked, ring, head = jnp.broadcast_to(extra.ranked_size, (groups,)), None, None
            fresh = jnp.broadcast_to(extra.fresh, (groups,))
        shares = _fresh_share(fresh, live, ranked, extra.ranked_weight, alpha, reading)
        indices, probabilities = jax.vmap(
            sample_group, in_axes=(None, 0, 0, 0, 0, 0, 0, 0, 0 if partitioned else None, 0 if partitioned else None)
        )(
            state,
            jax.random.split(key, groups),
            extra.slot_sums,
            extra.group_sums,
            extra.block_cdf,
            shares,
            live,
            fresh,
            ring,
            head,
        )
        return Draw(indices, probabilities, live)

    def set_priorities(state: BufferState, indices: jax.Array, losses: jax.Array) -> BufferState:
        """Write back the [G, B] losses: each group's go to its agent's row."""
        agent = jnp.arange(groups) // num_policies
        loss = state.extra.loss.at[agent[:, None], indices].set(losses)
        return state.replace(extra=state.extra.replace(loss=loss))

    def resized(state: BufferState) -> BufferState:
        # the blocks' running sums run on past the stored transitions (beyond them every block
        # holds the total), where an empty replay holds zeros; the rest is as placed
        return state.replace(extra=state.extra.replace(block_cdf=_block_cdf(state.extra.group_sums)))

    return Buffer(capacity, batch_size, num_agents, num_policies, init, add, draw, set_priorities, refresh, resized)
