"""Checks of single configured values, of mandatory values left unset and of model configs
against their classes' constructors, each failure a ConfigError naming its dotted key
(``pae.config.validation`` runs them over a whole run's settings; a model class checks its own
ranges with them)."""

from __future__ import annotations

import dataclasses
import inspect
import re
import typing
from collections.abc import Callable
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from pae.core.errors import ConfigError
from pae.core.ranges import check_boolean, check_choice, check_integer, check_number, is_int


def setting(cfg: DictConfig, key: str) -> Any:
    """The value at dotted ``key`` (None where it is unset)."""
    return OmegaConf.select(cfg, key, default=None)


def present(cfg: DictConfig, key: str) -> bool:
    """Whether the config has ``key`` (dotted), whatever its value."""
    parent, _, name = key.rpartition(".")
    node = setting(cfg, parent) if parent else cfg
    return isinstance(node, DictConfig) and name in node


def _checked(check: Callable[..., None], cfg: DictConfig, key: str, *args: Any) -> Any:
    """The value at ``key`` passed through ``check`` (:mod:`pae.core.ranges`): its
    ValueError a ConfigError."""
    value = setting(cfg, key)
    try:
        check(key, value, *args)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    return value


def integer(cfg: DictConfig, key: str, low: int) -> int:
    return _checked(check_integer, cfg, key, low)


def number(cfg: DictConfig, key: str, low: float, strict: bool, optional: bool = False) -> None:
    _checked(check_number, cfg, key, low, strict, optional)


def boolean(cfg: DictConfig, key: str) -> None:
    _checked(check_boolean, cfg, key)


def choice(cfg: DictConfig, key: str, choices: tuple[str, ...]) -> None:
    _checked(check_choice, cfg, key, choices)


def check_record(
    cfg: DictConfig,
    key: str,
    record_type: type,
    renamed: dict[str, str] | None = None,
    **given: Any,
) -> Any:
    """The settings record ``record_type`` (a dataclass whose ``__post_init__`` checks its
    ranges) built from the config at ``key``: the fields it has (a field's key there:
    ``renamed`` or its name), interpolations resolved, and ``given``, the others their
    defaults; its ValueError a ConfigError, each setting it names named with its key
    (``crop`` -> ``data.crop``)."""
    node = setting(cfg, key)
    values = OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig) else {}
    keys = {spec.name: spec.name for spec in dataclasses.fields(record_type)} | (renamed or {})
    values = {name: values[k] for name, k in keys.items() if k in values} | given
    try:
        return record_type(**values)
    except ValueError as err:
        names = "|".join(sorted(keys, key=len, reverse=True))
        named = re.sub(rf"(?<![\w.'])({names})(?![\w'])", lambda m: f"{key}.{keys[m[1]]}", str(err))
        raise ConfigError(named) from None


def existing_file(cfg: DictConfig, key: str) -> None:
    value = setting(cfg, key)
    if value is not None and not Path(str(value)).is_file():
        raise ConfigError(f"{key}={value}: no such file")


INSTANTIATE_KEYS = ("_target_", "_partial_", "_recursive_", "_convert_", "_args_")
"""Keys of a model config that Hydra reads itself, not constructor arguments."""
ANNOTATED_TYPES = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}


def constructor_types(target: Any) -> dict[str, Any]:
    """The constructor's annotated argument types, those of its ``settings_types`` included
    (empty where they cannot be resolved)."""
    try:
        types = typing.get_type_hints(target.__init__ if inspect.isclass(target) else target)
        for settings in getattr(target, "settings_types", ()):
            types = typing.get_type_hints(settings) | types
    except Exception:  # annotations naming what the module does not import: unchecked
        return {}
    return types


def matches_annotation(value: Any, annotation: Any) -> bool:
    """Whether a configured value is of a plain annotated type (bool, int, float, str)."""
    if annotation is bool:
        return isinstance(value, bool)
    if annotation is int:
        return is_int(value)
    if annotation is float:
        return is_int(value) or isinstance(value, float)
    return isinstance(value, str)


