"""JSON Schemas (draft 2020-12) of the public file formats, shipped with the package.

One schema per format, ``slcv-observations/1`` -> ``slcv-observations-1.schema.json`` beside
this module (``common.schema.json`` holds the pieces they share; ``slcv-problem/1`` is the
calibration file's ``problem`` section).  The schemas describe every documented field, with its
unit; extra fields are allowed (older readers ignore them).  They check a document's shape and
types; the readers (:func:`slcvjax.observations.formats.read_observations`, ...) check more (a
laser index below ``n_lasers``, a rotation matrix, a board's points against its type).

:func:`validate` raises the readers' :class:`~slcvjax.observations.formats.FormatError`,
naming the file and the JSON path of the first error (``obs.json: views[3].spots[2].laser: ...``).
"""

import json
from functools import cache
from importlib import resources
from typing import Any

from ..formats import FormatError

FORMATS = (
    "slcv-observations/1",
    "slcv-calibration/1",
    "slcv-problem/1",
    "slcv-setup/1",
    "slcv-points/1",
    "slcv-sweep/1",
    "slcv-design/1",
    "slcv-laser-design/1",
)
_ID = "urn:slcvjax:schema:"


def _file(name: str) -> str:
    return name.replace("/", "-") + ".schema.json"


def schema_text(name: str) -> str:
    """The schema file's text of a format (``"slcv-points/1"``) or of ``"common"``."""
    if name not in FORMATS + ("common",):
        raise KeyError(f"no schema for {name!r} (known: {', '.join(FORMATS)})")
    return resources.files(__package__).joinpath(_file(name)).read_text(encoding="utf-8")


@cache
def _schemas() -> dict[str, dict]:
    return {name: json.loads(schema_text(name)) for name in FORMATS + ("common",)}


def schema(name: str) -> dict:
    """The JSON Schema of a format (``"slcv-calibration/1"``), or ``"common"``'s definitions.

    Raises:
        KeyError: no schema of that name.
    """
    if name not in FORMATS + ("common",):
        raise KeyError(f"no schema for {name!r} (known: {', '.join(FORMATS)})")
    return json.loads(json.dumps(_schemas()[name]))  # a copy: the cached one stays as shipped


@cache
def _validator(name: str):
    from jsonschema import Draft202012Validator
    from referencing import Registry, Resource

    docs = _schemas()
    registry = Registry().with_resources(
        (docs[n]["$id"], Resource.from_contents(docs[n])) for n in FORMATS + ("common",)
    )
    return Draft202012Validator(docs[name], registry=registry)


def _where(path) -> str:
    """A JSON path as the readers write it: ``views[3].spots[2].laser`` (``(top level)`` for none)."""
    out = ""
    for p in path:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out or "(top level)"


def errors(doc: Any, name: str | None = None) -> list[tuple[str, str]]:
    """Every schema error of ``doc`` as ``(JSON path, message)``, the most relevant first
    (jsonschema's ``best_match`` order: the shallowest in the document; within an ``anyOf`` the
    branch that got deepest); ``name``: the format (default: the document's ``format`` field).

    Raises:
        KeyError: no schema for the format.
    """
    from jsonschema.exceptions import best_match, relevance

    if name is None:
        name = doc.get("format") if isinstance(doc, dict) else None
        if name not in FORMATS:
            return [("format", f"expected one of {', '.join(FORMATS)}, got {json.dumps(name)[:60]}")]
    found = sorted(_validator(name).iter_errors(doc), key=relevance, reverse=True)
    out = []
    for e in found:
        if e.context:  # an anyOf / oneOf: the branch that came closest
            e = best_match([e]) or e
        out.append((_where(e.absolute_path), e.message))
    return out


def validate(doc: Any, path: str, name: str | None = None) -> None:
    """Check a parsed document against its format's schema (``name``, default its ``format``
    field); :class:`FormatError` ``"PATH: JSON.path: message"`` naming the first error."""
    found = errors(doc, name)
    if found:
        where, msg = found[0]
        raise FormatError(f"{path}: {where}: {msg[:300]}")
