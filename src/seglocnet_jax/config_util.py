"""Plain-dict config trees (e.g. a resolved Hydra config) to frozen dataclass configs.

Library code never imports Hydra: an entry point resolves its ``DictConfig`` to a dict and calls
:func:`from_dict` per component. Unknown keys and bad values become :class:`ConfigError` naming the
full key (``train.optim.learning_rate``) and what was expected.
"""

from __future__ import annotations

import dataclasses
import types
import typing


class ConfigError(ValueError):
    """A configuration key is unknown or its value is invalid; the message names the key."""


def _is_dataclass_type(tp) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _convert(value, tp, key: str):
    origin = typing.get_origin(tp)
    if _is_dataclass_type(tp):
        if not isinstance(value, dict):
            raise ConfigError(f"{key} must be a mapping for {tp.__name__}, got {value!r}")
        return from_dict(tp, value, key)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        if len(args) == 1:
            return _convert(value, args[0], key)
        return value
    if origin is tuple and isinstance(value, list | tuple):
        return tuple(value)
    if tp is tuple and isinstance(value, list):
        return tuple(value)
    if tp is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if tp in (int, float, str, bool) and not isinstance(value, tp):
        raise ConfigError(f"{key} must be {tp.__name__}, got {value!r}")
    return value


def from_dict(cls, section: dict | None, prefix: str):
    """Builds dataclass ``cls`` from ``section`` (missing keys keep their defaults)."""
    section = dict(section or {})
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(section) - names)
    if unknown:
        raise ConfigError(
            f"unknown config key(s) {', '.join(f'{prefix}.{k}' for k in unknown)}; "
            f"{prefix} accepts: {', '.join(sorted(names))}"
        )
    kwargs = {k: _convert(v, hints[k], f"{prefix}.{k}") for k, v in section.items()}
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as err:
        msg = str(err)
        raise ConfigError(msg if prefix in msg else f"{prefix}: {msg}") from err
