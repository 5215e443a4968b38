"""World rules: simultaneous moves, conflicts, walls (the shared 'what a move does')."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from udan.envs.rules import (
    ACTION_DELTAS,
    DOWN,
    LEFT,
    RIGHT,
    UP,
    WAIT,
    resolve_moves,
)


def step(positions, actions, passable=None, size=5):
    pos = np.array([positions], dtype=np.int64)
    act = np.array([actions], dtype=np.int64)
    grid = np.ones((1, size, size), bool) if passable is None else passable[None]
    present = np.ones(act.shape, bool)
    return resolve_moves(pos, act, grid, present)[0].tolist()


def test_free_moves_apply_deltas():
    assert step([[2, 2], [0, 0]], [UP, RIGHT]) == [[1, 2], [0, 1]]


def test_edges_and_obstacles_block():
    grid = np.ones((5, 5), bool)
    grid[2, 3] = False
    assert step([[0, 0], [2, 2], [4, 4]], [UP, RIGHT, DOWN], grid) == [[0, 0], [2, 2], [4, 4]]


def test_a_move_off_a_side_does_not_wrap_to_the_next_row():
    # cells are numbered flat: (2, -1) would be (1, 4) and (1, 5) would be (2, 0)
    assert step([[2, 0], [1, 4]], [LEFT, RIGHT]) == [[2, 0], [1, 4]]


def test_two_agents_claiming_one_cell_both_wait():
    assert step([[2, 1], [2, 3]], [RIGHT, LEFT]) == [[2, 1], [2, 3]]


def test_swap_is_refused():
    assert step([[2, 1], [2, 2]], [RIGHT, LEFT]) == [[2, 1], [2, 2]]


def test_following_is_allowed_and_a_chain_behind_a_blocked_agent_stops():
    assert step([[2, 0], [2, 1], [2, 2]], [RIGHT, RIGHT, RIGHT]) == [[2, 1], [2, 2], [2, 3]]
    # the leader hits the edge, so everyone behind it waits too
    assert step([[2, 2], [2, 3], [2, 4]], [RIGHT, RIGHT, RIGHT]) == [[2, 2], [2, 3], [2, 4]]


def test_moving_into_a_waiting_agent_is_a_wait():
    assert step([[1, 1], [1, 2]], [RIGHT, WAIT]) == [[1, 1], [1, 2]]


def test_rotation_of_four_moves():
    # a 2x2 block rotating clockwise: every cell is vacated as it is entered
    got = step([[0, 0], [0, 1], [1, 1], [1, 0]], [RIGHT, DOWN, LEFT, UP])
    assert got == [[0, 1], [1, 1], [1, 0], [0, 0]]


def test_absent_agents_neither_move_nor_block():
    pos = np.array([[[2, 1], [2, 2]]])
    out = resolve_moves(
        pos, np.array([[RIGHT, WAIT]]), np.ones((1, 5, 5), bool), np.array([[True, False]])
    )
    assert out[0].tolist() == [[2, 2], [2, 2]]


def test_batches_are_independent():
    pos = np.array([[[0, 0], [0, 2]], [[0, 0], [0, 2]]])
    act = np.array([[RIGHT, LEFT], [RIGHT, WAIT]])
    out = resolve_moves(pos, act, np.ones((2, 3, 3), bool), np.ones((2, 2), bool))
    assert out[0].tolist() == [[0, 0], [0, 2]]  # both claim (0, 1)
    assert out[1].tolist() == [[0, 1], [0, 2]]


@settings(max_examples=300, deadline=None)
@given(
    size=st.integers(2, 6),
    n=st.integers(1, 12),
    seed=st.integers(0, 2**32 - 1),
)
def test_never_two_agents_in_a_cell_nor_a_swap(size, n, seed):
    rng = np.random.default_rng(seed)
    n = min(n, size * size)
    passable = rng.random((1, size, size)) > 0.2
    free = np.flatnonzero(passable[0])
    n = min(n, free.size)
    if n == 0:
        return
    cells = rng.choice(free, size=n, replace=False)
    pos = np.stack([cells // size, cells % size], -1)[None]
    act = rng.integers(0, 5, size=(1, n))
    present = np.ones((1, n), bool)
    out = resolve_moves(pos, act, passable, present)
    flat = out[0, :, 0] * size + out[0, :, 1]
    assert len(set(flat.tolist())) == n, "two agents in one cell"
    assert passable[0, out[0, :, 0], out[0, :, 1]].all(), "agent on a blocked cell"
    step_len = np.abs(out - pos).sum(-1)[0]
    assert (step_len <= 1).all()
    moved = step_len == 1
    assert (out[0][moved] == (pos + ACTION_DELTAS[act])[0][moved]).all(), "moved elsewhere"
    before = {tuple(p): i for i, p in enumerate(pos[0].tolist())}
    for i in np.flatnonzero(moved):
        j = before.get(tuple(out[0, i].tolist()))
        if j is not None:
            assert out[0, j].tolist() != pos[0, i].tolist(), "swap"


def _previous_resolve_moves(pos, actions, passable, present):
    """resolve_moves as numpy arrays, before the loop moved to udan._kernels (commit b68a9ec,
    without its cache of the cell numbering): the oracle the C loop is held to."""
    n_batch, height, width = passable.shape
    bordered = np.zeros((n_batch, height + 2, width + 2), dtype=bool)
    bordered[:, 1:-1, 1:-1] = passable
    cells = (height + 2) * (width + 2)
    strides = np.array([width + 2, 1])
    steps, base = ACTION_DELTAS @ strides, np.arange(0, n_batch * cells, cells)[:, None] + width + 3
    cur = pos @ strides + base
    dst = cur + steps[actions]
    dst = np.where(bordered.ravel().take(dst, mode="clip") & present, dst, cur)
    cur, dst = cur[present], dst[present]
    if cur.size == 0:
        return pos.copy()
    occupant = np.full(bordered.size, -1, dtype=np.int64)
    occupant[cur] = np.arange(cur.size)
    moving = dst != cur
    while moving.any():
        claims = np.bincount(dst, minlength=bordered.size)
        other = occupant[dst]
        blocked = moving & ((claims[dst] > 1) | ((other >= 0) & (dst[other] == cur)))
        if not blocked.any():
            break
        dst = np.where(blocked, cur, dst)
        moving &= ~blocked
    done = np.full(present.shape, WAIT)
    done[present] = np.where(dst != cur, actions[present], WAIT)
    return pos + ACTION_DELTAS[done]


@settings(max_examples=500, deadline=None)
@given(
    size=st.integers(1, 6),
    n=st.integers(1, 30),
    batch=st.integers(1, 4),
    seed=st.integers(0, 2**32 - 1),
)
def test_resolve_moves_moves_agents_as_the_previous_array_code_did(size, n, batch, seed):
    # crowded arenas: chains, swaps, rotations, several claims on one cell, absent agents
    # (anywhere on the arena, under others or not), side by side in a batch
    rng = np.random.default_rng(seed)
    height, width = size, int(rng.integers(1, 7))
    passable = rng.random((batch, height, width)) > 0.15
    pos = np.zeros((batch, n, 2), np.int64)
    present = np.zeros((batch, n), bool)
    for b in range(batch):
        free = np.flatnonzero(passable[b])
        count = min(n, free.size)
        cells = rng.choice(free, size=count, replace=False) if count else free
        present[b, :count] = rng.random(count) < 0.9
        pos[b, :count] = np.stack(np.divmod(cells, width), -1)
        pos[b, count:] = np.stack(np.divmod(rng.integers(0, height * width, n - count), width), -1)
    actions = rng.integers(0, 5, (batch, n))
    want = _previous_resolve_moves(pos, actions, passable, present)
    assert resolve_moves(pos, actions, passable, present).tolist() == want.tolist()


def test_an_agent_off_its_arena_is_refused():
    with pytest.raises(ValueError, match=r"agent 1 at \(0, 5\) is off the 5x5 arena"):
        step([[0, 0], [0, 5]], [UP, UP])
    with pytest.raises(IndexError, match="action 7"):
        step([[0, 0]], [7])
