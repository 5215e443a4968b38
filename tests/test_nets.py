"""UDAN building blocks: bridges, masks, monotonic mixing for any N."""

import torch

from udan.nets import AgentEncoder, GroupComm, LeaderScorer, QHead, SetMixer

torch.manual_seed(0)
H = 16


def test_mixer_is_monotonic_in_every_q_for_n_1_to_64():
    mixer = SetMixer(H, 8)
    for n in (1, 2, 3, 5, 17, 64):
        q = torch.randn(4, n, requires_grad=True)
        feats = torch.randn(4, n, H)
        q_tot = mixer(q, feats, torch.ones(4, n, dtype=torch.bool))
        assert q_tot.shape == (4,)
        (grad,) = torch.autograd.grad(q_tot.sum(), q)
        assert (grad >= 0).all()


def test_a_mixer_started_as_a_sum_is_vdn_until_it_learns():
    mixer = SetMixer(H, 8)
    mixer.start_as_sum()
    q = (torch.randn(3, 20) * 4).requires_grad_()
    mask = torch.rand(3, 20) < 0.7
    q_tot = mixer(q, torch.randn(3, 20, H), mask)
    assert torch.allclose(q_tot, q.masked_fill(~mask, 0).sum(1), atol=1e-4)
    q_tot.sum().backward()
    assert torch.allclose(q.grad, mask.float())
    assert mixer.w1.weight.grad.abs().sum() > 0, "the agents' features can still shape the mix"


def test_padded_agents_contribute_nothing_to_the_mixer():
    mixer = SetMixer(H, 8)
    q, feats = torch.randn(2, 3), torch.randn(2, 3, H)
    mask = torch.ones(2, 3, dtype=torch.bool)
    padded_q = torch.cat([q, torch.randn(2, 4) * 100], 1)
    padded_f = torch.cat([feats, torch.randn(2, 4, H)], 1)
    padded_mask = torch.cat([mask, torch.zeros(2, 4, dtype=torch.bool)], 1)
    assert torch.allclose(mixer(q, feats, mask), mixer(padded_q, padded_f, padded_mask))


def test_leader_attention_covers_only_the_neighbourhood():
    scorer = LeaderScorer(H, 8)
    feats = torch.randn(4, H)
    neighbours = torch.tensor([[0, 1, -1], [1, 0, -1], [2, 3, -1], [3, 2, -1]])
    logits = scorer(feats, neighbours)
    assert logits.shape == (4,) and torch.isfinite(logits).all()
    other = feats.clone()
    other[2:] += torch.randn(2, H) * 10  # agents outside 0's and 1's neighbourhood
    assert torch.allclose(scorer(other, neighbours)[:2], logits[:2])
    assert not torch.allclose(scorer(other, neighbours)[2:], logits[2:])
    absent = scorer(feats, torch.tensor([[-1, -1, -1]] * 4))
    assert torch.isfinite(absent).all(), "rows of absent slots stay finite"


def test_a_bridge_carries_information_from_its_first_group_into_its_second():
    comm = GroupComm(H)
    feats = torch.randn(5, H)
    rounds = [torch.tensor([[0, 1, 2]]), torch.tensor([[3, 2, 4]])]  # agent 2 bridges
    base = comm(feats, rounds)
    changed = feats.clone()
    changed[0] += 1.0  # only in the first group
    after = comm(changed, rounds)
    assert not torch.allclose(after[3], base[3]), "agent 3 hears agent 0 through the bridge"
    # without the bridge ordering (both groups in one pass each, no shared member) it would not
    lone = comm(changed, [torch.tensor([[3, 4]])])
    assert torch.allclose(lone[3], comm(feats, [torch.tensor([[3, 4]])])[3])


def test_ungrouped_agents_get_a_zero_message_and_q_heads_shape():
    comm, head = GroupComm(H), QHead(H, 5)
    feats = torch.randn(4, H)
    msg = comm(feats, [torch.tensor([[0, 1]])])
    assert (msg[2:] == 0).all() and (msg[:2] != 0).any()
    assert head(feats, msg).shape == (4, 5)


def test_encoder_state_is_per_agent_and_fresh_agents_forget():
    enc = AgentEncoder(10, H)
    obs = torch.randn(1, 3, 10)
    feats, state = enc(obs, enc.initial_state(3))
    feats2, _ = enc(obs, state)
    assert feats.shape == (1, 3, H) and not torch.allclose(feats, feats2), "memory matters"
    single, _ = enc(obs[:, 1:2], enc.initial_state(1))
    assert torch.allclose(single, feats[:, 1:2], atol=1e-6)
    fresh = torch.tensor([[False, True, False]])
    again, _ = enc(obs, state, fresh)
    assert torch.allclose(again[0, 1], feats[0, 1], atol=1e-6), "a new agent starts from zero"
    assert torch.allclose(again[0, 0], feats2[0, 0], atol=1e-6)


def test_fused_sequence_equals_step_by_step_with_mid_sequence_joins():
    enc = AgentEncoder(10, H)
    obs = torch.randn(6, 4, 10)
    fresh = torch.zeros(6, 4, dtype=torch.bool)
    fresh[0] = True
    whole, _ = enc(obs, enc.initial_state(4), fresh)
    state, steps = enc.initial_state(4), []
    for t in range(6):
        out, state = enc(obs[t : t + 1], state, fresh[t : t + 1])
        steps.append(out)
    assert torch.allclose(whole, torch.cat(steps), atol=1e-5)
    fresh[3, 2] = True  # an agent joins slot 2 at step 3
    joined, _ = enc(obs, enc.initial_state(4), fresh)
    restart, _ = enc(obs[3:, 2:3], enc.initial_state(1))
    assert torch.allclose(joined[3:, 2:3], restart, atol=1e-5)
