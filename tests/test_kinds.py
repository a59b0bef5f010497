"""Kinds know their rules: no module of the library compares a registered kind's name outside
that kind's own module and its registry (the run asks the kind instead, issue 64)."""

import ast
from pathlib import Path

import evojax_morph as em
from evojax_morph import agents
from evojax_morph.physics import engines

PACKAGE = Path(em.__file__).parent
# Where each kind's names may be compared: its own modules and its registry.
HOMES = {
    "space": (em.list_spaces(), ("spaces/",)),
    "fitness": (em.list_fitnesses(), ("fitnesses/",)),
    "agent": (agents.list_agents(), ("agents/",)),
    "engine": (engines.list_engines(), ("physics/engines.py", "physics/warp.py")),
}


def _strings(node: ast.AST) -> set[str]:
    """The string constants of a compared value, a tuple, list or set of them included."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return {node.value}
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return set().union(*(_strings(e) for e in node.elts)) if node.elts else set()
    return set()


def test_no_kind_name_is_compared_outside_its_home():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        where = path.relative_to(PACKAGE).as_posix()
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.Compare):
                continue
            compared = set().union(*(_strings(side) for side in [node.left, *node.comparators]))
            for kind, (names, homes) in HOMES.items():
                if compared & set(names) and not where.startswith(homes):
                    found.append(f"{where}:{node.lineno}: {kind} {ast.unparse(node)}")
    assert not found, "\n".join(found)


def test_the_check_sees_a_compare():
    """The scan finds what it looks for (a compare of the kind the run used to make)."""
    tree = ast.parse('if cfg.physics == "warp" or space in ("constructor",): pass')
    compares = [n for n in ast.walk(tree) if isinstance(n, ast.Compare)]
    assert [_strings(c.comparators[0]) for c in compares] == [{"warp"}, {"constructor"}]


def test_every_sort_of_kind_has_one_registry():
    """Spaces, fitnesses, agents, engines and tasks are registered the same way
    (`registry.Registry`): an unknown name's error names the sort and the known ones, `list`
    keeps each sort's order, and a kind registered later is got back and listed."""
    from evojax_morph import spaces, tasks
    from evojax_morph.fitnesses import base as fitnesses
    from evojax_morph.registry import Registry

    found = {"space": spaces._REGISTRY, "fitness": fitnesses._REGISTRY,
             "agent": agents._REGISTRY, "physics": engines._REGISTRY, "task": tasks.TASKS}
    listed = {"space": em.list_spaces(), "fitness": em.list_fitnesses(),
              "agent": agents.list_agents(), "physics": engines.list_engines(),
              "task": em.list_tasks()}
    for what, registry in found.items():
        assert isinstance(registry, Registry) and registry.list() == listed[what]
        try:
            registry.get("nope")
        except ValueError as e:
            assert str(e) == (f"unknown {what} 'nope'; known {registry.plural}: "
                              f"{', '.join(listed[what])}")
        else:
            raise AssertionError(f"{what}: an unknown name got back")
    assert em.list_spaces() == sorted(em.list_spaces())  # sorted; agents as registered
    assert agents.list_agents()[:2] == ["ddqn", "dqn"]
    mine = Registry("thing", sort=True)
    mine.register(tasks.TaskConfig(name="b"), tasks.TaskConfig(name="a"))
    assert mine.list() == ["a", "b"] and mine.get("b").name == "b" and "a" in mine