def accepted_arguments(target: Any) -> tuple[list[str], bool]:
    """The keyword arguments a class (or function) accepts, and whether it takes any: a
    class with ``settings_types`` (dataclasses of the settings its ``**settings`` take)
    accepts their fields; one whose ``**kwargs`` go to its base class's constructor accepts
    that one's."""
    parameters = inspect.signature(target).parameters.values()
    names = [p.name for p in parameters if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    if not any(p.kind == p.VAR_KEYWORD for p in parameters):
        return names, False
    settings_types = getattr(target, "settings_types", ())
    if settings_types:
        fields = [f.name for settings in settings_types for f in dataclasses.fields(settings)]
        return [*names, *dict.fromkeys(n for n in fields if n not in names)], False
    if inspect.isclass(target):
        for base in target.__mro__[1:]:
            if base is not object and "__init__" in vars(base):
                inherited, any_keyword = accepted_arguments(base)
                return [*names, *(n for n in inherited if n not in names)], any_keyword
    return names, True


def _hint(key: str, name: str, named: list[str]) -> str:
    """The nearest of a constructor's arguments to a misspelt ``name`` (of the config at
    ``key``), else all of them (where they are few enough for one line)."""
    import difflib

    near = difflib.get_close_matches(str(name), named, n=1)
    if near:
        return f"; did you mean {key}.{near[0]}?"
    return f" (it takes {', '.join(named)})" if len(named) <= 12 else ""


def check_constructor(cfg: DictConfig, key: str, supplied: tuple[str, ...] = ()) -> None:
    """The model config at ``key`` (with ``_target_``) fits its class's constructor: every key
    is an argument of it, every argument without a default is given (or in ``supplied``, the
    ones its step fills in), values annotated as a plain int, float, bool or str are one; the
    same for nested model configs (a backbone). A ConfigError naming the key otherwise.

    A class built from a run (a scene model's ``build``, the refiner its callback makes)
    declares what the run adds: ``from_run`` (constructor arguments filled in: never
    configured), ``build_keys``
    (config keys it reads or resolves before the constructor sees them: not checked against
    the constructor) and ``check_config(cfg, key)`` (the ranges its signature cannot state).
    """
    node = setting(cfg, key)
    if not isinstance(node, DictConfig) or "_target_" not in node:
        raise ConfigError(f"{key}: no model configured (a group with a _target_ class)")
    target_name = node["_target_"]
    try:
        from hydra.utils import get_object

        target = get_object(target_name)
        parameters = inspect.signature(target).parameters
    except Exception as err:
        line = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ConfigError(f"{key}._target_={target_name}: cannot be loaded ({line})") from None
    named = [
        name
        for name, p in parameters.items()
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
    ]
    accepted, any_keyword = accepted_arguments(target)
    types = constructor_types(target)
    from_run = tuple(getattr(target, "from_run", ()))
    build_keys = tuple(getattr(target, "build_keys", ()))
    for name in node:
        if name in INSTANTIATE_KEYS or name in build_keys:
            continue
        if name in from_run:
            raise ConfigError(
                f"{key}.{name}: filled in from the run for {target_name}, not set here"
            )
        if name not in accepted and not any_keyword:
            hint = _hint(key, name, accepted)
            raise ConfigError(f"{key}.{name}: not an argument of {target_name}{hint}")
        value = setting(cfg, f"{key}.{name}")
        annotation = types.get(name)
        if annotation in ANNOTATED_TYPES and not matches_annotation(value, annotation):
            raise ConfigError(f"{key}.{name} must be {ANNOTATED_TYPES[annotation]}, got {value!r}")
        if isinstance(value, DictConfig) and "_target_" in value:
            check_constructor(cfg, f"{key}.{name}")
    for name in named:
        p = parameters[name]
        if p.default is p.empty and name not in node and name not in (*supplied, *from_run):
            raise ConfigError(f"{key}.{name}: required by {target_name}, not set")
    check_config = getattr(target, "check_config", None)
    if check_config is not None:
        check_config(cfg, key)


FILLED_BY_PAE = ("hydra", "logger", "callbacks")
"""Groups whose mandatory values (``???``: a logger's ``save_dir``, a checkpoint callback's
``dirpath``) pae fills in for each step."""


def check_missing(cfg: DictConfig) -> None:
    """No mandatory value (``???``) that the user must give is left unset (``FILLED_BY_PAE``
    aside): a ConfigError naming the first, in pae's one-line form."""

    def first_missing(node: Any, prefix: str) -> str | None:
        for name in node if isinstance(node, DictConfig) else range(len(node)):
            key = f"{prefix}{name}"
            if key in FILLED_BY_PAE:
                continue
            if OmegaConf.is_missing(node, name):
                return key
            if OmegaConf.is_interpolation(node, name):
                continue
            child = node[name]
            if isinstance(child, DictConfig | ListConfig):
                found = first_missing(child, f"{key}.")
                if found:
                    return found
        return None

    key = first_missing(cfg, "")
    if key is not None:
        raise ConfigError(f"{key} is required and not set: add {key}=... to the command line")
