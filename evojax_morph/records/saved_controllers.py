"""Trained controllers kept with their bodies, so that a gait can be replayed without retraining.

A run directory keeps one under `controllers/NAME/` for the best body found (`best`) and for
each body of the greedy trajectory (`step0` = m0, `step1`, ...): an Orbax checkpoint of the
controller (the PPO `Params`, all K controllers of `PPOConfig.controllers` along a leading
axis) with JSON metadata: the space, the fitness config that rebuilds the networks, the run's
seed, the body and its fitness. Orbax writes to a temporary directory and renames it, so a
crash leaves no half-written controller behind. The metadata keeps the SHA-256 of each array of
the controller and of itself (`checkpoints.digests`, `checkpoints.seal`): `load` checks them and
that the controller is finite, so a damaged one is an error, never a replay of damaged weights.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import jax

from evojax_morph import ppo
from evojax_morph.fitnesses import FitnessConfig, get_fitness
from evojax_morph.morphology import Morphology
from evojax_morph.records.checkpoints import check, digests, read_error, seal, unseal
from evojax_morph.spaces import Space, make_space

DIR = "controllers"


@dataclasses.dataclass(frozen=True)
class SavedController:
    """A body, the controller trained on it, and what rebuilds the networks.

    Attributes:
      space: the space the body belongs to
      fitness: kind "ppo": its task and PPO settings
      seed: the run's seed
      morph: one body
      params: with K > 1 controllers, a leading (K,) axis
      value: the body's fitness in the run
      label: which body of the run: "best", "step 3"
    """

    space: Space
    fitness: FitnessConfig
    seed: int
    morph: Morphology
    params: ppo.Params
    value: float
    label: str


def has_controllers(cfg: FitnessConfig) -> bool:
    """Whether a fitness of `cfg` trains controllers worth keeping (its kind says so)."""
    return get_fitness(cfg.kind).trains_controllers


def _checkpointer():
    import orbax.checkpoint as ocp

    return ocp, ocp.Checkpointer(ocp.CompositeCheckpointHandler())


def save(path: Path, saved: SavedController) -> None:
    """Writes `saved` to the directory `path` (replaced if it exists); every process of a
    multi-process run calls it, Orbax writes once."""
    meta = {
        "space": saved.space.name,
        "fitness": saved.fitness.to_dict(),
        "seed": saved.seed,
        "morphology": saved.morph.to_dict(),
        "value": saved.value,
        "label": saved.label,
        "params": digests(jax.device_get(saved.params)),
    }
    ocp, ckptr = _checkpointer()
    with ckptr:
        args = ocp.args.Composite(
            params=ocp.args.StandardSave(saved.params), meta=ocp.args.JsonSave(seal(meta))
        )
        ckptr.save(Path(path).resolve(), args=args, force=True)


def load(path: Path) -> SavedController:
    """The controller saved in `path` by `save`, its networks rebuilt from the saved config.

    Raises:
      checkpoints.Damaged: a file does not read, a digest is missing or does not match, or the
        controller holds non-finite values.
    """
    path = Path(path).resolve()
    ocp, ckptr = _checkpointer()
    name = f"saved controller {path}"
    with ckptr:
        with read_error(name):
            meta = ckptr.restore(path, args=ocp.args.Composite(meta=ocp.args.JsonRestore()))
            meta = unseal(meta["meta"], "metadata")
        space = make_space(meta["space"])
        fitness = FitnessConfig.from_dict(meta["fitness"])
        init, _ = ppo.make_train(space, fitness.task, fitness.ppo)
        # Placed on this process's first device: a controller saved on a GPU reads on a CPU
        # (without a placement, Orbax restores to the saving device, "cuda:0").
        here = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=here),
                                jax.eval_shape(init, jax.random.PRNGKey(0)))
        restore = ocp.args.Composite(params=ocp.args.StandardRestore(abstract))
        with read_error(name):
            params = ckptr.restore(path, args=restore)["params"]
            check(jax.device_get(params), meta.get("params"))
    morph = space.from_json(space.to_json(Morphology.from_dict(meta["morphology"])))
    return SavedController(space, fitness, int(meta["seed"]), morph, params,
                           float(meta["value"]), meta["label"])


def step_dirs(run_dir: Path) -> dict[int, Path]:
    """The saved bodies of the greedy trajectory, by step (0: m0)."""
    found = {}
    for d in (Path(run_dir) / DIR).glob("step*"):
        m = re.fullmatch(r"step(\d+)", d.name)
        if m and d.is_dir():
            found[int(m.group(1))] = d
    return dict(sorted(found.items()))


def body_dir(run_dir: Path, body: str) -> Path:
    """The directory of a saved body: `body` is "best", "final" (the last body of the greedy
    trajectory) or "step N" (its N-th body, 0 for m0).

    Raises:
      ValueError: `body` names no body; FileNotFoundError: the run saved no such controller.
    """
    run_dir = Path(run_dir)
    words = body.split()
    steps = step_dirs(run_dir)
    if words == ["best"]:
        path = run_dir / DIR / "best"
    elif words == ["final"]:
        if not steps:
            raise FileNotFoundError(f"{run_dir} holds no greedy trajectory (a baseline agent's "
                                    "run, or a run without controllers)")
        path = steps[max(steps)]
    elif len(words) == 2 and words[0] == "step" and words[1].isdigit():
        if int(words[1]) not in steps:
            have = ", ".join(map(str, steps)) or "none"
            raise FileNotFoundError(f"{run_dir} has no controller of greedy step {words[1]} "
                                    f"(saved steps: {have})")
        path = steps[int(words[1])]
    else:
        raise ValueError(f"unknown body {body!r}: use best, final or step N")
    if not path.is_dir():
        raise FileNotFoundError(f"no saved controller in {run_dir} (looked for {path}): only runs "
                                "of the ppo fitness save their controllers")
    return path
