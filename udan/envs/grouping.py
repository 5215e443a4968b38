"""Who talks to whom: leaders, their groups, and the rounds that make bridges work.

Training and the edge runtime form groups with this same code: every ``interval`` steps the
agents whose leader probability exceeds ``threshold`` become leaders, and each leader groups
itself with its ``k - 1`` nearest agents (grid distance, ties by slot). An agent picked by
several leaders belongs to several groups and bridges them: paper eqs. (2)-(3) update its
encoding group after group, so groups are split into *rounds* of disjoint groups, processed in
order of the leaders' probability, highest first.
"""

from __future__ import annotations

import numpy as np

from udan import _kernels


def neighbour_tables(
    pos: np.ndarray, present: np.ndarray, count: int, out: np.ndarray | None = None
) -> np.ndarray:
    """Each agent's ``count`` nearest present agents in M arenas at once, itself first:
    ``pos`` (M, N, 2), ``present`` (M, N) -> (M, N, count) slots (into ``out`` if given), -1
    where fewer agents are present and in the rows of absent agents.

    Grid (Manhattan) distance, ties broken by slot, so training and the edge agree exactly.
    Each agent's neighbours are looked up ring by ring around it on a grid of the agents'
    cells (several agents may share a cell), so the work follows the agents found rather
    than the number of pairs (``udan._kernels.nearest``).
    """
    present = np.ascontiguousarray(present, bool)
    if out is None:
        out = np.empty((*present.shape, count), np.int64)
    _kernels.nearest(np.ascontiguousarray(pos, np.int64), present, out)
    return out


def neighbour_table(
    pos: np.ndarray, present: np.ndarray, count: int, out: np.ndarray | None = None
) -> np.ndarray:
    """:func:`neighbour_tables` of one arena: ``pos`` (N, 2), ``present`` (N,) -> (N, count),
    exactly ``count`` columns (a fixed-width input), -1 padded."""
    table = None if out is None else out[None]
    return neighbour_tables(pos[None], present[None], count, table)[0]


def nearest(pos: np.ndarray, present: np.ndarray, count: int) -> np.ndarray:
    """Each agent's ``count`` nearest present agents, itself first: (N, min(count, n)) slots
    for n agents present (:func:`neighbour_table` without the columns that would be -1 in
    every row)."""
    return neighbour_table(pos, present, min(count, int(np.count_nonzero(present))))


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
    probability (highest first, equal ones by slot), which is also the order bridges are
    updated in (``udan._kernels.leaders``: one pass and a merge sort). ``near``, a
    :func:`neighbour_table` of at least ``k`` columns already computed for the leader
    attention, saves a second search.
    """
    present = np.ascontiguousarray(present, bool)
    prob = np.asarray(leader_prob)
    leaders = np.empty(len(present), np.int64)
    # above the threshold in the probabilities' own type, as numpy compares an array to a number
    limit = float(prob.dtype.type(threshold))
    count = _kernels.leaders(np.ascontiguousarray(prob, np.float64), present, limit, leaders)
    size = min(k, int(np.count_nonzero(present)))
    if size < 2 or count == 0:
        return np.zeros((0, size), dtype=np.int64)
    if near is None or near.shape[1] < size:
        near = nearest(pos, present, k)
    return near[leaders[:count], :size]


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


def round_order(groups: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`group_rounds` as two arrays: the group indices (G,) listed round after round, and
    each round's number of groups (R,)."""
    groups = np.ascontiguousarray(groups, np.int64)
    order, sizes = np.empty(len(groups), np.int64), np.empty(len(groups), np.int64)
    rounds = _kernels.round_order(groups, order, sizes)
    return order, sizes[:rounds]


def group_rounds(groups: np.ndarray) -> list[np.ndarray]:
    """Split groups (in priority order) into rounds of disjoint groups; returns group indices.

    A group goes to the first round after the last round that holds any of its members, so an
    agent's groups are processed in priority order and each round can be one batched call.
    One pass over the groups (``udan._kernels.round_order``).
    """
    order, sizes = round_order(groups)
    return np.split(order, np.cumsum(sizes)[:-1]) if len(sizes) else []


def communication_matrix(groups: np.ndarray, n: int) -> np.ndarray:
    """The paper's C (N x N, bool): True where two agents share a group."""
    c = np.zeros((n, n), dtype=bool)
    for members in groups:
        c[np.ix_(members, members)] = True
    return c
