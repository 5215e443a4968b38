"""Who talks to whom: leaders, their groups, and the rounds that make bridges work (numpy only).

Training and the edge runtime form groups with this same code: every ``interval`` steps the
agents whose leader probability exceeds ``threshold`` become leaders, and each leader groups
itself with its ``k - 1`` nearest agents (grid distance, ties by slot). An agent picked by
several leaders belongs to several groups and bridges them: paper eqs. (2)-(3) update its
encoding group after group, so groups are split into *rounds* of disjoint groups, processed in
order of the leaders' probability, highest first.
"""

from __future__ import annotations

import functools

import numpy as np

#: Fleets up to this size compare all pairs (cheaper than growing rings on a small arena).
RING_SEARCH_FROM = 64

_ABSENT = np.iinfo(np.int64).max  # the pair key of an absent agent: sorts last


def nearest(pos: np.ndarray, present: np.ndarray, count: int) -> np.ndarray:
    """Each agent's ``count`` nearest present agents, itself first: (N, min(count, n)) slots.

    Grid (Manhattan) distance, ties broken by slot, so training and the edge agree exactly.
    Rows of absent agents are -1. Large fleets on distinct cells (the world rules guarantee it)
    are searched ring by ring on an occupancy grid, O(agents found); otherwise all pairs.
    """
    slots = np.flatnonzero(present)
    size = min(count, slots.size)
    found = None
    if size and slots.size > RING_SEARCH_FROM:
        found = _nearest_by_rings(pos[slots], slots, size)
    if found is None:
        return _nearest_all_pairs(pos[None], present[None], size)[0]
    out = np.full((len(present), size), -1, dtype=np.int64)
    out[slots] = found
    return out


def _nearest_all_pairs(pos: np.ndarray, present: np.ndarray, count: int) -> np.ndarray:
    """:func:`nearest` by sorting all pairs, for M arenas at once: (M, N, 2), (M, N) ->
    (M, N, count) slots, -1 where fewer agents are present.

    A pair's key is ``distance * N + slot`` (itself: ``slot - N``, first), so sorting the keys
    orders by distance then slot, and ``key % N`` gives the slot back; an absent agent's row
    and column are all ``absent``, which sorts last (with every agent present there is nothing
    to mask)."""
    m, n = present.shape
    everyone = present.all()
    key = np.abs(pos[:, :, None, :] - pos[:, None, :, :]).sum(-1) * n + _slot_keys(n)
    if not everyone:
        key = np.where(present[:, None, :] & present[:, :, None], key, _ABSENT)
    key.sort(axis=2)
    out = np.full((m, n, count), -1, dtype=np.int64)
    near = key[:, :, :count]
    out[:, :, : near.shape[2]] = near % n if everyone else np.where(near != _ABSENT, near % n, -1)
    return out


@functools.lru_cache(maxsize=64)
def _slot_keys(n: int) -> np.ndarray:
    """(N, N): each column's slot, less N on the diagonal (an agent comes first in its row)."""
    return np.arange(n) - n * np.eye(n, dtype=np.int64)


