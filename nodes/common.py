"""Helpers shared by the tracking nodes."""

from __future__ import annotations

import dataclasses
from typing import Any

from ..bus.node import ParamError, params_from_dict


def split_params(raw: dict[str, Any], *classes: type) -> tuple[Any, ...]:
    """Build one params dataclass per class from a flat graph.yaml ``params`` mapping.

    Each key goes to the first class that has a field of that name; a key no class knows is a
    ParamError naming it (so graph validation points at its line).
    """
    parts: list[dict[str, Any]] = [{} for _ in classes]
    owners = [{f.name for f in dataclasses.fields(cls)} for cls in classes]
    for key, value in raw.items():
        for names, part in zip(owners, parts, strict=True):
            if key in names:
                part[key] = value
                break
        else:
            known = sorted(set().union(*owners))
            raise ParamError(key, f"unknown parameter {key!r} (known: {', '.join(known)})")
    return tuple(params_from_dict(cls, part) for cls, part in zip(classes, parts, strict=True))
