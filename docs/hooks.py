"""MkDocs hooks (`mkdocs.yml`, `hooks:`): the pages whose sources lie outside docs/, and links
written for GitHub mapped onto the site.

Every link in the docs is written as GitHub resolves it: relative to the file, into any folder
of the repository. The site holds docs/ only, so a link that leaves it is mapped here:

- to a file with a page of its own (`PAGES`: the tutorial script, the experiments map, the
  contributing notes): to that page, whose source this hook turns into Markdown;
- to a folder of data under docs/ (GitHub lists a folder's files): to a page listing them,
  generated here for every such folder;
- to any other file of the repository (a module, a test): its text, unlinked;
- to nothing: left alone, so that `mkdocs build --strict` fails on it.

Links inside fenced code blocks are not touched.
"""

from __future__ import annotations

import os
import posixpath
import re

from mkdocs.structure.files import File, InclusionLevel

# repository path -> the page it becomes on the site
PAGES = {
    "examples/tutorial.py": "tutorial.md",
    "experiments/README.md": "experiments.md",
    "CONTRIBUTING.md": "contributing.md",
}
SKIP_DIRS = {"guide", "api"}  # folders of pages, not of data
LINK = re.compile(r"(!?)\[((?:[^\[\]]|\[[^\]]*\])*)\]\(([^()\s]+)\)")

_root = ""  # the repository root (the folder of mkdocs.yml)
_repo_path: dict[str, str] = {}  # site page -> its source's repository path
_listings: set[str] = set()  # docs/ folders (repository paths) with a generated listing


def percent_to_markdown(text: str) -> str:
    """A script in jupytext's percent format as Markdown: `# %% [markdown]` cells lose their
    leading `# `, code cells become fenced Python blocks."""
    parts = re.split(r"^# %%(.*)$", text, flags=re.M)
    out = []
    for header, body in zip(parts[1::2], parts[2::2]):
        body = body.strip("\n")
        if "[markdown]" in header:
            out.append("\n".join(line[2:] if line.startswith("# ") else line.lstrip("#")
                                 for line in body.splitlines()))
        elif body:
            out.append(f"```python\n{body}\n```")
    return "\n\n".join(out) + "\n"


def _printed(script: str) -> str:
    """What `script` printed when its test last stored it (SCRIPT_output.txt beside it, its first
    line naming the script's digest: tests/test_tutorial.py), as a section of Markdown."""
    path = os.path.join(_root, script[: -len(".py")] + "_output.txt")
    if not os.path.exists(path):
        return ""
    with open(path, encoding="utf-8") as f:
        lines = f.read().splitlines()[1:]
    body = "\n".join(lines)
    return (f"\n## What it printed\n\nOn a 2-core CPU, stored by its test "
            f"(`tests/test_tutorial.py`); numbers differ a little between CPUs.\n\n"
            f"```text\n{body}\n```\n")


def _listing(folder: str) -> str:
    """The Markdown of a page listing the files of `folder` (a repository path under docs/)."""
    names = sorted(os.listdir(os.path.join(_root, folder)))
    lines = [f"# {folder}/", "", "The files of this folder of the repository.", ""]
    for name in names:
        if os.path.isdir(os.path.join(_root, folder, name)):
            lines.append(f"- [{name}/]({name}/index.md)")
        else:
            lines.append(f"- [{name}]({name})")
    return "\n".join(lines) + "\n"


def on_files(files, config):
    global _root
    _root = os.path.dirname(os.path.abspath(config.config_file_path))
    docs = os.path.relpath(config.docs_dir, _root)
    for path, page in PAGES.items():
        with open(os.path.join(_root, path), encoding="utf-8") as f:
            text = f.read()
        if path.endswith(".py"):
            text = percent_to_markdown(text) + _printed(path)
        files.append(File.generated(config, page, content=text))
        _repo_path[page] = path
    for folder, dirs, _ in os.walk(config.docs_dir):
        rel = os.path.relpath(folder, config.docs_dir).replace(os.sep, "/")
        if rel == ".":
            dirs[:] = [d for d in dirs if d not in SKIP_DIRS]
            continue
        if os.path.exists(os.path.join(folder, "index.md")):
            continue
        repo = posixpath.join(docs, rel)
        _listings.add(repo)
        files.append(File.generated(config, f"{rel}/index.md", content=_listing(repo),
                                    inclusion=InclusionLevel.NOT_IN_NAV))
    return files


def _map(target: str, page_uri: str) -> str | None:
    """The site link for `target`, a link written on the page `page_uri` as GitHub reads it;
    "" to unlink it, None to leave it as it is."""
    if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith(("#", "/")):
        return None
    path, _, anchor = target.partition("#")
    anchor = f"#{anchor}" if anchor else ""
    source = _repo_path.get(page_uri, posixpath.join("docs", page_uri))
    resolved = posixpath.normpath(posixpath.join(posixpath.dirname(source), path))
    here = posixpath.dirname(page_uri) or "."
    if resolved in PAGES:
        return posixpath.relpath(PAGES[resolved], here) + anchor
    if resolved in _listings:
        return posixpath.relpath(posixpath.join(resolved[len("docs/"):], "index.md"), here)
    if resolved.startswith("docs/"):
        return posixpath.relpath(resolved[len("docs/"):], here) + anchor
    if os.path.exists(os.path.join(_root, resolved)):
        return ""
    return None


def _relink(text: str, page_uri: str) -> str:
    def one(m: re.Match) -> str:
        new = _map(m.group(3), page_uri)
        if new is None:
            return m.group(0)
        if new == "":
            return m.group(2)
        return f"{m.group(1)}[{m.group(2)}]({new})"

    return LINK.sub(one, text)


def on_page_markdown(markdown, page, config, files):
    # split at fences: the even pieces are prose, the odd ones code blocks
    pieces = re.split(r"(^```.*?^```[ \t]*$)", markdown, flags=re.M | re.S)
    return "".join(p if i % 2 else _relink(p, page.file.src_uri) for i, p in enumerate(pieces))
