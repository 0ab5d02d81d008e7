"""EncodeProcessDecode: the graph network of the GNS, as plain nn.Modules.

Encoder: MLPs lift node and edge features to latents. Processor: M unshared interaction
networks (sum aggregation, residuals on nodes and edges). Decoder: an MLP from node latents to
the (normalised) acceleration. Graphs arrive as senders / receivers index tensors (E,); several
graphs are one disjoint graph, told apart by n_node only where a global latent needs it.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from gns.config import ModelConfig

__all__ = ["EncodeProcessDecode", "InteractionNetwork", "build_mlp"]


def build_mlp(
    input_size: int,
    hidden_size: int,
    num_hidden_layers: int,
    output_size: int,
    layer_norm: bool = False,
) -> nn.Sequential:
    """Linear-ReLU blocks then a linear output, optionally LayerNorm-ed.

    num_hidden_layers=0 gives a single linear layer (the paper's "linear encoder/decoder").
    """
    layers: list[nn.Module] = []
    width = input_size
    for _ in range(num_hidden_layers):
        layers += [nn.Linear(width, hidden_size), nn.ReLU()]
        width = hidden_size
    layers.append(nn.Linear(width, output_size))
    if layer_norm:
        layers.append(nn.LayerNorm(output_size))
    return nn.Sequential(*layers)


def _sum_per_graph(values: Tensor, graph: Tensor, num_graphs: int) -> Tensor:
    out = values.new_zeros(num_graphs, values.shape[1])
    return out.index_add_(0, graph, values)


class InteractionNetwork(nn.Module):
    """One message-passing step: edge update, sum into receivers, node update, residuals.

    With a global latent (the full GN block of Battaglia et al. 2018) the global latent enters
    every edge and node update and is itself updated from the per-graph sums of the edge and
    node updates (the GN block's e' and v', before the residual).
    """

    def __init__(self, config: ModelConfig, global_latent: bool = False) -> None:
        super().__init__()
        latent, hidden, depth = config.latent_size, config.mlp_hidden_size, config.mlp_hidden_layers
        extra = latent if global_latent else 0
        norm = config.layer_norm
        self.edge_mlp = build_mlp(3 * latent + extra, hidden, depth, latent, norm)
        self.node_mlp = build_mlp(2 * latent + extra, hidden, depth, latent, norm)
        self.global_mlp = build_mlp(3 * latent, hidden, depth, latent, norm) if extra else None
        self.update_edges = config.edge_latent_updates

    def forward(
        self,
        nodes: Tensor,
        edges: Tensor,
        senders: Tensor,
        receivers: Tensor,
        globals_: Tensor | None = None,
        node_graph: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """nodes (N, L), edges (E, L), senders / receivers (E,) int64; with a global latent also
        globals_ (G, L) and node_graph (N,) the graph of each node. Returns the new latents."""
        edge_globals: list[Tensor] = []
        node_globals: list[Tensor] = []
        if globals_ is not None:
            assert node_graph is not None, "a global latent needs node_graph"
            node_globals = [globals_.index_select(0, node_graph)]
            edge_globals = [node_globals[0].index_select(0, receivers)]
        sender_latents = nodes.index_select(0, senders)
        receiver_latents = nodes.index_select(0, receivers)
        messages = self.edge_mlp(
            torch.cat([edges, sender_latents, receiver_latents, *edge_globals], dim=-1)
        )
        aggregated = nodes.new_zeros(nodes.shape[0], messages.shape[1])
        aggregated.index_add_(0, receivers, messages)
        node_update = self.node_mlp(torch.cat([nodes, aggregated, *node_globals], dim=-1))
        new_globals = None
        if globals_ is not None and node_graph is not None and self.global_mlp is not None:
            g = globals_.shape[0]
            edge_graph = node_graph.index_select(0, receivers)
            pooled = [
                globals_,
                _sum_per_graph(node_update, node_graph, g),
                _sum_per_graph(messages, edge_graph, g),
            ]
            new_globals = globals_ + self.global_mlp(torch.cat(pooled, dim=-1))
        # Residuals; edge latents stay as encoded when the edge updates are switched off.
        new_edges = edges + messages if self.update_edges else edges
        return nodes + node_update, new_edges, new_globals


class EncodeProcessDecode(nn.Module):
    """The GNS graph network.

    node_input_size, edge_input_size: feature widths (from the scene, see simulator.py).
    global_input_size: width of the global features when config.global_latent (0: the global
        latent starts from a learned vector).
    output_size: D, the acceleration's dimension.
    """

    def __init__(
        self,
        node_input_size: int,
        edge_input_size: int,
        output_size: int,
        config: ModelConfig,
        global_input_size: int = 0,
    ) -> None:
        super().__init__()
        latent, hidden = config.latent_size, config.mlp_hidden_size
        depth = config.mlp_hidden_layers if config.mlp_encoder_decoder else 0
        norm = config.layer_norm
        self.config = config
        self.node_encoder = build_mlp(node_input_size, hidden, depth, latent, norm)
        self.edge_encoder = build_mlp(edge_input_size, hidden, depth, latent, norm)
        self.global_encoder: nn.Module | None = None
        self.initial_global: nn.Parameter | None = None
        if config.global_latent:
            if global_input_size > 0:
                self.global_encoder = build_mlp(global_input_size, hidden, depth, latent, norm)
            else:
                self.initial_global = nn.Parameter(torch.zeros(latent))
        elif global_input_size:
            raise ValueError(
                "global features need config.global_latent; otherwise append them to the nodes"
            )
        self.processor = nn.ModuleList(
            InteractionNetwork(config, config.global_latent)
            for _ in range(config.message_passing_steps)
        )
        self.decoder = build_mlp(latent, hidden, depth, output_size, layer_norm=False)

    def forward(
        self,
        node_features: Tensor,
        edge_features: Tensor,
        senders: Tensor,
        receivers: Tensor,
        global_features: Tensor | None = None,
        n_node: Tensor | None = None,
    ) -> Tensor:
        """node_features (N, node_input_size), edge_features (E, edge_input_size), senders and
        receivers (E,) int64; with a global latent also n_node (G,) (default: one graph) and
        global_features (G, global_input_size). Returns (N, output_size)."""
        nodes = self.node_encoder(node_features)
        edges = self.edge_encoder(edge_features)
        globals_, node_graph = None, None
        if self.config.global_latent:
            n = node_features.shape[0]
            if n_node is None:
                n_node = torch.tensor([n], device=node_features.device)
            n_node = n_node.to(node_features.device)
            node_graph = torch.repeat_interleave(
                torch.arange(n_node.shape[0], device=n_node.device), n_node, output_size=n
            )
            if self.global_encoder is not None:
                if global_features is None:
                    raise ValueError("this model was built with global features; pass them")
                globals_ = self.global_encoder(global_features)
            else:
                assert self.initial_global is not None
                globals_ = self.initial_global.expand(n_node.shape[0], -1)
        elif global_features is not None:
            raise ValueError("this model has no global input; append global features to nodes")
        for step in self.processor:
            nodes, edges, globals_ = step(nodes, edges, senders, receivers, globals_, node_graph)
        return self.decoder(nodes)