def _nearest_by_rings(cells: np.ndarray, slots: np.ndarray, size: int) -> np.ndarray | None:
    """For agents on distinct ``cells``: bands of rings (distances 1-2, 3-4, 5-6, 7-9, ...)
    around every agent that still lacks neighbours, all at once, on an occupancy grid. The
    agents met in a band are nearer than any beyond it, so each joins in (distance, slot)
    order; an agent leaves the search once it has ``size``, so the work follows the agents
    found rather than the arena's size. None when two agents share a cell."""
    shape = cells.max(0) + 1
    if np.bincount(cells[:, 0] * shape[1] + cells[:, 1]).max() > 1:
        return None
    scale = int(slots.max()) + 1
    found = np.full((len(slots), size), -1, dtype=np.int64)
    found[:, 0] = slots  # itself, the only agent at distance 0
    have = np.ones(len(slots), dtype=np.int64)
    need = np.flatnonzero(have < size)
    near = far = margin = 0
    while need.size:
        near, far = far, far + max(2, far // 2)
        if far > margin:  # a border of empty cells as wide as the band: no bounds checks
            margin = 2 * far
            grid = np.full(shape + 2 * margin, -1, dtype=np.int64)
            width = grid.shape[1]
            origin = (cells[:, 0] + margin) * width + cells[:, 1] + margin
            grid.ravel()[origin] = slots
        d_row, d_col, dist = _band(near, far)
        hits = grid.ravel()[origin[need, None] + (d_row * width + d_col)].ravel()
        flat = np.flatnonzero(hits >= 0)  # 2-D nonzero is ~5x slower
        row, col = np.divmod(flat, dist.size)
        key = np.sort((row * (far + 1) + dist[col]) * scale + hits[flat])
        row = key // ((far + 1) * scale)
        counts = np.bincount(row, minlength=need.size)
        room = size - have[need]
        at = (need * size + have[need] - (np.cumsum(counts) - counts))[row] + np.arange(key.size)
        ok = at < (need * size + size)[row]  # within the row's room
        found.ravel()[at[ok]] = key[ok] % scale
        have[need] += np.minimum(counts, room)
        need = need[counts < room]
    return found


@functools.lru_cache(maxsize=64)
def _band(near: int, far: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row and column offsets, and distances, of the cells at Manhattan distance ``near`` < d
    <= ``far`` (each ring of 4 * d cells walked around the origin)."""
    dist = np.repeat(np.arange(near + 1, far + 1), 4 * np.arange(near + 1, far + 1))
    step = np.concatenate([np.arange(4 * d) for d in range(near + 1, far + 1)])
    side, along = step // dist, step % dist  # which quarter of the ring, how far along it
    d_row = np.choose(side, [along, dist - along, -along, along - dist])
    d_col = np.choose(side, [dist - along, -along, along - dist, along])
    return d_row, d_col, dist


def neighbour_table(pos: np.ndarray, present: np.ndarray, count: int) -> np.ndarray:
    """:func:`nearest` padded to exactly ``count`` columns with -1 (a fixed-width input)."""
    if len(present) <= RING_SEARCH_FROM:  # all pairs, padded as they are sorted
        return _nearest_all_pairs(pos[None], present[None], count)[0]
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


def one_group_a_round(groups: np.ndarray) -> bool:
    """Whether groups (G, s) come from fewer than 2s agents: any two groups then share one, so
    each group is a round of its own (:func:`group_rounds` without the search)."""
    n_groups, size = groups.shape
    return n_groups > 0 and 2 * size > int(groups.max()) + 1


def group_rounds(groups: np.ndarray) -> list[np.ndarray]:
    """Split groups (in priority order) into rounds of disjoint groups; returns group indices.

    A group goes to the first round after the last round that holds any of its members, so an
    agent's groups are processed in priority order and each round can be one batched call.
    """
    n_groups = len(groups)
    if one_group_a_round(groups):
        return list(np.arange(n_groups)[:, None])
    if n_groups >= VECTOR_ROUNDS_FROM:
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
    found by relaxing all groups at once, one pass per round.

    Each member's groups in priority order come from one sort of ``member * E + entry`` keys
    (E entries; unique, so a plain sort orders them as a stable argsort would, at a fraction
    of its cost); a group with no previous group for a member reads the extra round -1."""
    n_groups, size = groups.shape
    entries = groups.size
    key = np.sort(groups.ravel() * entries + np.arange(entries))
    entry = key % entries
    same = key[1:] // entries == key[:-1] // entries
    prev = np.full(entries, n_groups, dtype=np.int64)
    prev[entry[1:][same]] = entry[:-1][same] // size  # the member's previous group
    prev = np.ascontiguousarray(prev.reshape(n_groups, size).T)  # (size, groups): rows reduce
    rounds = np.zeros(n_groups + 1, dtype=np.int64)
    rounds[-1] = -1
    while True:
        after = rounds[prev].max(axis=0) + 1
        if (after == rounds[:-1]).all():
            break
        rounds[:-1] = after
    rounds = rounds[:-1]
    by_round = np.argsort(rounds, kind="stable")
    return np.split(by_round, np.cumsum(np.bincount(rounds))[:-1])


def communication_matrix(groups: np.ndarray, n: int) -> np.ndarray:
    """The paper's C (N x N, bool): True where two agents share a group."""
    c = np.zeros((n, n), dtype=bool)
    for members in groups:
        c[np.ix_(members, members)] = True
    return c
