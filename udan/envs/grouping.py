"""Who talks to whom: leaders, their groups, and the rounds that make bridges work (numpy only).

Training and the edge runtime form groups with this same code: every ``interval`` steps the
agents whose leader probability exceeds ``threshold`` become leaders, and each leader groups
itself with its ``k - 1`` nearest agents (grid distance, ties by slot). An agent picked by
several leaders belongs to several groups and bridges them: paper eqs. (2)-(3) update its
encoding group after group, so groups are split into *rounds* of disjoint groups, processed in
order of the leaders' probability, highest first.
"""

from __future__ import annotations

import numpy as np

#: Fleets up to this size compare all pairs (cheaper than growing rings on a small arena).
RING_SEARCH_FROM = 64


def nearest(pos: np.ndarray, present: np.ndarray, count: int) -> np.ndarray:
    """Each agent's ``count`` nearest present agents, itself first: (N, min(count, n)) slots.

    Grid (Manhattan) distance, ties broken by slot, so training and the edge agree exactly.
    Rows of absent agents are -1. Large fleets on distinct cells (the world rules guarantee it)
    are searched ring by ring on an occupancy grid, O(N x cells searched); otherwise all pairs.
    """
    slots = np.flatnonzero(present)
    size = min(count, slots.size)
    out = np.full((len(present), size), -1, dtype=np.int64)
    if size == 0:
        return out
    cells = pos[slots]
    shape = cells.max(0) + 1
    flat = cells[:, 0] * shape[1] + cells[:, 1]
    if slots.size <= RING_SEARCH_FROM or np.unique(flat).size < flat.size:
        return _nearest_all_pairs(pos[None], present[None], size)[0]
    out[slots] = _nearest_by_rings(cells, slots, size, shape)
    return out


def _nearest_all_pairs(pos: np.ndarray, present: np.ndarray, count: int) -> np.ndarray:
    """:func:`nearest` by sorting all pairs, for M arenas at once: (M, N, 2), (M, N) ->
    (M, N, count) slots, -1 where fewer agents are present."""
    m, n = present.shape
    absent = np.iinfo(np.int64).max
    dist = np.abs(pos[:, :, None, :] - pos[:, None, :, :]).sum(-1)
    key = np.where(present[:, None, :], dist * n + np.arange(n), absent)  # distance, then slot
    key[:, np.arange(n), np.arange(n)] = -1  # itself first
    order = np.argsort(key, axis=2, kind="stable")[:, :, :count]
    near = np.where(np.take_along_axis(key, order, axis=2) != absent, order, -1)
    near[~present] = -1
    out = np.full((m, n, count), -1, dtype=np.int64)
    out[:, :, : near.shape[2]] = near
    return out


