"""Size classes: a batch of bodies trained on a few templates by size, not one padded template.

Every body of a space steps through its padded template, so every slot costs physics time on
every body, used or not. A space may offer smaller templates (`Space.size_classes`), each with the
share of a batch it takes. `grouped` splits a batch by class inside one compiled program:

1. each body's class is the smallest that holds it (`SizeClass.fits`);
2. class c takes up to `capacity` bodies (a static number: ceil(share x B)), smallest class
   first; a body whose class is full moves to the next larger one, and the full template takes
   the rest up to its own capacity; a class's unused places train m0;
3. each class trains its bodies on its template, and the results go back in batch order.

The capacities are static so that no mix of sizes compiles anything new. A batch whose mix does
not fit them (more large bodies than the shares allow) trains whole on the full template
instead (`jax.lax.cond`: one branch runs), so every batch is trained, and the classes only save
time. Controllers keep the full template's observation and action layout on every template
(`Locomotion(limbs=)`), so a child inherits its parent's controller slot by slot whichever
template either runs on.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import jax
import jax.numpy as jnp

from evojax_morph.physics.templates import SpaceLike


def capacities(shares: tuple[float, ...], batch: int) -> list[int]:
    """Places of each class in a batch of `batch` bodies (the last: the full template)."""
    return [min(batch, math.ceil(share * batch)) for share in shares]


def assign(need: jax.Array, caps: list[int]) -> tuple[list[jax.Array], jax.Array]:
    """Which bodies each class trains: `need` (B,) the smallest class holding each body;
    returns (one (cap,) index array per class, B marking an unused place; whether every body
    has a place)."""
    batch = need.shape[0]
    placed = jnp.zeros(batch, bool)
    places = []
    for c, cap in enumerate(caps):
        here = jnp.nonzero(~placed & (need <= c), size=cap, fill_value=batch)[0]
        placed = placed.at[here].set(True, mode="drop")
        places.append(here)
    return places, placed.all()


def places(space: SpaceLike, morphs) -> tuple[jax.Array, list[jax.Array], jax.Array]:
    """A batch of `space`'s bodies by size class: (need (B,), the smallest class holding each
    body, the last index the full template; the places of each class and whether every body
    has one, as `assign` gives them for the space's shares)."""
    batch = morphs.active.shape[0]
    classes = space.size_classes()
    fits = [jax.vmap(c.fits)(morphs) for c, _ in classes] + [jnp.ones(batch, bool)]
    need = jnp.argmax(jnp.stack(fits), axis=0)  # the first (smallest) class that fits
    shares = tuple(share for _, share in classes) + (space.full_share,)
    return need, *assign(need, capacities(shares, batch))


def grouped(space: SpaceLike, train: Callable, class_trains: list[Callable]) -> Callable:
    """`train(keys, morphs, params)` (the full template's, results of (B, ...) arrays) run per
    size class: `class_trains[c]` trains on class c's template (`space.size_classes()[c]`)."""
    trains = list(class_trains) + [train]

    def run(keys, morphs, params):
        batch = keys.shape[0]
        _, where, all_placed = places(space, morphs)
        m0 = space.initial()

        def by_class(keys, morphs, params):
            out = None
            for here, class_train in zip(where, trains):
                result = class_train(_take(keys, here, batch), _take(morphs, here, batch, m0),
                                     _take(params, here, batch))
                out = _put(out, here, result, batch)
            return out

        return jax.lax.cond(all_placed, by_class, train, keys, morphs, params)

    return run


def _take(tree, here: jax.Array, batch: int, fill=None):
    """The rows of a batch of `batch` at places `here`; at unused places (`here` = batch) the
    last row, or `fill` (one row, e.g. m0) where given."""
    at = jnp.minimum(here, batch - 1)
    if fill is None:
        return jax.tree.map(lambda x: x[at], tree)
    used = here < batch
    return jax.tree.map(
        lambda x, x0: jnp.where(used.reshape((-1,) + (1,) * x0.ndim), x[at], x0), tree, fill)


def _put(out, here: jax.Array, result, batch: int):
    """`result` (one row per place) written into `out` (B rows; zeros if None) at `here`."""
    if out is None:
        out = jax.tree.map(lambda x: jnp.zeros((batch,) + x.shape[1:], x.dtype), result)
    return jax.tree.map(lambda o, r: o.at[here].set(r, mode="drop"), out, result)
