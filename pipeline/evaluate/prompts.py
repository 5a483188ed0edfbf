"""Query prompts derived from mesh names ("006_mustard_bottle" -> "the mustard bottle")."""

from __future__ import annotations

import re

DEFAULT_PROMPT_TEMPLATE = "the {name}"
# leading catalogue ids: "006_", "065-a_", "obj_000002" style prefixes
_ID_PREFIX = re.compile(r"^(?:\d+(?:-[a-z])?[_\- ]+)")


def readable_name(mesh_name: str) -> str:
    """Words of a mesh name without its catalogue id: ``065-a_cups`` -> ``cups``."""
    name = _ID_PREFIX.sub("", mesh_name)
    name = re.sub(r"[_\-]+", " ", name).strip()
    return name or mesh_name


def prompt_for(mesh_name: str, template: str = DEFAULT_PROMPT_TEMPLATE, names: dict | None = None) -> str:
    """The prompt of a mesh: ``template`` with ``{name}`` (readable name) and ``{raw}`` (mesh name).

    ``names`` overrides the readable name per mesh name (e.g. ``{"hope_000002": "bbq sauce bottle"}``).
    """
    name = (names or {}).get(mesh_name) or readable_name(mesh_name)
    return template.format(name=name, raw=mesh_name)
