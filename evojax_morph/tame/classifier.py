"""TAME's classifier q(a | s_T, m): which primitive drove each motor, from where the body ended.

A `gnn.TreeGNN` over the morphology tree (so it can score bodies it never saw), fed each node's
morphology features and final state, with one logit per primitive and node.
"""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp

from evojax_morph.agents.gnn import TreeGNN, node_features
from evojax_morph.morphology import Morphology

STATE_SIZE = 4  # per node: dx, dz, cos(pitch), sin(pitch)


class Classifier(nn.Module):
    """q(a | s_T, m): per-node logits over the primitives, from the tree and its final state."""

    num_kinds: int
    num_sites: int
    num_primitives: int
    hidden: int = 64
    layers: int = 3

    @nn.compact
    def __call__(self, m: Morphology, states: jax.Array) -> jax.Array:
        """(N, num_primitives) logits from one body and its (N, STATE_SIZE) final states."""
        feats = node_features(m, jnp.zeros(()), self.num_kinds, self.num_sites)
        nodes = jnp.concatenate([feats, states * m.active[:, None]], -1)
        gnn = TreeGNN(self.hidden, self.layers, self.num_primitives, head=(self.hidden,))
        return gnn(m, nodes)[0]


def node_log_likelihood(classifier: Classifier, params, m: Morphology, states, labels, labelled):
    """log q(a_j | s_T, m) summed over the labelled nodes of one rollout, and the count right.

    Args:
      states: (N, STATE_SIZE) final state per node.
      labels: (N,) int32: the primitive that drove each node's motor.
      labelled: (N,) bool: the node has an active motor.
    Returns:
      () log-likelihood and () number of labelled nodes the argmax gets right.
    """
    logits = classifier.apply(params, m, states)  # (N, K)
    logp = jnp.take_along_axis(jax.nn.log_softmax(logits), labels[:, None], -1)[:, 0]
    right = jnp.argmax(logits, -1) == labels
    return jnp.sum(logp * labelled), jnp.sum(right * labelled)


def log_likelihood(classifier: Classifier, params, m: Morphology, r):
    """(E,) sum over labelled nodes of log q(a_j | s_T, m), and (E,) fraction of them right,
    for the E rollouts `r` (a `Rollouts`) of one body."""
    loglik, right = jax.vmap(
        lambda s, a: node_log_likelihood(classifier, params, m, s, a, r.labelled)
    )(r.states, r.labels)
    return loglik, right / jnp.maximum(r.labelled.sum(), 1)
