"""World rules: simultaneous moves, conflicts, walls (the shared 'what a move does')."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from udan.envs.rules import (
    ACTION_DELTAS,
    DOWN,
    LEFT,
    RIGHT,
    UP,
    WAIT,
    resolve_few,
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


@settings(max_examples=500, deadline=None)
@given(size=st.integers(2, 5), n=st.integers(1, 14), seed=st.integers(0, 2**32 - 1))
def test_resolve_few_moves_agents_as_resolve_moves_does(size, n, seed):
    # crowded arenas: chains, swaps, rotations and several claims on one cell are common
    rng = np.random.default_rng(seed)
    passable = rng.random((size, size)) > 0.15
    free = np.flatnonzero(passable)
    n = min(n, free.size)
    if n == 0:
        return
    cells = rng.choice(free, size=n, replace=False)
    pos = np.stack([cells // size, cells % size], -1)
    act = rng.integers(0, 5, size=n)
    want = pos + ACTION_DELTAS[act]
    inside = ((want >= 0) & (want < size)).all(1)
    ok = inside & passable[want[:, 0].clip(0, size - 1), want[:, 1].clip(0, size - 1)]
    dst = np.where(ok[:, None], want, pos)
    moved = resolve_few(list(map(tuple, pos.tolist())), list(map(tuple, dst.tolist())))
    out = resolve_moves(pos[None], act[None], passable[None], np.ones((1, n), bool))[0]
    assert moved == (out != pos).any(1).tolist()
