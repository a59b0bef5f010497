"""A graph network over the morphology tree (jraph), with one output row per node."""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import jraph

from evojax_morph.morphology import Morphology


def node_features(m: Morphology, progress: jax.Array, num_kinds: int, num_sites: int) -> jax.Array:
    """(max_nodes, F): one-hot kind and site, attributes, depth, active flag and progress."""
    n = m.max_nodes
    active = m.active.astype(jnp.float32)[:, None]
    feats = [
        jax.nn.one_hot(m.kind, num_kinds),
        jax.nn.one_hot(m.site, num_sites),
        m.attrs.astype(jnp.float32),
        (m.depth() / n)[:, None],
        active,
        jnp.full((n, 1), progress, jnp.float32),
        (jnp.arange(n) == 0)[:, None].astype(jnp.float32),  # the root
    ]
    return jnp.concatenate(feats, -1) * active


def tree_graphs(m: Morphology, nodes: jax.Array) -> tuple[jraph.GraphsTuple, jraph.GraphsTuple]:
    """The tree as two graphs of fixed size: child-to-parent edges and parent-to-child edges.

    Slot i > 0 has one edge each way; an inactive slot's edges are self loops on itself, and
    its features are zero, so it sends nothing to the active tree.
    """
    n = m.max_nodes
    child = jnp.arange(1, n)
    parent = jnp.where(m.active[1:], m.parent[1:], child)

    def graph(senders, receivers):
        return jraph.GraphsTuple(
            nodes=nodes, edges=None, senders=senders, receivers=receivers, globals=None,
            n_node=jnp.array([n]), n_edge=jnp.array([n - 1]),
        )

    return graph(child, parent), graph(parent, child)


class TreeGNN(nn.Module):
    """Graph convolutions over the tree in both directions, then a shared per-node MLP head.

    Returns (max_nodes, out_size) per-node outputs and a (hidden,) masked mean of the final node
    embeddings over active nodes, for graph-level heads.
    """

    hidden: int = 64
    layers: int = 3
    out_size: int = 1
    head: Sequence[int] = (64,)

    @nn.compact
    def __call__(self, m: Morphology, nodes: jax.Array):
        mask = m.active[:, None].astype(jnp.float32)
        h = nn.relu(nn.Dense(self.hidden)(nodes)) * mask
        for _ in range(self.layers):
            up, down = tree_graphs(m, h)
            conv = lambda: jraph.GraphConvolution(nn.Dense(self.hidden), add_self_edges=False)
            message = conv()(up).nodes + conv()(down).nodes
            h = nn.relu(nn.Dense(self.hidden)(h) + message) * mask
        pooled = jnp.sum(h * mask, 0) / jnp.maximum(mask.sum(), 1.0)
        out = h
        for size in self.head:
            context = jnp.broadcast_to(pooled, (out.shape[0], pooled.shape[-1]))
            out = nn.relu(nn.Dense(size)(jnp.concatenate([out, context], -1)))
        return nn.Dense(self.out_size)(out), pooled
