"""Dotted keys into a summary: ``speed_error.rms``, ``gains.k_w``, ``speed_error.windows.1.max``.

The one spelling of a value's place in ``summary.json`` for the commands that name one
(`compare`'s configuration differences and its tolerance file, the HTML report): tables
by key, lists by a 0-based index.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any


def flatten(tree: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """The leaves of nested tables by dotted key (``{"gains": {"k_w": 800}}`` →
    ``{"gains.k_w": 800}``); lists are leaves."""
    out: dict[str, Any] = {}
    for k, v in tree.items():
        if isinstance(v, Mapping):
            out.update(flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


class DottedKeyError(KeyError):
    """A dotted key that does not lead to a value: ``found`` is the part that does, and
    ``choices`` the keys (or index range) available after it."""

    def __init__(self, key: str, found: str, choices: str) -> None:
        super().__init__(key)
        self.key, self.found, self.choices = key, found, choices

    def __str__(self) -> str:
        where = f"under {self.found!r}" if self.found else "at the top"
        return f"no {self.key!r}: {where} there is {self.choices}"


def lookup(tree: Mapping[str, Any], key: str) -> Any:
    """The value at dotted ``key`` (a part that is a number indexes a list); raises
    :class:`DottedKeyError` naming how far the key leads and what is there instead."""
    node: Any = tree
    done: list[str] = []
    for part in key.split("."):
        if isinstance(node, Mapping):
            if part not in node:
                raise DottedKeyError(key, ".".join(done), _keys(node))
            node = node[part]
        elif isinstance(node, Sequence) and not isinstance(node, str):
            if not part.isdigit() or int(part) >= len(node):
                raise DottedKeyError(key, ".".join(done),
                                     f"a list of {len(node)} (index 0..{len(node) - 1})"
                                     if node else "an empty list")
            node = node[int(part)]
        else:
            raise DottedKeyError(key, ".".join(done), f"the value {node!r}, not a table")
        done.append(part)
    return node


def _keys(node: Mapping[str, Any]) -> str:
    names = sorted(node)
    if not names:
        return "an empty table"
    more = f", … ({len(names)} keys)" if len(names) > 12 else ""
    return "a table of " + ", ".join(names[:12]) + more
