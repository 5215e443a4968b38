"""Leaders, groups and bridge rounds (shared by training and the edge)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from udan.envs.grouping import (
    communication_matrix,
    form_groups,
    group_rounds,
    hypothetical_groups,
    nearest,
    neighbour_table,
    neighbour_tables,
    round_order,
)


def test_a_leader_groups_with_its_k_minus_1_nearest():
    pos = np.array([[0, 0], [0, 1], [5, 5], [0, 3], [8, 8]])
    present = np.ones(5, bool)
    prob = np.array([0.9, 0.1, 0.2, 0.3, 0.1])
    groups = form_groups(pos, present, prob, k=3, threshold=0.5)
    assert groups.tolist() == [[0, 1, 3]]


def test_leaders_ordered_by_probability_and_absent_agents_ignored():
    pos = np.array([[0, 0], [0, 1], [0, 2], [7, 7], [7, 8]])
    present = np.array([True, True, True, False, True])
    prob = np.array([0.6, 0.1, 0.9, 0.99, 0.7])
    groups = form_groups(pos, present, prob, k=2, threshold=0.5)
    assert groups.tolist() == [[2, 1], [4, 2], [0, 1]]


def test_a_leader_is_above_the_threshold_in_the_probabilities_own_type():
    """Exactly at the threshold is not above it, and float32 probabilities meet the threshold as
    a float32, as numpy compares them (float32(0.3) is not above 0.3 rounded to float32, though
    it is above the float64 0.3); equal probabilities lead in slot order."""
    pos = np.array([[0, 0], [0, 1], [0, 2], [5, 5]])
    present = np.ones(4, bool)
    prob = np.array([0.5, 0.7, 0.5000001, 0.7], np.float32)
    assert form_groups(pos, present, prob, 2, 0.5).tolist() == [[1, 0], [3, 2], [2, 1]]
    thirty = np.full(4, 0.3, np.float32)
    assert len(form_groups(pos, present, thirty, 2, 0.3)) == 0
    assert len(form_groups(pos, present, thirty.astype(np.float64), 2, 0.3)) == 4


def test_no_leader_or_too_few_agents_means_no_groups():
    pos = np.array([[0, 0], [1, 1]])
    assert form_groups(pos, np.ones(2, bool), np.array([0.1, 0.2]), 3, 0.5).shape == (0, 2)
    assert form_groups(pos, np.array([True, False]), np.ones(2), 3, 0.5).shape[0] == 0


def test_groups_shrink_to_the_fleet():
    pos = np.array([[0, 0], [4, 4]])
    groups = form_groups(pos, np.ones(2, bool), np.array([0.9, 0.1]), k=4, threshold=0.5)
    assert groups.tolist() == [[0, 1]]


def test_rounds_are_disjoint_and_keep_each_agents_group_order():
    groups = np.array([[0, 1, 2], [3, 2, 4], [5, 6, 7], [2, 8, 9], [4, 5, 9]])
    rounds = group_rounds(groups)
    seen_round = {}
    for r, idx in enumerate(rounds):
        members = groups[idx].ravel()
        assert len(set(members.tolist())) == members.size, "a round's groups share an agent"
        for g in idx:
            for m in groups[g]:
                assert seen_round.get(m, -1) < r
                seen_round[m] = r
    assert [i.tolist() for i in rounds] == [[0, 2], [1], [3], [4]]


@settings(max_examples=200, deadline=None)
@given(st.integers(2, 12), st.integers(2, 4), st.integers(0, 12), st.integers(0, 2**32 - 1))
def test_each_group_is_one_round_after_the_earlier_groups_it_shares_an_agent_with(
    agents, size, count, seed
):
    rng = np.random.default_rng(seed)
    size = min(size, agents)
    groups = np.array([rng.choice(agents, size, replace=False) for _ in range(count)])
    groups = groups.reshape(count, size)
    rounds = group_rounds(groups)
    round_of = {int(g): r for r, idx in enumerate(rounds) for g in idx}
    assert sorted(round_of) == list(range(count))
    assert all(list(idx) == sorted(idx) for idx in rounds)  # priority order within a round
    for g in range(count):
        shared = [h for h in range(g) if set(groups[h]) & set(groups[g])]
        assert round_of[g] == max((round_of[h] for h in shared), default=-1) + 1


def test_hypothetical_groups_and_the_communication_matrix():
    pos = np.array([[0, 0], [0, 1], [0, 5]])
    groups = hypothetical_groups(pos, np.ones(3, bool), k=2)
    assert sorted(g[0] for g in groups) == [0, 1, 2] and len(groups) == 3
    c = communication_matrix(np.array([[0, 1]]), 3)
    assert c.tolist() == [[True, True, False], [True, True, False], [False, False, False]]


@pytest.mark.parametrize("distinct_cells", [True, False])
def test_nearest_is_itself_first_then_by_distance_then_slot(distinct_cells):
    """Small and large fleets, agents on cells of their own or sharing cells, some absent:
    always a plain sort by (distance, slot)."""
    rng = np.random.default_rng(0)
    for _ in range(150):
        h, w = (int(v) for v in rng.integers(1, 12, size=2))
        n = int(rng.integers(1, 30 if rng.random() < 0.8 else 140))
        if distinct_cells:
            n = min(n, h * w)
            cells = rng.choice(h * w, size=n, replace=False)
        else:
            cells = rng.integers(0, h * w, size=n)
        pos = np.stack([cells // w, cells % w], -1) + rng.integers(-50, 50, size=2)
        present = rng.random(n) < (0.8 if rng.random() < 0.7 else 1.0)  # or all of them
        count = int(rng.integers(1, 10))
        got = nearest(pos, present, count)
        slots = np.flatnonzero(present)
        assert (got[~present] == -1).all()
        for i in slots:
            others = sorted((abs(pos[i] - pos[j]).sum(), j) for j in slots if j != i)
            want = [i, *[j for _, j in others][: min(count, len(slots)) - 1]]
            assert got[i].tolist() == want


def test_groups_from_a_precomputed_neighbour_table_equal_a_fresh_search():
    rng = np.random.default_rng(3)
    for _ in range(100):
        n = int(rng.integers(1, 20))
        cells = rng.choice(81, size=n, replace=False)
        pos = np.stack([cells // 9, cells % 9], -1)
        present = rng.random(n) < 0.8
        k, width = int(rng.integers(1, 5)), int(rng.integers(1, 10))
        table = neighbour_table(pos, present, width)
        near = nearest(pos, present, width)
        assert table.shape == (n, width) and (table[:, near.shape[1] :] == -1).all()
        assert (table[:, : near.shape[1]] == near).all()
        assert (
            hypothetical_groups(pos, present, k, table) == hypothetical_groups(pos, present, k)
        ).all()
        prob = rng.random(n)
        assert (
            form_groups(pos, present, prob, k, 0.5, near=table)
            == form_groups(pos, present, prob, k, 0.5)
        ).all()


@pytest.mark.parametrize("agents", [7, 70])
def test_many_arenas_at_once_equal_one_arena_at_a_time(agents):
    """Training's batched tables: shared cells and absent agents included; -1 columns beyond
    the agents present."""
    rng = np.random.default_rng(agents)
    for _ in range(50):
        m, count = int(rng.integers(0, 6)), int(rng.integers(1, 10))
        side = 20 if agents > 64 else int(rng.integers(3, 9))
        if rng.random() < 0.5:  # distinct cells, else shared ones
            flat = np.argsort(rng.random((m, side * side)), axis=1)[:, :agents]
        else:
            flat = rng.integers(0, side * side, (m, agents))
        pos = np.stack(np.divmod(flat, side), -1)
        present = rng.random((m, agents)) < rng.random()
        got = neighbour_tables(pos, present, count)
        assert got.shape == (m, agents, count)
        for i in range(m):
            assert (got[i] == neighbour_table(pos[i], present[i], count)).all()


def test_agents_spread_wider_than_the_search_grid_and_bad_members_are_refused():
    with pytest.raises(ValueError, match="span more than 2"):
        nearest(np.array([[0, 0], [3000, 3000]]), np.ones(2, bool), 2)
    with pytest.raises(ValueError, match="members are slots"):
        group_rounds(np.array([[0, -1]]))


def test_many_groups_get_the_rounds_of_the_rule():
    """Thousands of groups with long chains of shared members: each group one round after the
    last round holding any of its members (the rule, written as a plain loop)."""
    rng = np.random.default_rng(5)
    for _ in range(200):
        agents, size = int(rng.integers(3, 300)), int(rng.integers(1, 4))
        count = int(rng.integers(0, 2000))
        groups = np.stack([rng.choice(agents, size, replace=False) for _ in range(count)])
        groups = groups.reshape(count, size)
        last, rounds = {}, []
        for g, members in enumerate(groups.tolist()):
            r = max((last.get(m, -1) for m in members), default=-1) + 1
            rounds.extend([] for _ in range(r + 1 - len(rounds)))
            rounds[r].append(g)
            last.update(dict.fromkeys(members, r))
        assert [r.tolist() for r in group_rounds(groups)] == rounds
        order, sizes = round_order(groups)
        assert order.tolist() == [g for r in rounds for g in r]
        assert sizes.tolist() == list(map(len, rounds))
