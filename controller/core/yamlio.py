"""Line-aware, safe YAML loading and validation with ``path:line:col`` errors.

Plans, cells and objects are YAML written by people. This module loads them from
ruamel.yaml's node graph (not its constructors) so that:

- every key and value keeps its position, and every error names ``path:line:col``
  (1-based);
- duplicate keys are refused;
- only the YAML 1.2 core schema is accepted: ``yes``/``no``/``on``/``off`` stay
  strings (no implicit booleans), and any explicit non-core tag (``!!python/...``,
  ``!custom``) is refused;
- aliases are expanded under a budget, so an "alias bomb" fails fast;
- bytes that are not UTF-8 are refused with the position of the first bad byte.

``validate`` then runs a pydantic model over the data and maps each validation
error back to the position of the offending key or value. ``dump_yaml_text`` is the other
direction: the one way YAML that people will read is written (generated plans and objects,
the benches' edited copies).
"""
from __future__ import annotations

import io
import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import pydantic
from ruamel.yaml import YAML
from ruamel.yaml.error import MarkedYAMLError, YAMLError
from ruamel.yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode
from ruamel.yaml.reader import ReaderError
from ruamel.yaml.tokens import (BlockEndToken, BlockMappingStartToken, BlockSequenceStartToken,
                                FlowMappingEndToken, FlowMappingStartToken, FlowSequenceEndToken,
                                FlowSequenceStartToken)

from .errors import InputError, InputErrors
from .inputfiles import read_input_bytes

MAX_NODES = 200_000          # constructed values, aliases expanded: bounds an alias bomb
MAX_FILE_BYTES = 4_000_000
MAX_DEPTH = 64               # nested collections; ruamel's composer recurses once per level

_OPENS = (BlockMappingStartToken, BlockSequenceStartToken, FlowMappingStartToken, FlowSequenceStartToken)
_CLOSES = (BlockEndToken, FlowMappingEndToken, FlowSequenceEndToken)

_CORE = "tag:yaml.org,2002:"
_INT_RE = re.compile(r"^[-+]?(0|[1-9][0-9_]*)$|^0o[0-7]+$|^0x[0-9a-fA-F]+$")
_FLOAT_RE = re.compile(r"^[-+]?(\.[0-9]+|[0-9][0-9_]*(\.[0-9_]*)?)([eE][-+]?[0-9]+)?$")

Path_ = tuple[Any, ...]


@dataclass
class YamlDoc:
    """Plain Python data (dict/list/str/int/float/bool/None) plus where each part came from."""

    path: str
    data: Any
    positions: dict[Path_, tuple[int, int]] = field(default_factory=dict)   # value positions
    key_positions: dict[Path_, tuple[int, int]] = field(default_factory=dict)

    def where(self, loc: Path_) -> tuple[int, int]:
        """(line, col), 1-based, of the deepest known part of ``loc``."""
        loc = tuple(loc)
        while loc:
            if loc in self.positions:
                return self.positions[loc]
            if loc in self.key_positions:
                return self.key_positions[loc]
            loc = loc[:-1]
        return self.positions.get((), (1, 1))

    def error(self, loc: Path_, message: str) -> InputError:
        line, col = self.where(loc)
        return InputError(message, path=self.path, line=line, col=col)


def _pos(node: Node) -> tuple[int, int]:
    return node.start_mark.line + 1, node.start_mark.column + 1


