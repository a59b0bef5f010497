"""The user-facing documents hold together: README.md's shape, every relative link of the README,
CONTRIBUTING.md and the user guide resolving in the repository (a file, and an anchor where one
is named), and every name `evojax_morph` exports on a page of the API reference. Text only, a
second at most; `mkdocs build --strict` (.ci/run) checks the same links as the site resolves
them."""

import dataclasses
import inspect
import re
from pathlib import Path

import evojax_morph as em

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", ROOT / "docs" / "index.md",
        *sorted((ROOT / "docs" / "guide").glob("*.md")),
        *sorted((ROOT / "docs" / "api").glob("*.md"))]
LINK = re.compile(r"!?\[((?:[^\[\]]|\[[^\]]*\])*)\]\(([^()\s]+)\)")
SETUP = [
    'pip install -e . && python -m evojax_morph.run --space bad_walker   # the main job',
    'pip install -e ".[test]" && pytest                                  # the tests (CPU)',
]


def prose(text: str) -> str:
    """`text` without its fenced code blocks (their lines blanked, so line numbers hold)."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith(("```", "~~~")):
            fenced = not fenced
            out.append("")
        else:
            out.append("" if fenced else line)
    return "\n".join(out)


def github_slug(heading: str) -> str:
    """The anchor GitHub gives a heading: its text lower-cased, everything but letters, digits,
    spaces, hyphens and underscores dropped, spaces made hyphens."""
    text = LINK.sub(r"\1", heading).replace("`", "").replace("*", "")
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    found = set()
    for line in prose(path.read_text()).splitlines():
        m = re.match(r"^#{1,6} (.*?)#*\s*$", line)
        if m:
            slug = github_slug(m.group(1))
            n = seen.get(slug, 0)
            seen[slug] = n + 1
            found.add(slug if n == 0 else f"{slug}-{n}")
    return found


def test_readme_is_short_with_its_commands_and_a_picture_at_the_top():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250
    top = lines[:15]
    assert [line for line in top if line.startswith("pip install")] == SETUP
    assert any(line.startswith("![") for line in lines[:40])


def test_every_relative_link_resolves():
    broken = []
    for doc in DOCS:
        for target in (m.group(2) for m in LINK.finditer(prose(doc.read_text()))):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):
                continue  # a URL
            path, _, anchor = target.partition("#")
            dest = (doc.parent / path).resolve() if path else doc
            if not dest.exists():
                broken.append(f"{doc.relative_to(ROOT)}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
                broken.append(f"{doc.relative_to(ROOT)}: {target} (no such heading)")
    assert not broken, "\n".join(broken)


def test_every_exported_name_is_in_the_api_reference():
    shown = set()
    for page in (ROOT / "docs" / "api").glob("*.md"):
        shown |= set(re.findall(r"^::: ([\w.]+)", page.read_text(), flags=re.M))
    lazy = {"GymEvolutionEnv": "evojax_morph.envs.gym_env.GymEvolutionEnv",
            "SB3EvolutionEnv": "evojax_morph.envs.sb3_env.SB3EvolutionEnv"}
    paths = {name: f"{getattr(em, name).__module__}.{getattr(em, name).__qualname__}"
             for name in em.__all__}
    missing = sorted(name for name, path in {**paths, **lazy}.items() if path not in shown)
    assert not missing, f"not on an API page: {missing}"


def undocumented_fields(cls) -> list[str]:
    """The fields of the dataclass or NamedTuple `cls` its docstring's `Attributes:` section
    (Google style, as the API reference renders it) does not name; a field documented only by
    a `#` comment in the source shows as nothing there."""
    fields = ([f.name for f in dataclasses.fields(cls)] if dataclasses.is_dataclass(cls)
              else list(getattr(cls, "_fields", ())))
    doc = inspect.getdoc(cls) or ""
    section = doc.split("\nAttributes:\n", 1)[1] if "\nAttributes:\n" in doc else ""
    named = set(re.findall(r"^  (\w+)(?: \([^)]*\))?:", section, flags=re.M))
    return [f for f in fields if f not in named]


def test_every_field_of_an_exported_class_is_documented():
    """What the quickstart prints and a user reads (FitnessResult's fitness, distance and
    upright; Confirmed's body, ...) is on the API page, for every class `evojax_morph`
    exports."""
    missing = [f"{name}.{field}" for name in em.__all__ if inspect.isclass(getattr(em, name))
               for field in undocumented_fields(getattr(em, name))]
    assert not missing, f"fields without an Attributes: entry: {missing}"

    @dataclasses.dataclass
    class Commented:  # what the check must catch
        """A class whose field is documented by a comment alone."""

        x: int = 0  # a comment, which the API reference does not show

    assert undocumented_fields(Commented) == ["x"]
