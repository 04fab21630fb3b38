"""Encode-process-decode graph network (Sanchez-Gonzalez et al. 2020) built on torch-geometric message passing.

Encoder: MLPs lift node and edge features to a latent size. Processor: `message_passing_steps` interaction layers
with unshared weights; each updates every edge from its own latent and its two endpoints, then every node from its
latent and the sum of its incoming edges, both as residuals. Decoder: an MLP from node latents to the output
(per-vertex normalised acceleration). Every MLP has `hidden_layers` ReLU layers of the latent size; all but the
decoder end in a LayerNorm, as in the reference implementation.
"""

from __future__ import annotations

import torch
from torch import nn
from torch_geometric.nn import MessagePassing


def mlp(input_size: int, hidden_size: int, output_size: int, hidden_layers: int, layer_norm: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    size = input_size
    for _ in range(hidden_layers):
        layers += [nn.Linear(size, hidden_size), nn.ReLU()]
        size = hidden_size
    layers.append(nn.Linear(size, output_size))
    if layer_norm:
        layers.append(nn.LayerNorm(output_size))
    return nn.Sequential(*layers)


class InteractionLayer(MessagePassing):
    """One message-passing step on latent node and edge features; edge_index rows are (sender, receiver).

    The edge MLP reads [edge, sender, receiver]; its first linear layer is split into one part per input, so the
    sender and receiver parts are applied once per node and then gathered, instead of once per edge on a
    concatenation: the same function with a third of that layer's work, edges outnumbering nodes about 4 to 1.
    """

    def __init__(self, latent_size: int, hidden_layers: int):
        super().__init__(aggr="sum")
        if hidden_layers < 1:
            raise ValueError(f"the edge and node MLPs need at least one hidden layer, got {hidden_layers}")
        self.edge_input = nn.Linear(latent_size, latent_size)
        self.sender_input = nn.Linear(latent_size, latent_size, bias=False)
        self.receiver_input = nn.Linear(latent_size, latent_size, bias=False)
        self.edge_mlp = nn.Sequential(
            nn.ReLU(), mlp(latent_size, latent_size, latent_size, hidden_layers - 1, layer_norm=True)
        )
        self.node_mlp = mlp(2 * latent_size, latent_size, latent_size, hidden_layers, layer_norm=True)

    def forward(
        self, nodes: torch.Tensor, edge_index: torch.Tensor, edges: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        size = (nodes.shape[0], nodes.shape[0])
        edge_updates = self.edge_updater(
            edge_index, senders=self.sender_input(nodes), receivers=self.receiver_input(nodes), edges=edges, size=size
        )
        incoming = self.propagate(edge_index, edges=edge_updates, size=size)
        node_updates = self.node_mlp(torch.cat([nodes, incoming], dim=-1))
        return nodes + node_updates, edges + edge_updates

    def edge_update(self, senders_j: torch.Tensor, receivers_i: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
        return self.edge_mlp(self.edge_input(edges) + senders_j + receivers_i)

    def message(self, edges: torch.Tensor) -> torch.Tensor:
        return edges


class EncodeProcessDecode(nn.Module):
    """Node features [n, Fn], edge index [2, E], edge features [E, Fe] -> per-node outputs [n, output_size]."""

    def __init__(
        self,
        node_input_size: int,
        edge_input_size: int,
        output_size: int,
        latent_size: int = 128,
        message_passing_steps: int = 10,
        hidden_layers: int = 2,
    ):
        super().__init__()
        self.node_encoder = mlp(node_input_size, latent_size, latent_size, hidden_layers, layer_norm=True)
        self.edge_encoder = mlp(edge_input_size, latent_size, latent_size, hidden_layers, layer_norm=True)
        self.processor = nn.ModuleList(
            InteractionLayer(latent_size, hidden_layers) for _ in range(message_passing_steps)
        )
        self.decoder = mlp(latent_size, latent_size, output_size, hidden_layers, layer_norm=False)

    def forward(
        self, node_features: torch.Tensor, edge_index: torch.Tensor, edge_features: torch.Tensor
    ) -> torch.Tensor:
        nodes = self.node_encoder(node_features)
        edges = self.edge_encoder(edge_features)
        for layer in self.processor:
            nodes, edges = layer(nodes, edge_index, edges)
        return self.decoder(nodes)