class _Builder:
    def __init__(self, path: str) -> None:
        self.path = path
        self.count = 0
        self.doc = YamlDoc(path=path, data=None)

    def fail(self, node: Node, message: str) -> InputError:
        line, col = _pos(node)
        return InputError(message, path=self.path, line=line, col=col)

    def build(self, node: Node, loc: Path_, depth: int = 0) -> Any:
        self.count += 1
        if self.count > MAX_NODES:
            raise self.fail(node, f"document expands to more than {MAX_NODES} values (alias bomb?)")
        if depth > MAX_DEPTH:
            raise self.fail(node, f"document is nested more than {MAX_DEPTH} levels deep")
        self.doc.positions.setdefault(loc, _pos(node))
        tag = str(node.tag)
        if isinstance(node, MappingNode):
            if tag != _CORE + "map":
                raise self.fail(node, f"tag {tag!r} is not allowed (plain YAML only)")
            out: dict[Any, Any] = {}
            for key_node, value_node in node.value:
                if str(key_node.tag) == _CORE + "merge":
                    raise self.fail(key_node, "merge keys (<<) are not allowed")
                key = self.build(key_node, loc + ("<key>",), depth + 1)
                if not isinstance(key, (str, int)) or isinstance(key, bool):
                    raise self.fail(key_node, f"mapping keys must be strings, got {type(key).__name__}")
                if key in out:
                    raise self.fail(key_node, f"duplicate key {key!r}")
                self.doc.key_positions[loc + (key,)] = _pos(key_node)
                out[key] = self.build(value_node, loc + (key,), depth + 1)
            self.doc.positions.pop(loc + ("<key>",), None)
            return out
        if isinstance(node, SequenceNode):
            if tag != _CORE + "seq":
                raise self.fail(node, f"tag {tag!r} is not allowed (plain YAML only)")
            return [self.build(item, loc + (i,), depth + 1) for i, item in enumerate(node.value)]
        assert isinstance(node, ScalarNode)
        return self.scalar(node, tag)

    def scalar(self, node: ScalarNode, tag: str) -> Any:
        text = node.value
        if tag == _CORE + "str":
            return text
        if tag == _CORE + "null":
            return None
        if tag == _CORE + "bool":
            if text in ("true", "True", "TRUE"):
                return True
            if text in ("false", "False", "FALSE"):
                return False
            raise self.fail(node, f"{text!r} is not a boolean (write true or false)")
        if tag == _CORE + "int":
            if not _INT_RE.match(text):
                raise self.fail(node, f"{text!r} is not an integer")
            return int(text.replace("_", ""), 0)
        if tag == _CORE + "float":
            low = text.lower()
            if low in (".nan", ".inf", "+.inf", "-.inf"):
                raise self.fail(node, f"{text!r}: NaN and infinity are not allowed")
            try:
                value = float(text.replace("_", ""))
            except ValueError:
                raise self.fail(node, f"{text!r} is not a number") from None
            if not math.isfinite(value):
                raise self.fail(node, f"{text!r} is out of range")
            return value
        raise self.fail(node, f"tag {tag!r} is not allowed")


def _line_col(text: str, index: int) -> tuple[int, int]:
    """1-based (line, column) of character ``index`` of ``text``."""
    before = text[:index]
    return before.count("\n") + 1, index - (before.rfind("\n") + 1) + 1


def _refuse_deep_nesting(yaml: YAML, text: str, path: str) -> None:
    """Refuse collections nested deeper than MAX_DEPTH before composing: the scanner is
    iterative, the composer recursive, so ``[[[[...]]]]`` a few thousand deep would end in
    RecursionError instead of an error at its place."""
    depth = 0
    for token in yaml.scan(text):
        if isinstance(token, _OPENS):
            depth += 1
            if depth > MAX_DEPTH:
                mark = token.start_mark
                raise InputError(f"document is nested more than {MAX_DEPTH} levels deep",
                                 path=path, line=mark.line + 1, col=mark.column + 1)
        elif isinstance(token, _CLOSES):
            depth -= 1


