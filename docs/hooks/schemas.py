"""MkDocs hook: the file formats' JSON Schemas in the site, and a page of their fields.

Each ``slcvjax/observations/schemas/*.schema.json`` is published as ``schemas/NAME.schema.json``
(``formats.md`` links to them), and ``schemas.md`` lists every field of every format, generated
from the schemas at every build so that it cannot fall behind them: its JSON path, its type, whether
it is required, and its description (with its unit).  The formats and their order are the package's.
"""

import json
from pathlib import Path

from mkdocs.structure.files import File

from slcvjax.observations.schemas import FORMATS

SCHEMAS = Path(__file__).parent.parent.parent / "slcvjax" / "observations" / "schemas"
ORDER = [*FORMATS, "common"]  # the formats in the package's order, then the shared definitions

INTRO = """# Schema reference

Every public file format has a JSON Schema (draft 2020-12), shipped in the package
(`slcvjax.observations.schemas`: `schema(name)`, `validate(doc, path)`) and linked below. This page is
generated from them when the site is built: each field by its JSON path (`[]` an item of a list, `{}` any
key of an object, `A | B` the alternatives), its type, whether it is required where its parent is given,
and its description. [File formats](formats.md) explains them. Extra fields are allowed everywhere.
"""


def _file(name: str) -> str:
    return name.replace("/", "-") + ".schema.json"


def _load() -> dict[str, dict]:
    return {name: json.loads((SCHEMAS / _file(name)).read_text(encoding="utf-8")) for name in ORDER}


def _resolve(ref: str, doc: dict, docs: dict) -> tuple[dict, dict, str]:
    """The schema a ``$ref`` points to, the document it lies in, and a Markdown link to it where
    it is a shared definition (``common#/$defs/NAME``) of another document."""
    name, _, pointer = ref.partition("#")
    target_doc = docs[name.removeprefix("urn:slcvjax:schema:")] if name else doc
    node = target_doc
    for part in filter(None, pointer.split("/")):
        node = node[part]
    return node, target_doc, name.removeprefix("urn:slcvjax:schema:")


def _type(node: dict, doc: dict, docs: dict) -> str:
    if "const" in node:
        return f"`{json.dumps(node['const'])}`"
    if "enum" in node:
        return " \\| ".join(f"`{json.dumps(v)}`" for v in node["enum"])
    if "$ref" in node:
        target, _, other = _resolve(node["$ref"], doc, docs)
        if other and other != doc.get("$id", "").removeprefix("urn:slcvjax:schema:"):
            anchor = node["$ref"].rpartition("/")[2] if "#" in node["$ref"] else ""
            page = f"[{other}{'.' + anchor if anchor else ''}](#{_anchor(other)})"
            return page
        return _type(target, doc, docs)
    if "anyOf" in node:
        return " \\| ".join(_type(alt, doc, docs) for alt in node["anyOf"])
    if "allOf" in node:
        return next((_type(a, doc, docs) for a in node["allOf"] if "$ref" in a or "type" in a), "object")
    t = node.get("type", "any")
    t = " \\| ".join(t) if isinstance(t, list) else t
    if "items" in node and isinstance(node["items"], dict) and "properties" not in node["items"]:
        t += f" of {_type(node['items'], doc, docs)}"
    if "minItems" in node and node.get("minItems") == node.get("maxItems"):
        t += f" ({node['minItems']})"
    return t


def _anchor(name: str) -> str:
    return name.replace("/", "").replace("-", "-").lower()


def _rows(node: dict, doc: dict, docs: dict, path: str, required: bool, out: list, seen: set) -> None:
    """One row per property below ``node`` (recursing into objects, items, allOf branches and the
    document's own definitions; shared definitions of another document are linked, not repeated)."""
    if "$ref" in node and "properties" not in node:
        target, target_doc, other = _resolve(node["$ref"], doc, docs)
        own = not other or other == doc.get("$id", "").removeprefix("urn:slcvjax:schema:")
        if own and id(target) not in seen:
            _rows(target, target_doc, docs, path, required, out, seen | {id(target)})
        return
    for branch in node.get("allOf", []):
        _rows(branch, doc, docs, path, required, out, seen)
    for branch in node.get("anyOf", []):
        if branch.get("type") != "null":
            _rows(branch, doc, docs, path, required, out, seen)
    req = set(node.get("required", []))
    for key, sub in (node.get("properties") or {}).items():
        where = f"{path}.{key}" if path else key
        description = sub.get("description") or ""
        if not description and "$ref" in sub:
            description = _resolve(sub["$ref"], doc, docs)[0].get("description", "")
        out.append((where, _type(sub, doc, docs), key in req, description))
        _rows(sub, doc, docs, where, key in req, out, seen)
    for key, suffix in (("items", "[]"), ("additionalProperties", "{}")):
        sub = node.get(key)
        if not isinstance(sub, dict):
            continue
        if "$ref" in sub and "properties" not in sub:  # a list or map of a definition: named once
            target = _resolve(sub["$ref"], doc, docs)[0]
            out.append((path + suffix, _type(sub, doc, docs), False, target.get("description", "")))
        _rows(sub, doc, docs, path + suffix, False, out, seen)


def render() -> str:
    docs = _load()
    parts = [INTRO]
    for name in ORDER:
        doc = docs[name]
        parts.append(f"## {name}\n")
        parts.append(f"[`{_file(name)}`](schemas/{_file(name)}): {doc.get('description', '')}\n")
        if name == "common":
            rows = []
            for key, sub in doc["$defs"].items():
                rows.append((f"$defs.{key}", _type(sub, doc, docs), False, sub.get("description", "")))
                _rows(sub, doc, docs, f"$defs.{key}", False, rows, set())
        else:
            rows = []
            _rows(doc, doc, docs, "", True, rows, set())
        table = ["| field | type | required | description |", "| --- | --- | --- | --- |"]
        seen = set()
        for where, typ, req, desc in rows:
            if where in seen:
                continue
            seen.add(where)
            # brackets escaped: "[laser][level]" would be read as a reference link
            desc = desc.replace("|", "\\|").replace("\n", " ").replace("[", "\\[").replace("]", "\\]")
            table.append(f"| `{where}` | {typ} | {'yes' if req else ''} | {desc} |")
        parts.append("\n".join(table) + "\n")
    return "\n".join(parts)


def on_files(files, config):
    files.append(File.generated(config, "schemas.md", content=render()))
    for name in ORDER:
        text = (SCHEMAS / _file(name)).read_text(encoding="utf-8")
        files.append(File.generated(config, f"schemas/{_file(name)}", content=text))
    return files
