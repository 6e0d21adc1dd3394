"""YAML for the configuration: read (errors with file, line and field), validate, override, write."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml
from pydantic import BaseModel, ValidationError

from georefine.config.base import StrictModel
from georefine.errors import ConfigError

__all__ = ["apply_overrides", "deep_merge", "override_fields", "read_yaml", "validate_model", "write_yaml"]


def read_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping; errors name the file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read file: {exc.strerror}", path=path) from exc
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise ConfigError(f"invalid YAML: {getattr(exc, 'problem', exc)}", path=path, line=line) from exc
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError("top level must be a mapping", path=path, expected="key: value pairs", found=type(data).__name__)
    return data


def _line_of_key(path: Path, loc: tuple) -> int | None:
    """Best-effort 1-based line of a nested key path in a YAML file (for error messages)."""
    try:
        node = yaml.compose(path.read_text(encoding="utf-8"))
    except Exception:  # noqa: BLE001 - only used to enrich an error message
        return None
    for key in loc:
        if node is None:
            return None
        if isinstance(node, yaml.MappingNode):
            found = None
            for k, v in node.value:
                if k.value == str(key):
                    found = (k, v)
                    break
            if found is None:
                return node.start_mark.line + 1
            if key == loc[-1]:
                return found[0].start_mark.line + 1
            node = found[1]
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int) and key < len(node.value):
            node = node.value[key]
        else:
            return node.start_mark.line + 1
    return node.start_mark.line + 1 if node is not None else None


def validate_model(model: type[BaseModel], data: dict[str, Any], path: str | Path | None = None) -> BaseModel:
    """Validate ``data`` against ``model``; the first error becomes a :class:`ConfigError`."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = tuple(err.get("loc", ()))
        field = ".".join(str(x) for x in loc) or None
        line = _line_of_key(Path(path), loc) if path is not None and loc else None
        if err.get("type") == "extra_forbidden":
            message = "unknown key"
            expected = "one of " + ", ".join(sorted(_known_keys(model, loc[:-1]))) if loc else None
            raise ConfigError(message, path=path, line=line, field=field, expected=expected, found=repr(loc[-1])) from exc
        found = err.get("input")  # a whole section (a model-level rule) is named by its field, not printed
        raise ConfigError(
            err.get("msg", "invalid value"), path=path, line=line, field=field,
            found=None if isinstance(found, dict) else repr(found),
        ) from exc


def _known_keys(model: type[BaseModel], loc: tuple) -> list[str]:
    current: Any = model
    for key in loc:
        if isinstance(key, int):
            continue
        field = getattr(current, "model_fields", {}).get(key)
        if field is None:
            return []
        ann = field.annotation
        for cand in getattr(ann, "__args__", (ann,)):
            inner = getattr(cand, "__args__", (cand,))
            for c in (cand, *inner):
                if isinstance(c, type) and issubclass(c, BaseModel):
                    current = c
                    break
    return list(getattr(current, "model_fields", {}).keys())


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Apply ``key.sub=value`` overrides (values parsed as YAML scalars/lists) to a nested dict.

    Returns a new dict; ``data`` is not modified.
    """
    import copy

    out = copy.deepcopy(data)
    for item in overrides:
        if "=" not in item:
            raise ConfigError("override must look like key.sub=value", field="overrides", found=repr(item))
        key, _, raw = item.partition("=")
        parts = [p for p in key.strip().split(".") if p]
        if not parts:
            raise ConfigError("override has an empty key", field="overrides", found=repr(item))
        try:
            value = yaml.safe_load(raw) if raw.strip() else None
        except yaml.YAMLError as exc:
            raise ConfigError("override value is not valid YAML", field=key, found=repr(raw)) from exc
        node = out
        for p in parts[:-1]:
            child = node.get(p)
            if child is None:
                child = node[p] = {}
            if not isinstance(child, dict):
                raise ConfigError("cannot set a sub-key of a scalar", field=key, found=repr(child))
            node = child
        node[parts[-1]] = value
    return out


def override_fields(section: StrictModel, values: Mapping[str, Any], *, name: str) -> StrictModel:
    """A copy of a configuration section with ``values`` (field name to value) set, validated together.

    Parameters
    ----------
    section
        The section as loaded (e.g. ``config.processing.lidargrammetry``).
    values
        The fields to set (e.g. from command-line options); ``None`` values are set as ``None``.
    name
        The section's place in ``project.yaml`` (``"processing.lidargrammetry"``); errors name
        ``name.field``.

    Raises
    ------
    ConfigError
        An unknown field or a value the section refuses.
    """
    data = {**section.model_dump(), **dict(values)}
    try:
        return validate_model(type(section), data)  # type: ignore[return-value]
    except ConfigError as exc:
        raise ConfigError(exc.message, field=f"{name}.{exc.field}" if exc.field else name,
                          expected=exc.expected, found=exc.found) from exc.__cause__


def deep_merge(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    """Recursive dict merge (``update`` wins); returns a new dict."""
    out = dict(base)
    for k, v in update.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = v
    return out


def write_yaml(path: str | Path, data: dict[str, Any] | BaseModel) -> None:
    """Write YAML atomically (temporary name, then rename)."""
    from georefine.io.files import atomic_output

    if isinstance(data, BaseModel):
        data = data.model_dump(mode="json")
    with atomic_output(path, "w") as fh:
        fh.write(yaml.safe_dump(data, sort_keys=False, default_flow_style=None))