def parse_yaml_text(text_bytes: bytes, path: str) -> YamlDoc:
    """Parse YAML bytes into a :class:`YamlDoc`; raise :class:`InputError` with a position."""
    if len(text_bytes) > MAX_FILE_BYTES:
        raise InputError(f"file is larger than {MAX_FILE_BYTES} bytes", path=path, line=1, col=1)
    try:
        text = text_bytes.decode("utf-8")
    except UnicodeDecodeError as exc:
        before = text_bytes[: exc.start]
        line = before.count(b"\n") + 1
        col = len(before) - (before.rfind(b"\n") + 1) + 1
        raise InputError(f"not valid UTF-8 (byte 0x{text_bytes[exc.start]:02x})",
                         path=path, line=line, col=col) from None
    if text.startswith("\ufeff"):
        text = text[1:]
    if not text.strip() or all(ln.strip().startswith("#") or not ln.strip() for ln in text.splitlines()):
        raise InputError("file is empty", path=path, line=1, col=1)
    yaml = YAML(typ="rt")
    yaml.version = (1, 2)
    try:
        _refuse_deep_nesting(yaml, text, path)
        node = yaml.compose(text)
    except MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line, col = (mark.line + 1, mark.column + 1) if mark is not None else (1, 1)
        problem = (exc.problem or exc.context or "invalid YAML").strip().splitlines()[0]
        raise InputError(f"YAML syntax: {problem}", path=path, line=line, col=col) from None
    except ReaderError as exc:   # a character YAML does not allow (NUL, other controls): at its place
        line, col = _line_col(text, int(exc.position))
        code = ord(exc.character) if isinstance(exc.character, str) else int(exc.character)
        name = "NUL" if code == 0 else f"#x{code:04x}"
        raise InputError(f"YAML syntax: the control character {name} is not allowed in a YAML file",
                         path=path, line=line, col=col) from None
    except YAMLError as exc:   # unmarked errors (e.g. stream-level problems)
        raise InputError(f"YAML syntax: {exc}", path=path, line=1, col=1) from None
    if node is None:
        raise InputError("file is empty", path=path, line=1, col=1)
    builder = _Builder(path)
    builder.doc.data = builder.build(node, ())
    return builder.doc


def load_yaml(path: str | Path) -> YamlDoc:
    """Read and parse a YAML file; every failure is an :class:`InputError`."""
    try:
        raw = read_input_bytes(path)
    except FileNotFoundError:
        raise InputError("no such file", path=str(path)) from None
    except IsADirectoryError:
        raise InputError("is a directory, not a YAML file", path=str(path)) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path=str(path)) from None
    return parse_yaml_text(raw, str(path))


M = TypeVar("M", bound=pydantic.BaseModel)


def _message(err: dict[str, Any]) -> str:
    loc = [str(x) for x in err.get("loc", ()) if not str(x).startswith("function-")]
    msg = err.get("msg", "invalid value")
    if err.get("type") == "extra_forbidden":
        return f"unknown key {loc[-1]!r}" if loc else "unknown key"
    if err.get("type") == "missing":
        return f"missing required key {loc[-1]!r}" if loc else "missing required key"
    msg = msg.removeprefix("Value error, ").removeprefix("Assertion failed, ")
    where = ".".join(loc)
    return f"{where}: {msg}" if where else msg


def validate(doc: YamlDoc, model: type[M], context: dict[str, Any] | None = None) -> M:
    """Validate ``doc.data`` against a pydantic model; errors carry ``path:line:col``."""
    # JSON mode keeps strictness (no "5" -> 5, no "off" -> False) while letting YAML
    # lists fill tuple fields, which strict Python-mode validation would refuse.
    try:
        return model.model_validate_json(json.dumps(doc.data), strict=True, context=context)
    except pydantic.ValidationError as exc:
        errors: list[InputError] = []
        for err in exc.errors():
            loc = tuple(x for x in err.get("loc", ()) if not (isinstance(x, str) and x.startswith("function-")))
            if err.get("type") == "extra_forbidden" and loc in doc.key_positions:
                line, col = doc.key_positions[loc]
                errors.append(InputError(_message(err), path=doc.path, line=line, col=col))
            elif err.get("type") == "missing":
                errors.append(doc.error(loc[:-1], _message(err)))
            else:
                errors.append(doc.error(loc, _message(err)))
        errors.sort(key=lambda e: (e.line or 0, e.col or 0))
        raise InputErrors(errors) from None


class Spec(pydantic.BaseModel):
    """Base of every file schema: unknown keys refused, no silent type coercion."""

    model_config = pydantic.ConfigDict(extra="forbid", strict=True, frozen=True)


def load_validated(path: str | Path, model: type[M], context: dict[str, Any] | None = None) -> tuple[M, YamlDoc]:
    """Load ``path`` and validate it against ``model``."""
    doc = load_yaml(path)
    return validate(doc, model, context), doc


def dump_yaml_text(doc: Any) -> str:
    """``doc`` as YAML text for people: block style with lists of scalars inline, lines up to 120
    characters. ``doc`` is plain data or a document loaded round-trip (ruamel.yaml ``YAML()``),
    whose comments and key order are kept."""
    yaml = YAML()
    yaml.default_flow_style = None
    yaml.width = 120
    buf = io.StringIO()
    yaml.dump(doc, buf)
    return buf.getvalue()
