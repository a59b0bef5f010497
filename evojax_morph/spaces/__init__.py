"""Morphology spaces, registered by name.

To add a space: subclass `Space` in a module of this package and list it in `_REGISTRY`
(`registry.Registry`).
"""

from __future__ import annotations

from evojax_morph.registry import Registry
from evojax_morph.spaces.bad_walker import BadWalker
from evojax_morph.spaces.base import Space
from evojax_morph.spaces.constructor import Constructor
from evojax_morph.spaces.crawler import Crawler, CrawlerNear
from evojax_morph.spaces.length_walker import LengthWalker

_REGISTRY: Registry[type[Space]] = Registry(
    "space", (BadWalker, Constructor, Crawler, CrawlerNear, LengthWalker), sort=True)


def list_spaces() -> list[str]:
    """Names accepted by `make_space`."""
    return _REGISTRY.list()


def get_space(name: str) -> type[Space]:
    """The space class registered as `name`: its rules (`Space.gpu_defaults`) without building
    its template."""
    return _REGISTRY.get(name)


def make_space(name: str, **kwargs) -> Space:
    """The space registered as `name`; keyword arguments go to its constructor."""
    return get_space(name)(**kwargs)


__all__ = ["BadWalker", "Constructor", "Crawler", "CrawlerNear", "LengthWalker", "Space",
           "get_space", "list_spaces", "make_space"]
