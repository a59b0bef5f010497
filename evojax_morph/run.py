"""`python -m evojax_morph.run --space NAME`: evolve a morphology with a learning agent.

The evolution loop (agent, batched fitness) is still to come; for now this command checks the
space, builds its padded physics and shows the morphology evolution would start from.
"""

from __future__ import annotations

import argparse
import sys

import evojax_morph as em


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evojax_morph.run", description=__doc__)
    parser.add_argument("--space", required=True, help=f"morphology space: {', '.join(em.list_spaces())}")
    args = parser.parse_args(argv)
    if args.space not in em.list_spaces():
        parser.error(f"unknown space {args.space!r}; known spaces: {', '.join(em.list_spaces())}")
    space = em.make_space(args.space)
    t = space.template
    print(f"space {space.name}: {space.max_nodes} nodes x {space.num_mutations} mutations")
    print(f"padded template: {t.nbody - 1} bodies, {t.ngeom - 1} capsules, {t.nv} dofs, {t.nu} motors")
    print("m0:")
    print(space.format(space.initial()))
    print("not yet: the evolution agent and the PPO fitness are not built yet (see the issues).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
