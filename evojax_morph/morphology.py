"""A morphology is a fixed-capacity tree of limbs stored as padded arrays.

Node 0 is the root. A node's parent always has a smaller index, so one pass in index order
visits parents before children. Inactive slots hold neutral values (parent -1, zeros) so that
two morphologies with the same bodies compare equal whatever slots they went through.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct


@struct.dataclass
class Morphology:
    """A padded tree of limbs; what each kind, site and attribute means is up to its space.

    Attributes:
      active: (max_nodes,) bool: the slot holds a limb
      parent: (max_nodes,) int32: parent slot, -1 for the root and inactive slots
      kind: (max_nodes,) int32: limb kind (the space's `kind_names`)
      site: (max_nodes,) int32: where on its parent the limb attaches (`site_names`)
      attrs: (max_nodes, num_attrs) float32: continuous attributes, e.g. length
    """

    active: jax.Array  # (max_nodes,) bool
    parent: jax.Array  # (max_nodes,) int32
    kind: jax.Array  # (max_nodes,) int32
    site: jax.Array  # (max_nodes,) int32
    attrs: jax.Array  # (max_nodes, num_attrs) float32

    @property
    def max_nodes(self) -> int:
        return self.active.shape[-1]

    @property
    def num_nodes(self) -> jax.Array:
        """Active limbs, root included: () int32, or (B,) for a batch."""
        return self.active.sum(-1)

    def depth(self) -> jax.Array:
        """(max_nodes,) int32: edges from the root; 0 for the root and inactive slots."""
        depth = jnp.zeros(self.max_nodes, jnp.int32)
        for i in range(1, self.max_nodes):  # parents come first
            parent_depth = depth[jnp.maximum(self.parent[i], 0)] + 1
            depth = depth.at[i].set(jnp.where(self.active[i], parent_depth, 0))
        return depth

    def to_dict(self) -> dict:
        """JSON-ready description: one entry per active node."""
        if self.active.ndim != 1:
            raise ValueError("to_dict takes one morphology, not a batch; index it first")
        nodes = []
        for i in np.flatnonzero(np.asarray(self.active)):
            nodes.append(
                {
                    "id": int(i),
                    "parent": int(self.parent[i]),
                    "kind": int(self.kind[i]),
                    "site": int(self.site[i]),
                    "attrs": [float(a) for a in np.asarray(self.attrs[i])],
                }
            )
        return {"max_nodes": self.max_nodes, "num_attrs": self.attrs.shape[-1], "nodes": nodes}

    @classmethod
    def from_dict(cls, d: dict) -> Morphology:
        n, a = int(d["max_nodes"]), int(d["num_attrs"])
        active = np.zeros(n, bool)
        parent = np.full(n, -1, np.int32)
        kind = np.zeros(n, np.int32)
        site = np.zeros(n, np.int32)
        attrs = np.zeros((n, a), np.float32)
        for node in d["nodes"]:
            i = int(node["id"])
            if not 0 <= i < n:
                raise ValueError(f"node id {i} outside capacity {n}")
            if len(node["attrs"]) != a:
                raise ValueError(f"node {i} has {len(node['attrs'])} attrs, expected {a}")
            active[i], parent[i], kind[i], site[i] = (
                True,
                node["parent"],
                node["kind"],
                node["site"],
            )
            attrs[i] = node["attrs"]
        if not active[0]:
            raise ValueError("a morphology needs its root, node 0")
        for i in range(1, n):
            if active[i] and not (0 <= parent[i] < i and active[parent[i]]):
                raise ValueError(
                    f"node {i} has parent {parent[i]}: parents must be active and earlier"
                )
        return cls(
            active=jnp.asarray(active),
            parent=jnp.asarray(parent),
            kind=jnp.asarray(kind),
            site=jnp.asarray(site),
            attrs=jnp.asarray(attrs),
        )


ATTR_RESOLUTION = 1e-5  # attributes closer than this are one value (canonical uses 6 digits)


def _mix(x: jax.Array) -> jax.Array:
    """MurmurHash3's 32-bit finaliser: a bijection of uint32 that spreads every bit."""
    x = x ^ (x >> 16)
    x = x * jnp.uint32(0x85EBCA6B)
    x = x ^ (x >> 13)
    x = x * jnp.uint32(0xC2B2AE35)
    return x ^ (x >> 16)


def _signature(m: Morphology, seed: jax.Array) -> jax.Array:
    """() uint32 hash of the tree under `seed`, bottom up: a node's hash mixes its (kind, site,
    attributes) with the wrapping sum of its children's mixed hashes, so slot numbers and the
    order of siblings do not count."""
    quantised = jnp.round(m.attrs / ATTR_RESOLUTION).astype(jnp.int32)
    code = _mix(seed ^ m.kind.astype(jnp.uint32))
    code = _mix(code + m.site.astype(jnp.uint32) * jnp.uint32(0x9E3779B9))
    for a in range(m.attrs.shape[-1]):
        code = _mix(code + jax.lax.bitcast_convert_type(quantised[:, a], jnp.uint32))
    acc = jnp.zeros(m.max_nodes, jnp.uint32)  # children's sum, filled before the node is read
    for i in range(m.max_nodes - 1, 0, -1):  # a parent's index is smaller than its child's
        subtree = _mix(code[i] + acc[i])
        add = jnp.where(m.active[i], _mix(subtree ^ jnp.uint32(0x27D4EB2F)), jnp.uint32(0))
        acc = acc.at[jnp.maximum(m.parent[i], 0)].add(add)
    return _mix(code[0] + acc[0])


SEEDS = (0x243F6A88, 0xB7E15162)  # two independent hashes: a 64-bit signature


def signature(m: Morphology) -> jax.Array:
    """(2,) uint32, jittable: a hash of the body's tree of (kind, site, attributes), equal for
    bodies with equal `Space.canonical` names (slot numbers and sibling order ignored;
    attributes to `ATTR_RESOLUTION`). Distinct bodies collide with probability about 2^-64;
    a table checks its own bodies have distinct signatures when it is loaded (`fitnesses.table`)."""
    return jnp.stack([_signature(m, jnp.uint32(s)) for s in SEEDS])


def canonical(m: Morphology) -> str:
    """A name for the shape of `m` (host-side or on a device), equal for bodies that differ only
    in slot numbers and sibling order: its tree of (kind, site, attributes). `signature` is its
    jittable hash."""
    m = jax.device_get(m)

    def name(node: int) -> str:
        children = sorted(
            name(j) for j in range(1, m.max_nodes) if m.active[j] and int(m.parent[j]) == node
        )
        attrs = ",".join(f"{a:.6g}" for a in np.asarray(m.attrs[node], float))
        return f"{int(m.kind[node])}@{int(m.site[node])}[{attrs}](" + " ".join(children) + ")"

    return name(0)


def tree_select(cond: jax.Array, a, b):
    """Per batch element, `a` where `cond` else `b`, for pytrees with a leading (B,) axis."""
    return jax.tree.map(
        lambda x, y: jnp.where(cond.reshape((-1,) + (1,) * (x.ndim - 1)), x, y), a, b
    )


def stack(morphs: Sequence[Morphology]) -> Morphology:
    """Batches morphologies of one space along a new leading axis."""
    if not morphs:
        raise ValueError("stack needs at least one morphology")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *morphs)


