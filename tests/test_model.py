"""EncodeProcessDecode against the definitions: interaction networks, residuals, options."""

from __future__ import annotations

import pytest
import torch
from gns.config import ModelConfig
from gns.model import EncodeProcessDecode, InteractionNetwork, build_mlp
from torch import nn

TINY = dict(latent_size=16, mlp_hidden_size=16, message_passing_steps=2)


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def random_graph(n=30, e=120, seed=0, node_size=7, edge_size=3):
    g = torch.Generator().manual_seed(seed)
    senders = torch.randint(0, n, (e,), generator=g)
    receivers = torch.randint(0, n, (e,), generator=g)
    nodes = torch.randn(n, node_size, generator=g)
    edges = torch.randn(e, edge_size, generator=g)
    return nodes, edges, senders, receivers


def test_build_mlp_has_the_requested_depth_and_optional_layer_norm():
    mlp = build_mlp(5, 8, 2, 3, layer_norm=True)
    linears = [m for m in mlp if isinstance(m, nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(5, 8), (8, 8), (8, 3)]
    assert isinstance(mlp[-1], nn.LayerNorm)
    linear = build_mlp(5, 8, 0, 3)
    assert len(linear) == 1 and isinstance(linear[0], nn.Linear)


def test_interaction_network_matches_a_per_edge_loop():
    torch.manual_seed(0)
    config = ModelConfig(**TINY)
    step = InteractionNetwork(config)
    nodes, edges, senders, receivers = random_graph(n=9, e=25, node_size=16, edge_size=16)
    new_nodes, new_edges, new_globals = step(nodes, edges, senders, receivers)
    assert new_globals is None
    # The definition, one edge at a time: e' = phi_e(e, v_s, v_r); v' = phi_v(v, sum e').
    expected_edges = edges.clone()
    incoming = torch.zeros_like(nodes)
    for k in range(edges.shape[0]):
        s, r = int(senders[k]), int(receivers[k])
        message = step.edge_mlp(torch.cat([edges[k], nodes[s], nodes[r]]))
        expected_edges[k] = edges[k] + message
        incoming[r] += message
    expected_nodes = nodes + step.node_mlp(torch.cat([nodes, incoming], dim=-1))
    torch.testing.assert_close(new_edges, expected_edges, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(new_nodes, expected_nodes, rtol=1e-5, atol=1e-5)


def capture_steps(model):
    """(input, output) latents of every processor step of the next forward pass."""
    records = []

    def hook(module, args, output):
        records.append((args[0], args[1], output[0], output[1]))

    handles = [step.register_forward_hook(hook) for step in model.processor]
    return records, handles


@pytest.mark.parametrize("edge_updates", [True, False])
def test_every_processor_step_changes_node_and_edge_latents(edge_updates):
    torch.manual_seed(1)
    config = ModelConfig(**{**TINY, "message_passing_steps": 3}, edge_latent_updates=edge_updates)
    model = EncodeProcessDecode(7, 3, 2, config)
    records, handles = capture_steps(model)
    model(*random_graph())
    for h in handles:
        h.remove()
    assert len(records) == 3
    for nodes_in, edges_in, nodes_out, edges_out in records:
        assert (nodes_out - nodes_in).norm() > 1e-2 * nodes_in.norm()
        if edge_updates:
            assert (edges_out - edges_in).norm() > 1e-2 * edges_in.norm()
        else:
            assert torch.equal(edges_out, edges_in)
    # Edge latents reach the next step: the second step sees the first step's output.
    assert torch.equal(records[1][1], records[0][3])


def test_processor_steps_are_unshared():
    model = EncodeProcessDecode(7, 3, 2, ModelConfig(**TINY))
    a, b = model.processor
    assert a.edge_mlp[0].weight.data_ptr() != b.edge_mlp[0].weight.data_ptr()
    assert not torch.equal(a.edge_mlp[0].weight, b.edge_mlp[0].weight)


def test_the_model_is_permutation_equivariant():
    torch.manual_seed(2)
    model = EncodeProcessDecode(7, 3, 2, ModelConfig(**TINY)).double()
    nodes, edges, senders, receivers = random_graph(seed=3)
    nodes, edges = nodes.double(), edges.double()
    out = model(nodes, edges, senders, receivers)
    g = torch.Generator().manual_seed(4)
    perm = torch.randperm(nodes.shape[0], generator=g)  # new node i is old node perm[i]
    inverse = torch.argsort(perm)
    edge_perm = torch.randperm(edges.shape[0], generator=g)
    out_perm = model(
        nodes[perm], edges[edge_perm], inverse[senders[edge_perm]], inverse[receivers[edge_perm]]
    )
    torch.testing.assert_close(out_perm, out[perm], rtol=1e-10, atol=1e-12)


def test_disjoint_graphs_in_one_batch_do_not_interact():
    torch.manual_seed(5)
    model = EncodeProcessDecode(7, 3, 2, ModelConfig(**TINY)).double()
    a = [t.double() if t.is_floating_point() else t for t in random_graph(n=10, e=40, seed=6)]
    b = [t.double() if t.is_floating_point() else t for t in random_graph(n=12, e=50, seed=7)]
    batched = model(
        torch.cat([a[0], b[0]]), torch.cat([a[1], b[1]]), torch.cat([a[2], b[2] + 10]),
        torch.cat([a[3], b[3] + 10]),
    )  # fmt: skip
    torch.testing.assert_close(batched, torch.cat([model(*a), model(*b)]))


def test_linear_encoder_and_decoder():
    model = EncodeProcessDecode(7, 3, 2, ModelConfig(**TINY, mlp_encoder_decoder=False))
    assert [type(m) for m in model.node_encoder] == [nn.Linear, nn.LayerNorm]
    assert [type(m) for m in model.decoder] == [nn.Linear]
    plain = EncodeProcessDecode(7, 3, 2, ModelConfig(**TINY, layer_norm=False))
    assert not any(isinstance(m, nn.LayerNorm) for m in plain.modules())
    assert sum(isinstance(m, nn.Linear) for m in plain.decoder) == 3


def test_global_latent_is_per_graph_and_updated_every_step():
    torch.manual_seed(8)
    config = ModelConfig(**TINY, global_latent=True)
    model = EncodeProcessDecode(7, 3, 2, config, global_input_size=1).double()
    nodes, edges, senders, receivers = random_graph(n=20, e=0, seed=9)
    # Two graphs of 10 nodes; edges only inside each graph.
    g = torch.Generator().manual_seed(10)
    senders = torch.cat([torch.randint(0, 10, (30,), generator=g), torch.randint(10, 20, (30,))])
    receivers = torch.cat([torch.randint(0, 10, (30,), generator=g), torch.randint(10, 20, (30,))])
    nodes, edges = nodes.double(), torch.randn(60, 3, generator=g, dtype=torch.float64)
    n_node = torch.tensor([10, 10])
    context = torch.tensor([[0.3], [0.8]], dtype=torch.float64)
    globals_seen = []
    handles = [
        s.register_forward_hook(lambda m, args, out: globals_seen.append((args[4], out[2])))
        for s in model.processor
    ]
    out = model(nodes, edges, senders, receivers, context, n_node)
    for h in handles:
        h.remove()
    for before, after in globals_seen:
        assert after.shape == (2, 16) and (after - before).norm() > 1e-2 * before.norm()
    changed = model(
        nodes, edges, senders, receivers, context * torch.tensor([[1.0], [2.0]]), n_node
    )
    torch.testing.assert_close(changed[:10], out[:10], rtol=1e-12, atol=1e-12)
    assert (changed[10:] - out[10:]).abs().max() > 1e-6


def test_global_latent_without_global_input_starts_from_a_learned_vector():
    model = EncodeProcessDecode(7, 3, 2, ModelConfig(**TINY, global_latent=True))
    assert model.global_encoder is None and model.initial_global is not None
    assert model(*random_graph()).shape == (30, 2)


def test_global_features_need_a_global_latent():
    with pytest.raises(ValueError, match="global_latent"):
        EncodeProcessDecode(7, 3, 2, ModelConfig(**TINY), global_input_size=2)
    model = EncodeProcessDecode(7, 3, 2, ModelConfig(**TINY))
    with pytest.raises(ValueError, match="no global input"):
        model(*random_graph(), torch.zeros(1, 2))
