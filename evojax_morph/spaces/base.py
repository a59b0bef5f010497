"""What every morphology space provides, and the machinery they share."""

from __future__ import annotations

import abc
import functools
import json
from collections.abc import Callable
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from evojax_morph.morphology import Morphology, canonical, format_tree
from evojax_morph.physics import mjcf, templates
from evojax_morph.physics.templates import mjx


class SizeClass(NamedTuple):
    """The bodies of a space that a smaller template holds (`Space.size_classes`).

    space: the same space on the smaller template (same morphologies, mutations and nodes).
    limbs: (L_c,) int: the slot in the full template of each limb slot of the smaller one, so
      that a controller keeps the full template's observation and action layout
      (`Locomotion(..., limbs=)`).
    fits(m) -> () bool, jittable: whether `m` fits the smaller template.
    """

    name: str
    space: Space
    limbs: np.ndarray
    fits: Callable[[Morphology], jax.Array]


def _on_host(fn: Callable, *args):
    """`fn(*args)`, `fn` jitted and `args` concrete, as numpy arrays: compiled once (then
    cached by JAX) and run on the CPU where JAX has one, else on the default device. A compiled
    program's call runs even inside a trace, where the jitted function's would join the trace
    (or, under `jax.ensure_compile_time_eval`, run op by op)."""
    args = jax.tree.map(np.asarray, args)
    try:
        device = jax.local_devices(backend="cpu")[0]
    except RuntimeError:  # JAX_PLATFORMS without the CPU
        device = None
    with jax.default_device(device):
        return jax.tree.map(np.asarray, fn.lower(*args).compile()(*args))