def unstack(morphs: Morphology) -> list[Morphology]:
    """Splits a batch made by `stack` back into single morphologies."""
    return [jax.tree.map(lambda x, i=i: x[i], morphs) for i in range(morphs.active.shape[0])]


def format_tree(
    m: Morphology,
    kind_names: Sequence[str],
    site_names: Sequence[str],
    attr_names: Sequence[str] = (),
) -> str:
    """Draws an active tree, one node a line, children indented under their parent."""
    active = np.asarray(m.active)
    parent, kind, site = (np.asarray(x) for x in (m.parent, m.kind, m.site))
    attrs = np.asarray(m.attrs)
    children = {
        i: [j for j in np.flatnonzero(active) if parent[j] == i] for i in range(len(active))
    }

    def label(i: int) -> str:
        text = f"{i}: {kind_names[kind[i]]}"
        if i > 0:
            text += f" @ {site_names[site[i]]}"
        extras = ", ".join(f"{n}={attrs[i, k]:.3g}" for k, n in enumerate(attr_names))
        return text + (f" ({extras})" if extras else "")

    lines = [label(0)]

    def walk(i: int, prefix: str) -> None:
        kids = children[i]
        for k, j in enumerate(kids):
            last = k == len(kids) - 1
            lines.append(prefix + ("└── " if last else "├── ") + label(j))
            walk(j, prefix + ("    " if last else "│   "))

    walk(0, "")
    return "\n".join(lines)