def _nearest_by_rings(
    cells: np.ndarray, slots: np.ndarray, size: int, shape: np.ndarray
) -> np.ndarray:
    """Every cell within a Manhattan radius around every agent at once, keyed by (distance,
    slot) and sorted, so the result equals sorting all pairs by (distance, slot); agents that
    find fewer than ``size`` within the radius search again with a radius half as big again."""
    grid = np.full(tuple(shape), -1, dtype=np.int64)
    grid[cells[:, 0], cells[:, 1]] = slots
    found = np.full((len(slots), size), -1, dtype=np.int64)
    scale = int(slots.max()) + 1
    big = np.iinfo(np.int64).max  # sorts empty cells after every slot
    # a diamond that holds about twice the agents needed, at the fleet's mean density
    density = len(slots) / float(shape[0] * shape[1])
    radius = max(1, int(np.ceil(np.sqrt(size / density))))
    need = np.arange(len(slots))
    while need.size:
        padded = np.pad(grid, radius, constant_values=-1)  # off the grid: no agent
        d_row, d_col = _diamond(radius)
        width = padded.shape[1]
        origin = (cells[need, 0] + radius) * width + cells[need, 1] + radius
        hits = padded.ravel()[origin[:, None] + (d_row * width + d_col)[None, :]]
        dist = np.abs(d_row) + np.abs(d_col)
        keys = np.where(hits >= 0, dist * scale + hits, big)
        if keys.shape[1] > size:
            keys = np.partition(keys, size - 1, axis=1)[:, :size]
        keys.sort(axis=1)
        complete = (keys[:, -1] != big) | (radius >= shape.sum())
        done = need[complete]
        found[done] = np.where(keys[complete] != big, keys[complete] % scale, -1)
        need = need[~complete]
        radius += max(1, radius // 2)
    return found


def _diamond(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Row and column offsets of every cell within Manhattan ``radius`` of the origin."""
    d = np.arange(-radius, radius + 1)
    rows, cols = np.meshgrid(d, d, indexing="ij")
    keep = np.abs(rows) + np.abs(cols) <= radius
    return rows[keep], cols[keep]


def neighbour_table(pos: np.ndarray, present: np.ndarray, count: int) -> np.ndarray:
    """:func:`nearest` padded to exactly ``count`` columns with -1 (a fixed-width input)."""
    near = nearest(pos, present, count)
    out = np.full((len(present), count), -1, dtype=np.int64)
    out[:, : near.shape[1]] = near
    return out


def neighbour_tables(pos: np.ndarray, present: np.ndarray, count: int) -> np.ndarray:
    """:func:`neighbour_table` of M arenas at once: ``pos`` (M, N, 2), ``present`` (M, N) ->
    (M, N, count). Fleets up to ``RING_SEARCH_FROM`` sort the pairs of every arena in one call
    (training asks for hundreds of small arenas per update); larger ones go arena by arena."""
    m, n = present.shape
    if n <= RING_SEARCH_FROM:
        return _nearest_all_pairs(pos, present, count)
    out = np.full((m, n, count), -1, dtype=np.int64)
    for i in range(m):
        out[i] = neighbour_table(pos[i], present[i], count)
    return out


def form_groups(
    pos: np.ndarray,
    present: np.ndarray,
    leader_prob: np.ndarray,
    k: int,
    threshold: float,
    near: np.ndarray | None = None,
) -> np.ndarray:
    """Groups of one arena as a (G, min(k, n)) array of slots, leader first then by distance.

    ``pos`` (N, 2), ``present`` (N,), ``leader_prob`` (N,). Leaders are ordered by
    probability (highest first), which is also the order bridges are updated in. ``near``, a
    :func:`neighbour_table` of at least ``k`` columns already computed for the leader
    attention, saves a second pass over all pairs.
    """
    slots = np.flatnonzero(present)
    size = min(k, slots.size)
    leaders = slots[leader_prob[slots] > threshold]
    if size < 2 or leaders.size == 0:
        return np.zeros((0, size), dtype=np.int64)
    leaders = leaders[np.argsort(-leader_prob[leaders], kind="stable")]
    if near is None or near.shape[1] < size:
        near = nearest(pos, present, k)
    return near[leaders, :size]


def hypothetical_groups(
    pos: np.ndarray, present: np.ndarray, k: int, near: np.ndarray | None = None
) -> np.ndarray:
    """Every present agent as a leader with its k-1 nearest (the leader classifier's targets).

    ``near``, as in :func:`form_groups`, reuses a neighbour table computed for the attention.
    """
    slots = np.flatnonzero(present)
    size = min(k, slots.size)
    if size < 2:
        return np.zeros((0, size), dtype=np.int64)
    if near is None or near.shape[1] < size:
        near = nearest(pos, present, k)
    return near[slots, :size]


#: From this many groups, rounds are found with array operations instead of a loop over groups.
VECTOR_ROUNDS_FROM = 48


def group_rounds(groups: np.ndarray) -> list[np.ndarray]:
    """Split groups (in priority order) into rounds of disjoint groups; returns group indices.

    A group goes to the first round after the last round that holds any of its members, so an
    agent's groups are processed in priority order and each round can be one batched call.
    """
    if len(groups) >= VECTOR_ROUNDS_FROM:
        return _rounds_by_relaxation(groups)
    last_round: dict[int, int] = {}
    rounds: list[list[int]] = []
    for g, members in enumerate(groups.tolist()):
        r = max((last_round.get(m, -1) for m in members), default=-1) + 1
        if r == len(rounds):
            rounds.append([])
        rounds[r].append(g)
        for m in members:
            last_round[m] = r
    return [np.array(r, dtype=np.int64) for r in rounds]


def _rounds_by_relaxation(groups: np.ndarray) -> list[np.ndarray]:
    """:func:`group_rounds` for many groups: a group's round is one more than the round of the
    previous group of each of its members (the longest chain of shared members before it),
    found by relaxing all groups at once, one pass per round."""
    n_groups, size = groups.shape
    flat = groups.ravel()
    order = np.argsort(flat, kind="stable")  # each member's groups, in priority order
    prev = np.full(flat.size, -1, dtype=np.int64)
    same = flat[order[1:]] == flat[order[:-1]]
    prev[order[1:][same]] = order[:-1][same] // size  # the member's previous group
    prev = prev.reshape(n_groups, size)
    has_prev = prev >= 0
    rounds = np.zeros(n_groups, dtype=np.int64)
    while True:
        after = np.where(has_prev, rounds[prev] + 1, 0).max(axis=1)
        if (after == rounds).all():
            break
        rounds = after
    by_round = np.argsort(rounds, kind="stable")
    return np.split(by_round, np.cumsum(np.bincount(rounds))[:-1])


def communication_matrix(groups: np.ndarray, n: int) -> np.ndarray:
    """The paper's C (N x N, bool): True where two agents share a group."""
    c = np.zeros((n, n), dtype=bool)
    for members in groups:
        c[np.ix_(members, members)] = True
    return c
