"""The paper's experience sample optimizer (section III.C, eq. 12-15): rank-based replay.

Shape legend: C capacity, N agents, B batch size per agent, F = 32 fan-out of the sampling
table, C' = C rounded up to a multiple of F^2, NB = 2**14 loss bins.

Every agent i keeps, for every stored transition, the latest TD loss ``(Q_i(s, a) - y)^2``
of its own critic (eq. 14-15) and samples transition j with probability

    P_i(j) = (1 - beta) * p_j^alpha / sum_k p_k^alpha + beta / M                (eq. 12)

where ``p_j`` is the rank of j's loss among the M stored transitions (eq. 13): 1 for the
smallest loss, M for the largest. The paper writes ``p^a / sum p^a + beta``, which sums to
``1 + M * beta``; this is its normalised reading: ``beta`` is the share of samples drawn
uniformly, ``alpha`` how sharply the rest favour large losses (alpha = 0 or beta = 1 is
uniform replay; with alpha = 1 the largest loss is drawn twice as often as the average one,
with alpha = 2 three times). Equal losses share their average rank, as in
``scipy.stats.rankdata(method="average")``. A new transition has not been evaluated yet, so
its loss is +inf: it enters at the top. After each update the losses of the sampled
transitions are written back (:meth:`Buffer.set_priorities`).

Ranks are refreshed lazily, every ``--refresh-every`` updates (:meth:`Buffer.refresh`),
because ranking 1e6 losses costs about 30 updates. A refresh bins every loss by its float32
bit pattern (a log scale with 64 bins per octave, so losses within ~1% of each other tie),
counts the bins, gives each transition the average rank of its bin, and stores the rank part
of ``P`` as a three-level table of running sums (slots in groups of F, groups in blocks of F,
then the blocks), so a draw is a binary search over the blocks and two reads of F
neighbouring values: a few cache lines instead of a binary search through C values.
Between refreshes:

* transitions added since the refresh are tied at the top (their loss is unknown), above
  every ranked one, which is exactly eq. 12 while the buffer is not full;
* losses written back since the refresh wait for the next one;
* once the buffer is full, a slot overwritten since the refresh keeps its old rank's share
  as well as its share of the top; :attr:`Sample.probabilities` is always the exact
  probability of the draw as made, so importance weights stay correct.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from flax import struct

from roverswarm.buffers.uniform import Buffer, BufferState, Sample, Transition, empty_state, gather, write

LOSS_BINS = 2**14
"""float32 bit pattern >> 17: sign-free exponent and top 6 mantissa bits, 64 bins per octave."""
_BIN_SHIFT = 17
FAN_OUT = 32


@struct.dataclass
class RankState:
    """Losses and the sampling table of the last refresh (per agent where [N, ...])."""

    loss: jax.Array  # [N, C] latest TD loss per slot; +inf until first sampled
    slot_sums: jax.Array  # [N, C'] running sums of the ranked share P_rank(j) within each group of F slots
    group_sums: jax.Array  # [N, C' / F] running sums of the groups' shares within each block of F groups
    block_cdf: jax.Array  # [N, C' / F^2] running sums of the blocks' shares
    ranked_size: jax.Array  # [] int32, transitions stored at the last refresh
    ranked_weight: jax.Array  # [N] sum of (rank / ranked_size)^alpha over them
    fresh: jax.Array  # [] int32, transitions added since the last refresh (<= C)
    fresh_start: jax.Array  # [] int32, ring position at the last refresh (the first fresh slot)


def loss_bins(loss: jax.Array) -> jax.Array:
    """Monotone log-scale bin in [0, LOSS_BINS) of each loss (>= 0; +inf in the top bins)."""
    return jax.lax.bitcast_convert_type(jnp.abs(loss).astype(jnp.float32), jnp.int32) >> _BIN_SHIFT


def average_ranks(loss: jax.Array, valid: jax.Array) -> jax.Array:
    """1-based ascending rank of each valid loss [C] (ties: their average rank); 0 where invalid."""
    bins = loss_bins(loss)
    counts = jnp.zeros(LOSS_BINS, jnp.float32).at[bins].add(valid.astype(jnp.float32))
    mid = jnp.cumsum(counts) - (counts - 1.0) / 2.0  # average rank of each bin's members
    return jnp.where(valid, mid[bins], 0.0)


def _padded(capacity: int) -> int:
    """C': the capacity rounded up to whole blocks of F^2 slots."""
    return -(-capacity // FAN_OUT**2) * FAN_OUT**2


def _refresh_agent(loss: jax.Array, size: jax.Array, capacity: int, alpha: float):
    """One agent's sampling table from its losses: (slot_sums, group_sums, block_cdf, total weight)."""
    ranks = average_ranks(loss, jnp.arange(capacity) < size)
    # eq. 12's numerator, scaled by the top rank so that the largest weight is 1 for any alpha
    weights = jnp.where(ranks > 0, (ranks / jnp.maximum(size, 1)) ** alpha, 0.0)
    total = weights.sum()
    share = jnp.pad(weights / jnp.maximum(total, 1e-30), (0, _padded(capacity) - capacity))
    slot_sums = jnp.cumsum(share.reshape(-1, FAN_OUT), axis=1)
    group_sums = jnp.cumsum(slot_sums[:, -1].reshape(-1, FAN_OUT), axis=1)
    return slot_sums.reshape(-1), group_sums.reshape(-1), jnp.cumsum(group_sums[:, -1]), total


def _descend(sums: jax.Array, row: jax.Array, target: jax.Array) -> tuple[jax.Array, jax.Array]:
    """In row ``row`` (of F running sums) of ``sums``: the first j with sum > target, and the
    target minus the sums before j (where the draw falls inside entry j)."""
    values = sums.reshape(-1, FAN_OUT)[row]  # [B, F]
    # never past the row's last entry with a share (running sums differ from the level
    # above in the last float32 bits, so the target can reach the row's total)
    j = jnp.minimum(jnp.sum(values <= target[:, None], axis=1), jnp.argmax(values, axis=1))
    before = jnp.where(j > 0, jnp.take_along_axis(values, jnp.maximum(j - 1, 0)[:, None], axis=1)[:, 0], 0.0)
    return j, target - before


def _fresh_share(extra: RankState, capacity: int, alpha: float) -> jax.Array:
    """[N] share of the ranked part that goes to the fresh transitions (tied at the top).

    Their weight is ``n * (top / M_r)^alpha`` beside the ranked ones' ``sum (rank / M_r)^alpha``,
    compared in logs so that no alpha overflows."""
    n = jnp.maximum(extra.fresh, 1).astype(jnp.float32)
    ranked = jnp.maximum(extra.ranked_size, 1).astype(jnp.float32)
    top = extra.ranked_size.astype(jnp.float32) + (n + 1.0) / 2.0
    log_ratio = jnp.log(jnp.maximum(extra.ranked_weight, 1e-30)) - jnp.log(n) - alpha * jnp.log(top / ranked)
    share = jax.nn.sigmoid(-log_ratio)
    return jnp.where(extra.fresh == 0, 0.0, jnp.where(extra.fresh >= capacity, 1.0, share))


@functools.lru_cache(maxsize=None)
def ranked_buffer(capacity: int, batch_size: int, num_agents: int, alpha: float, beta: float) -> Buffer:
    """The experience sample optimizer with amplification ``alpha`` and uniform share ``beta``.

    Cached like :func:`~roverswarm.buffers.uniform.uniform_buffer`, so jitted code that takes
    it as a static argument compiles once per setting."""
    padded = _padded(capacity)

    def init(example: Transition) -> BufferState:
        extra = RankState(
            loss=jnp.full((num_agents, capacity), jnp.inf),
            slot_sums=jnp.zeros((num_agents, padded)),
            group_sums=jnp.zeros((num_agents, padded // FAN_OUT)),
            block_cdf=jnp.zeros((num_agents, padded // FAN_OUT**2)),
            ranked_size=jnp.zeros((), jnp.int32),
            ranked_weight=jnp.zeros((num_agents,)),
            fresh=jnp.zeros((), jnp.int32),
            fresh_start=jnp.zeros((), jnp.int32),
        )
        return empty_state(capacity, example, extra)

    def add(state: BufferState, transitions: Transition) -> BufferState:
        state, indices = write(state, transitions)
        extra = state.extra
        extra = extra.replace(
            loss=extra.loss.at[:, indices].set(jnp.inf),
            fresh=jnp.minimum(extra.fresh + indices.shape[0], capacity),
        )
        return state.replace(extra=extra)

    def rerank(extra: RankState, size: jax.Array, position: jax.Array) -> RankState:
        slot_sums, group_sums, block_cdf, total = jax.vmap(_refresh_agent, in_axes=(0, None, None, None))(
            extra.loss, size, capacity, alpha
        )
        return extra.replace(
            slot_sums=slot_sums,
            group_sums=group_sums,
            block_cdf=block_cdf,
            ranked_size=size,
            ranked_weight=total,
            fresh=jnp.zeros((), jnp.int32),
            fresh_start=position,
        )

    def refresh(state: BufferState, due: jax.Array) -> BufferState:
        # only the rank state passes through the branch, so the replay data is never copied
        extra = jax.lax.cond(due, rerank, lambda e, *_: e, state.extra, state.size, state.position)
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

    def sample_agent(key, slot_sums, group_sums, block_cdf, fresh_share, size, fresh_count, fresh_start):
        # two random words per draw: the first picks the part of P (uniform share, fresh top,
        # ranked) and, rescaled, the ranked block; the second the slot: by its 32 bits for
        # the uniform and fresh parts (a float32 uniform has too few values to spread over
        # 1e6 slots evenly), as a fraction within the ranked block
        k_pick, k_slot = jax.random.split(key)
        pick = jax.random.uniform(k_pick, (batch_size,))
        bits = jax.random.bits(k_slot, (batch_size,), jnp.uint32)
        within = jax.lax.bitcast_convert_type((bits >> 9) | jnp.uint32(0x3F800000), jnp.float32) - 1.0
        top = beta + (1.0 - beta) * fresh_share  # [0, beta): uniform, [beta, top): fresh
        fresh = jnp.maximum(fresh_count, 1)
        uniform_index = (bits % jnp.maximum(size, 1).astype(jnp.uint32)).astype(jnp.int32)
        fresh_index = (fresh_start + (bits % fresh.astype(jnp.uint32)).astype(jnp.int32)) % capacity
        rescaled = jnp.clip((pick - top) / jnp.maximum(1.0 - top, 1e-30), 0.0, 1.0)
        ranked_index = jnp.minimum(ranked_draw(slot_sums, group_sums, block_cdf, rescaled, within), capacity - 1)
        index = jnp.where(pick < beta, uniform_index, jnp.where(pick < top, fresh_index, ranked_index))
        # the exact probability of this draw (a mixture of the three ways to reach a slot)
        is_fresh = ((index - fresh_start) % capacity) < fresh_count
        rank_part = (1.0 - fresh_share) * snapshot_probability(slot_sums, index) + is_fresh * fresh_share / fresh
        probability = beta / jnp.maximum(size, 1) + (1.0 - beta) * rank_part
        return index, probability

    def sample(state: BufferState, key: jax.Array) -> Sample:
        extra = state.extra
        shares = _fresh_share(extra, capacity, alpha)
        indices, probabilities = jax.vmap(sample_agent, in_axes=(0, 0, 0, 0, 0, None, None, None))(
            jax.random.split(key, num_agents), extra.slot_sums, extra.group_sums, extra.block_cdf, shares,
            state.size, extra.fresh, extra.fresh_start,
        )
        return Sample(batch=gather(state, indices), indices=indices, probabilities=probabilities)

    def set_priorities(state: BufferState, indices: jax.Array, losses: jax.Array) -> BufferState:
        loss = jax.vmap(lambda l, i, v: l.at[i].set(v))(state.extra.loss, indices, losses)
        return state.replace(extra=state.extra.replace(loss=loss))

    return Buffer(capacity, batch_size, num_agents, init, add, sample, set_priorities, refresh)
