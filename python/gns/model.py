"""EncodeProcessDecode: the graph network of the GNS, as plain nn.Modules.

Encoder: MLPs lift node and edge features to latents. Processor: M unshared interaction
networks (sum aggregation, residuals on nodes and edges). Decoder: an MLP from node latents to
the (normalised) acceleration. Graphs arrive as senders / receivers index tensors (E,); several
graphs are one disjoint graph, told apart by n_node only where a global latent needs it.

Two implementations of the same function share every parameter (one state_dict loads into
either): "plain", the readable reference (gather, concatenate, MLP, index_add_), and "fast", the
default, which splits the first layer of each edge MLP so that the sender and receiver parts
are multiplied once per node instead of once per edge (see InteractionNetwork). `precision`
"bf16" runs the network under autocast (matmuls in bfloat16, LayerNorm, sums and the output in
float32); "auto" runs fp32 here, and rollouts may switch it to bf16 after measuring (see
gns.rollout).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterable
from contextlib import AbstractContextManager, nullcontext
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from gns.config import IMPLEMENTATIONS, Implementation, ModelConfig, Precision

__all__ = [
    "EncodeProcessDecode",
    "InteractionNetwork",
    "at_least_fp32",
    "build_mlp",
    "native_bf16",
    "precision_context",
    "resolve_precision",
]


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


# Edges per block (and per CPU thread) of the fast path's edge MLP without autograd: (1024, 128)
# fp32 temporaries are 512 KiB, one L2 cache; on a 2-core EPYC (AVX2, one thread) blocks of
# 1024-2048 edges ran GNS-10-128 ~25% faster than whole (E, 128) tensors, which spill to L3
# between the matmul, ReLU and LayerNorm passes. GPUs run whole tensors.
EDGE_BLOCK = 1024


def _run_mlp(layers: Iterable[nn.Module], x: Tensor) -> Tensor:
    """An MLP of build_mlp's layers as the fast path runs it.

    ReLUs run in place: their input is always the fresh output of a Linear that autograd does
    not need again (addmm saves its inputs, not its output), which saves one (rows, width)
    temporary per hidden layer. LayerNorm runs in at least float32, so that under bf16
    autocast (where CPU autocast would keep it in bf16) the latents and their residual sums
    stay float32 and only the matmuls are bf16.
    """
    for layer in layers:
        if isinstance(layer, nn.ReLU):
            x = torch.relu_(x)
        elif isinstance(layer, nn.LayerNorm):
            x = layer(at_least_fp32(x))
        else:
            x = layer(x)
    return x


def at_least_fp32(x: Tensor) -> Tensor:
    """x in at least float32: bfloat16 (under autocast) becomes float32, float32 and float64
    stay as they are. The GNS's and CConv's residual streams and outputs are kept so."""
    return x.to(torch.promote_types(x.dtype, torch.float32))


def _sum_per_graph(values: Tensor, graph: Tensor, num_graphs: int) -> Tensor:
    out = values.new_zeros(num_graphs, values.shape[1])
    return out.index_add_(0, graph, values)


def _sum_into(values: Tensor, index: Tensor, rows: int) -> Tensor:
    """(rows, W) sums of the (E, W) values by index, in at least float32: a bfloat16 sum of a
    dozen messages would round away the small ones."""
    dtype = torch.promote_types(values.dtype, torch.float32)
    out = values.new_zeros(rows, values.shape[1], dtype=dtype)
    return out.index_add_(0, index, values.to(dtype))


class InteractionNetwork(nn.Module):
    """One message-passing step: edge update, sum into receivers, node update, residuals.

    With a global latent (the full GN block of Battaglia et al. 2018) the global latent enters
    every edge and node update and is itself updated from the per-graph sums of the edge and
    node updates (the GN block's e' and v', before the residual).

    Parameters are those of the plain definition; implementation="fast" computes the same
    function with the edge MLP's first Linear split by columns, W = [W_e | W_s | W_r (| W_g)]:
    W [e, v_s, v_r] = W_e e + (W_s v)[s] + (W_r v)[r], so the node parts cost N rows instead of
    E (E/N is ~11-25 in the paper's datasets): about 40% of the edge MLP's FLOPs at L = H.
    Without autograd (rollouts) it also runs the edge MLP over cache-sized blocks of edges.
    Neither path assumes sorted or symmetric edges: the backward of the gathers is index_add_
    of a contiguous gradient, as fast on a CPU as a sorted segment sum (the (N, H) target
    stays in cache), so the reverse-edge permutation buys nothing here.
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
        *,
        implementation: Implementation = "fast",
        edge_mask: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """nodes (N, L), edges (E, L), senders / receivers (E,) int64; with a global latent also
        globals_ (G, L) and node_graph (N,) the graph of each node. Returns the new latents.
        implementation: "fast" or "plain" (the same function, see the class). edge_mask (E,):
        1 for an edge, 0 for a padding edge, whose message is zeroed before it reaches any node
        or global sum (see EncodeProcessDecode.forward)."""
        if globals_ is not None and node_graph is None:
            raise ValueError("a global latent needs node_graph")
        args = (nodes, edges, senders, receivers, globals_, node_graph, edge_mask)
        if implementation == "fast":
            return self._fast(*args)
        if implementation != "plain":
            raise ValueError(f"implementation must be 'fast' or 'plain', got {implementation!r}")
        return self._plain(*args)

    def _plain(
        self,
        nodes: Tensor,
        edges: Tensor,
        senders: Tensor,
        receivers: Tensor,
        globals_: Tensor | None,
        node_graph: Tensor | None,
        edge_mask: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """The reference: the GN block as written, every edge MLP input concatenated."""
        edge_globals: list[Tensor] = []
        node_globals: list[Tensor] = []
        if globals_ is not None and node_graph is not None:
            node_globals = [globals_.index_select(0, node_graph)]
            edge_globals = [node_globals[0].index_select(0, receivers)]
        sender_latents = nodes.index_select(0, senders)
        receiver_latents = nodes.index_select(0, receivers)
        messages = _masked(
            self.edge_mlp(torch.cat([edges, sender_latents, receiver_latents, *edge_globals], -1)),
            edge_mask,
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

    def _fast(
        self,
        nodes: Tensor,
        edges: Tensor,
        senders: Tensor,
        receivers: Tensor,
        globals_: Tensor | None,
        node_graph: Tensor | None,
        edge_mask: Tensor | None = None,
    ) -> tuple[Tensor, Tensor, Tensor | None]:
        """The same function as _plain with the first edge layer split (see the class)."""
        n, latent = nodes.shape
        first = self.edge_mlp[0]
        assert isinstance(first, nn.Linear)
        weight, hidden = first.weight, first.out_features
        # (2H, L): the sender and receiver column blocks stacked, so one (N, L) @ (L, 2H)
        # matmul projects every node for both roles.
        w_nodes = torch.cat([weight[:, latent : 2 * latent], weight[:, 2 * latent : 3 * latent]])
        projected = F.linear(nodes, w_nodes)
        from_senders = projected[:, :hidden]
        # The bias and the receiver's global latent are per receiver: add them on N rows, not E.
        from_receivers = projected[:, hidden:] + first.bias.to(projected.dtype)
        node_inputs = [nodes]
        edge_graph = None
        if globals_ is not None and node_graph is not None:
            node_inputs.append(globals_.index_select(0, node_graph))
            per_graph = F.linear(globals_, weight[:, 3 * latent :]).to(projected.dtype)
            from_receivers = from_receivers + per_graph.index_select(0, node_graph)
            edge_graph = node_graph.index_select(0, receivers)
        w_edge = weight[:, :latent]
        layers = list(self.edge_mlp)[1:]
        tracked = torch.is_grad_enabled() and any(t.requires_grad for t in (nodes, edges, weight))

        def messages_of(edge: slice) -> Tensor:
            """phi_e of the edges in `edge`: W_e e + (W_s v)[s] + (W_r v + b)[r], then the
            rest of the edge MLP; padding edges' zeroed."""
            gathered = from_senders.index_select(0, senders[edge])
            gathered = gathered.add_(from_receivers.index_select(0, receivers[edge]))
            mask = None if edge_mask is None else edge_mask[edge]
            if not gathered.dtype == edges.dtype == w_edge.dtype:
                # Under autocast `gathered` is bf16, and addmm casts the fp32 edges.
                first_layer = torch.addmm(gathered, edges[edge], w_edge.t())
            else:
                # In place saves addmm copying `gathered` into a new output first (autograd
                # allows it: no backward needs the sum of the gathers).
                first_layer = gathered.addmm_(edges[edge], w_edge.t())
            return _masked(_run_mlp(layers, first_layer), mask)

        num_edges = edges.shape[0]
        pooled_messages = None
        # torch.compile fuses the whole-tensor path itself, and a Python loop over E / block
        # would specialise the compiled graph on E, which changes every step.
        if tracked or torch.compiler.is_compiling() or edges.device.type != "cpu":
            messages = messages_of(slice(0, num_edges))
            aggregated = _sum_into(messages, receivers, n)
            if edge_graph is not None and globals_ is not None:
                pooled_messages = _sum_into(messages, edge_graph, globals_.shape[0])
            new_edges = edges + messages if self.update_edges else edges
        else:
            # Without autograd nothing needs the (E, H) intermediates afterwards: run the edge
            # MLP over blocks of edges whose temporaries stay in cache, summing and adding the
            # residual block by block (the sums in the same edge order as the whole tensor).
            dtype = torch.promote_types(edges.dtype, torch.float32)
            aggregated = edges.new_zeros(n, latent, dtype=dtype)
            if edge_graph is not None and globals_ is not None:
                pooled_messages = edges.new_zeros(globals_.shape[0], latent, dtype=dtype)
            new_edges = torch.empty_like(edges) if self.update_edges else edges
            size = EDGE_BLOCK * torch.get_num_threads()  # each thread's rows stay in its L2
            for begin in range(0, num_edges, size):
                block = slice(begin, begin + size)
                messages = messages_of(block)
                aggregated.index_add_(0, receivers[block], messages.to(dtype))
                if pooled_messages is not None and edge_graph is not None:
                    pooled_messages.index_add_(0, edge_graph[block], messages.to(dtype))
                if self.update_edges:
                    torch.add(edges[block], messages, out=new_edges[block])

        node_inputs.insert(1, aggregated.to(nodes.dtype))
        node_update = _run_mlp(self.node_mlp, torch.cat(node_inputs, dim=-1))
        new_globals = None
        if globals_ is not None and node_graph is not None and self.global_mlp is not None:
            assert pooled_messages is not None
            pooled = [
                globals_,
                _sum_into(node_update, node_graph, globals_.shape[0]).to(globals_.dtype),
                pooled_messages.to(globals_.dtype),
            ]
            new_globals = globals_ + self.global_mlp(torch.cat(pooled, dim=-1))
        return _residual(nodes, node_update), new_edges, new_globals


def _masked(messages: Tensor, edge_mask: Tensor | None) -> Tensor:
    """The (E, L) messages with those of padding edges (edge_mask 0) zeroed: index_add_ then
    adds exact zeros, so every node's sum is what it is without the padding. A multiply, not a
    select, so that the whole step stays one fixed-shape graph (CUDA graphs)."""
    if edge_mask is None:
        return messages
    return messages * edge_mask.to(messages.dtype)[:, None]


def _residual(x: Tensor, update: Tensor) -> Tensor:
    """x + update; without autograd in place on `update`, a fresh MLP output. With autograd
    out of place, as index_add_ (the global latent's pooling) saves its source for the
    backward. Never in place when that would round an fp32 residual stream to the bf16 of an
    autocast update."""
    tracked = torch.is_grad_enabled() and (update.requires_grad or x.requires_grad)
    if tracked or update.dtype != torch.promote_types(x.dtype, update.dtype):
        return x + update
    return update.add_(x)


def native_bf16(device: torch.device | str) -> bool:
    """Whether `device` multiplies bfloat16 natively: a CUDA GPU with bf16, or a CPU with
    AVX512-BF16 or AMX. Elsewhere (e.g. AVX2-only CPUs) bf16 matmuls are emulated, ~10-20x
    slower than fp32, so rollouts never try bf16 there."""
    device = torch.device(device)
    if device.type == "cuda":
        return torch.cuda.is_available() and torch.cuda.is_bf16_supported()
    if device.type == "cpu":
        return bool(torch.cpu._is_avx512_bf16_supported() or torch.cpu._is_amx_tile_supported())
    return False


def precision_context(precision: Precision, device: torch.device) -> AbstractContextManager[Any]:
    """Where a network's forward runs: under bf16 autocast when `precision` resolves to bf16
    on `device` (see resolve_precision), otherwise as it is. Shared by the GNS and CConv."""
    if resolve_precision(precision, device) == "bf16":
        return torch.autocast(device.type, dtype=torch.bfloat16)
    return nullcontext()


def resolve_precision(precision: Precision, device: torch.device | str) -> Precision:
    """ "fp32" or "bf16": what the network runs in. "auto" is fp32 (the paper's): bf16 was
    measured both faster and slower than fp32 depending on the model's size and the CPU
    (issue 22), so only a rollout that times both for its model switches to it."""
    if precision == "auto":
        return "fp32"
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"precision must be 'auto', 'fp32' or 'bf16', got {precision!r}")
    return precision


class EncodeProcessDecode(nn.Module):
    """The GNS graph network.

    node_input_size, edge_input_size: feature widths (from the scene, see simulator.py).
    global_input_size: width of the global features when config.global_latent (0: the global
        latent starts from a learned vector).
    output_size: D, the acceleration's dimension.

    How it runs (the function and the parameters are the same either way) comes from the
    config and may be changed on the module: `implementation` ("fast" or "plain"),
    `precision` ("auto", "fp32", "bf16": the output is at least float32 either way) and
    `torch_compile` (torch.compile the fast path; falls back to eager with a warning).
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
        self.implementation: Implementation = config.implementation
        self.precision: Precision = config.precision
        self.torch_compile = config.torch_compile
        self._compiled: Callable[..., Tensor] | None = None
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
        edge_mask: Tensor | None = None,
    ) -> Tensor:
        """node_features (N, node_input_size), edge_features (E, edge_input_size), senders and
        receivers (E,) int64; with a global latent also n_node (G,) (default: one graph) and
        global_features (G, global_input_size). Returns (N, output_size), at least float32.

        edge_mask (E,) float, 1 for a real edge and 0 for a padding edge (static-capacity edge
        lists, gns.simulator.pad_edges): a padding edge's message is zeroed before any sum, so
        no node's result depends on it (its own edge latent is computed and never read)."""
        if self.implementation not in IMPLEMENTATIONS:
            raise ValueError(
                f"implementation must be 'fast' or 'plain', got {self.implementation!r}"
            )
        device = node_features.device
        node_graph, num_graphs = None, 0
        if self.config.global_latent:
            n = node_features.shape[0]
            if n_node is None:
                n_node = torch.tensor([n], device=device)
            n_node = n_node.to(device)
            num_graphs = n_node.shape[0]
            node_graph = torch.repeat_interleave(
                torch.arange(n_node.shape[0], device=device), n_node, output_size=n
            )
            if self.global_encoder is not None and global_features is None:
                raise ValueError("this model was built with global features; pass them")
        elif global_features is not None:
            raise ValueError("this model has no global input; append global features to nodes")
        args = (
            node_features,
            edge_features,
            senders,
            receivers,
            global_features,
            node_graph,
            edge_mask,
        )
        with precision_context(self.precision, device):
            if self.implementation == "fast" and self.torch_compile:
                out = self._run_compiled(*args, num_graphs)
            else:
                out = self._encode_process_decode(*args, num_graphs, self.implementation)
        return at_least_fp32(out)

    def _encode_process_decode(
        self,
        node_features: Tensor,
        edge_features: Tensor,
        senders: Tensor,
        receivers: Tensor,
        global_features: Tensor | None,
        node_graph: Tensor | None,
        edge_mask: Tensor | None,
        num_graphs: int,
        implementation: Implementation = "fast",
    ) -> Tensor:
        """forward's body: node_graph (N,) the graph of each node and num_graphs G when
        there is a global latent; edge_mask as forward's."""
        # Encoders and decoder run as modules on either path (hooks on them keep working);
        # they are a small share of the work, and the fast path's savings are in the processor.
        nodes = self.node_encoder(node_features)
        edges = self.edge_encoder(edge_features)
        globals_ = None
        if node_graph is not None:
            if self.global_encoder is not None:
                assert global_features is not None
                globals_ = self.global_encoder(global_features)
            else:
                assert self.initial_global is not None
                globals_ = self.initial_global.expand(num_graphs, -1)
        if implementation == "fast":
            # The residual streams in at least float32 under bf16 autocast (see _run_mlp; the
            # encoders' LayerNorms round to bf16 once).
            nodes, edges = at_least_fp32(nodes), at_least_fp32(edges)
            globals_ = None if globals_ is None else at_least_fp32(globals_)
        for step in self.processor:
            nodes, edges, globals_ = step(
                nodes, edges, senders, receivers, globals_, node_graph,
                implementation=implementation, edge_mask=edge_mask,
            )  # fmt: skip
        return self.decoder(nodes)

    def _run_compiled(self, *args: Any) -> Tensor:
        """The fast path through torch.compile (dynamic shapes: E changes every step); on any
        failure (no C++ compiler, an unsupported op) warn once and stay eager."""
        if self._compiled is None:
            self._compiled = torch.compile(self._encode_process_decode, dynamic=True)
        try:
            return self._compiled(*args)
        except Exception as err:  # noqa: BLE001 - any compiler failure means "run eager"
            warnings.warn(
                f"torch.compile of the GNS failed ({type(err).__name__}: {err}); running the "
                "fast path eagerly",
                RuntimeWarning,
                stacklevel=3,
            )
            self.torch_compile = False
            return self._encode_process_decode(*args)