class Space(abc.ABC):
    """A morphology search space: its initial body, its mutations and its physics.

    State: a `Morphology` of `max_nodes` slots.
    Action: `(node, mutation)` with `node < max_nodes` and `mutation < num_mutations`; valid
      actions are those of `action_mask(m)`. `mutate` is pure and jittable; a masked action is a
      no-op inside jit and a `ValueError` when called eagerly from Python.
    Physics: `template` is the padded `mujoco.MjModel` holding every slot; `mjx_model(m)` is that
      template specialised to `m` in JAX; `to_mjcf(m)` is the standalone, unpadded MJCF of `m`.
    """

    name: ClassVar[str]
    kind_names: ClassVar[tuple[str, ...]]
    site_names: ClassVar[tuple[str, ...]]
    mutation_names: ClassVar[tuple[str, ...]]
    attr_names: ClassVar[tuple[str, ...]]
    fitness_scale: ClassVar[float] = 1.0  # typical magnitude of the predefined fitness
    max_nodes: int
    default_horizon: int  # mutations per episode of the evolution MDP when none is asked for

    # --- a run's defaults on a GPU (mujoco_playground's `default_config`) -------------------

    @classmethod
    def gpu_defaults(cls) -> dict:
        """The settings (`RunConfig` fields) a run of this space takes on a GPU, where the
        same command evaluates a larger batch with a longer PPO budget; the controllers per
        body come from `gpu_controllers`, the agents' settings from these (`run.cli`)."""
        return {
            "num_envs": 256,
            "train_steps": 50_000,
            "steps": 100,
            "chunk": 10,
            "checkpoint_every": 2,
            "confirm": 8,
            "confirm_controllers": 32,
        }

    @classmethod
    def gpu_controllers(cls, engine) -> int:
        """Controllers per body on a GPU for a fitness stepping on `engine` (an `Engine`): the
        engine's own (`Engine.gpu_controllers`), which spend its speed on less noise."""
        return engine.gpu_controllers

    # --- what a space defines -------------------------------------------------------------

    @abc.abstractmethod
    def initial(self) -> Morphology:
        """m0, the morphology every evolution starts from."""

    @abc.abstractmethod
    def action_mask(self, m: Morphology) -> jax.Array:
        """(max_nodes, num_mutations) bool: the mutations allowed on each node of `m`."""

    @abc.abstractmethod
    def _apply(self, m: Morphology, node: jax.Array, mutation: jax.Array) -> Morphology:
        """`m` after a mutation known to be valid."""

    @abc.abstractmethod
    def predefined_fitness(self, m: Morphology) -> jax.Array:
        """() float32: the space's hand-crafted deterministic fitness."""

    @property
    @abc.abstractmethod
    def plan(self) -> templates.BodyPlan:
        """Static slots of the padded template."""

    @abc.abstractmethod
    def layout(self, m: Morphology) -> templates.Layout:
        """Where the capsules of `m` lie; valid geometry for inactive slots too."""

    # With size classes: each class's share of a batch, then the full template's (a class left
    # out, its template the full one's, gives its share to the full template).
    SHARES: ClassVar[tuple[float, ...]] = (1.0,)

    @property
    def full_share(self) -> float:
        """The full template's share of a batch (`evojax_morph.physics.classes`)."""
        return round(sum(self.SHARES) - sum(share for _, share in self.size_classes()), 6)

    def size_classes(self) -> tuple[tuple[SizeClass, float], ...]:
        """Smaller templates for the smaller bodies, smallest first, each with the share of a
        batch it takes (`evojax_morph.physics.classes`); none by default."""
        return ()

    # --- shared machinery -----------------------------------------------------------------

    @property
    def num_mutations(self) -> int:
        return len(self.mutation_names)

    @property
    def num_actions(self) -> int:
        return self.max_nodes * self.num_mutations

    def mutate(self, m: Morphology, node, mutation) -> Morphology:
        """Applies `mutation` to `node`; pure, jittable and vmappable.

        Inside jit an out-of-range or masked action leaves `m` unchanged. Called eagerly with
        concrete values, it raises `ValueError` for such an action instead.
        """
        concrete = not any(
            isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((m, node, mutation))
        )
        if concrete:
            self._check_action(m, node, mutation)
        node = jnp.asarray(node, jnp.int32)
        mutation = jnp.asarray(mutation, jnp.int32)
        in_range = (
            (node >= 0)
            & (node < self.max_nodes)
            & (mutation >= 0)
            & (mutation < self.num_mutations)
        )
        node_c = jnp.clip(node, 0, self.max_nodes - 1)
        mutation_c = jnp.clip(mutation, 0, self.num_mutations - 1)
        valid = in_range & self.action_mask(m)[node_c, mutation_c]
        new = self._apply(m, node_c, mutation_c)
        return jax.tree.map(lambda a, b: jnp.where(valid, a, b), new, m)

    def _check_action(self, m: Morphology, node, mutation) -> None:
        if m.active.ndim != 1:
            raise ValueError("mutate takes one morphology; use jax.vmap(space.mutate) for a batch")
        node, mutation = np.asarray(node), np.asarray(mutation)
        if node.ndim or mutation.ndim:
            raise ValueError("mutate takes one node and one mutation; vmap it for batches")
        if not 0 <= node < self.max_nodes:
            raise ValueError(f"node {int(node)} is outside 0..{self.max_nodes - 1} of {self.name}")
        if not 0 <= mutation < self.num_mutations:
            raise ValueError(
                f"mutation {int(mutation)} is outside 0..{self.num_mutations - 1} of {self.name} "
                f"({', '.join(self.mutation_names)})"
            )
        if not bool(self.action_mask(m)[node, mutation]):
            raise ValueError(
                f"mutation {self.mutation_names[mutation]!r} is not allowed on node {int(node)} "
                f"of this {self.name} morphology (see space.action_mask)"
            )

    def random_mutation(self, key: jax.Array, m: Morphology) -> Morphology:
        """`m` after one valid mutation, drawn uniformly over the valid actions."""
        mask = self.action_mask(m).reshape(-1)
        action = jax.random.categorical(key, jnp.where(mask, 0.0, -jnp.inf))
        return self.mutate(m, action // self.num_mutations, action % self.num_mutations)

    def random_morphology(self, key: jax.Array, num_mutations: int) -> Morphology:
        """A random walk of `num_mutations` valid mutations from m0, uniform over valid actions."""
        step = lambda m, key: (self.random_mutation(key, m), None)  # noqa: E731
        m, _ = jax.lax.scan(step, self.initial(), jax.random.split(key, num_mutations))
        return m

    def canonical(self, m: Morphology) -> str:
        """A name for the shape of `m`, equal for bodies that differ only in slot numbers and
        sibling order: its tree of (kind, site, attributes) (`morphology.canonical`)."""
        return canonical(m)

    def enumerate_bodies(self, max_depth: int | None = None) -> tuple[list[Morphology], list[int]]:
        """Every distinct body (by `canonical`) within `max_depth` mutations of m0, breadth first.

        Args:
          max_depth: mutations from m0 to follow; None: until no new body appears.
        Returns:
          (bodies, depths): m0 first, each body at the fewest mutations that reach it.
        """
        mutate, action_mask = jax.jit(self.mutate), jax.jit(self.action_mask)
        m0 = jax.device_get(self.initial())
        seen, bodies, depths, frontier, depth = {self.canonical(m0)}, [m0], [0], [m0], 0
        while frontier and (max_depth is None or depth < max_depth):
            depth += 1
            new = []
            for m in frontier:
                for node, mutation in zip(*np.nonzero(np.asarray(action_mask(m)))):
                    child = jax.device_get(mutate(m, node, mutation))
                    key = self.canonical(child)
                    if key not in seen:
                        seen.add(key)
                        new.append(child)
            bodies += new
            depths += [depth] * len(new)
            frontier = new
        return bodies, depths

    def format(self, m: Morphology) -> str:
        """The active tree of `m`, one limb a line."""
        return format_tree(m, self.kind_names, self.site_names, self.attr_names)

    def to_json(self, m: Morphology) -> str:
        return json.dumps({"space": self.name, **m.to_dict()}, indent=1)

    def from_json(self, text: str) -> Morphology:
        d = json.loads(text)
        if d.get("space") != self.name:
            raise ValueError(f"this morphology is of space {d.get('space')!r}, not {self.name!r}")
        if d["max_nodes"] != self.max_nodes or d["num_attrs"] != len(self.attr_names):
            raise ValueError(
                f"capacity {d['max_nodes']} x {d['num_attrs']} attrs does not match {self.name}'s "
                f"{self.max_nodes} x {len(self.attr_names)}"
            )
        return Morphology.from_dict(d)

    # --- physics --------------------------------------------------------------------------

    @functools.cached_property
    def template(self) -> mujoco.MjModel:
        """The padded MuJoCo model holding every slot of the space: m0's layout with every
        slot on. Two compiled programs on the host (`host_layout`), also when first asked for
        inside a trace; op by op, m0 and its layout would be 50 to 134 programs, each
        compiled on its first use, on the accelerator."""
        full = self.host_layout(_on_host(jax.jit(self.initial)))
        full = full.replace(limb_active=np.ones_like(full.limb_active),
                            geom_active=np.ones_like(full.geom_active))
        return mjcf.compile_template(self.plan, full, f"{self.name}_template")

    @functools.cached_property
    def _index(self) -> templates.TemplateIndex:
        return templates.TemplateIndex.build(self.plan, self.template)

    def mjx_template(self) -> mjx.Model:
        """`template` on this process's first device, in float64 when jax_enable_x64 is on.

        A fixed local device, not the default: first built inside a trace whose outputs span
        several hosts, the default would give arrays no single process may close over."""
        return self._mjx_template(bool(jax.config.jax_enable_x64))

    @functools.lru_cache(maxsize=2)  # noqa: B019  (spaces live as long as the process)
    def _mjx_template(self, x64: bool) -> mjx.Model:
        del x64  # only a cache key: put_model picks the dtype from the flag
        with jax.ensure_compile_time_eval():
            return mjx.put_model(self.template, device=jax.local_devices()[0])

    def mjx_model(self, m: Morphology) -> mjx.Model:
        """The template specialised to `m`: jit and vmap over `m` compile once for all bodies."""
        return templates.specialise(self.mjx_template(), self.plan, self._index, self.layout(m))

    def to_mjcf(self, m: Morphology) -> str:
        """A standalone MJCF of `m` alone, without padding, named as in the template."""
        if m.active.ndim != 1:
            raise ValueError("to_mjcf takes one morphology, not a batch")
        return mjcf.write_mjcf(self.plan, self.host_layout(m), self.name, padded=False)

    def host_layout(self, m: Morphology) -> templates.Layout:
        """`layout` of one body (concrete) as numpy arrays, for the host (MJCF, drawings, the
        template): one compiled call (`_on_host`). Run eagerly it would be hundreds of small
        ops, each compiled on its first use, on the accelerator (seconds a run on a GPU)."""
        return _on_host(self._host_layout, m)

    @functools.cached_property
    def _host_layout(self) -> Callable:
        return jax.jit(self.layout)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(max_nodes={self.max_nodes})"
