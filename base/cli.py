"""The shell every command-line tool shares: structured hydra configs, one-line errors, exit status 2.

A tool's settings are a dataclass registered in hydra's ConfigStore (:func:`register_config`): the
dataclass is the schema and holds the defaults; ``configs/<tool>.yaml`` composes it
(``defaults: [<schema name>, _self_]``) and holds only what differs.  A tool's module ends with
``if __name__ == "__main__": run_cli("<tool>", run)``; ``run(cfg)`` does the work.

- Unknown keys, wrong types and unparsable overrides are rejected by hydra/OmegaConf while composing;
  required keys are ``MISSING`` (``???``).  Both, and bad input (``base.errors.InputError``) raised by
  the tool, print ``error: <message>`` on stderr and exit with status 2, without a traceback.
- ``--help`` prints the tool's docstring and its composed config.
- A top-level ``threads`` key sets torch's thread count.

The tools compose with hydra's compose API: they write no hydra run directory or logs, and relative
paths are relative to where you run.  ``train.py`` runs under ``hydra.main`` (run directories,
multirun) and reports what hydra cannot compose with :func:`config_error`.
"""
from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.core.config_store import ConfigStore
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import HydraException
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from base.errors import InputError

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
REQUIRED = MISSING  # "???": a setting the user must give (named on exit 2 when missing)


def register_config(name: str, node: type, group: str | None = None) -> None:
    """Register the dataclass ``node`` as config ``name`` (in ``group``) in hydra's ConfigStore."""
    ConfigStore.instance().store(name=name, node=node, group=group)


def _first_line(text: str) -> str:
    return " ".join(str(text).strip().splitlines()[:1]).strip()


def config_error(error: BaseException) -> InputError:
    """A hydra / OmegaConf composition error as one InputError line (the override and the reason)."""
    parts = [_first_line(error)]
    cause = error.__cause__ or error.__context__
    while cause is not None and len(parts) < 3:
        line = _first_line(cause)
        if line and line not in parts and "$VALUE" not in line:
            parts.append(line)
        cause = cause.__cause__ or cause.__context__
    return InputError(": ".join(p.rstrip(".") for p in parts if p))


def compose_config(config_name: str, overrides: Sequence[str]) -> DictConfig:
    """Compose ``configs/<config_name>.yaml`` with command-line ``overrides``; InputError on any error.

    Missing required keys (``???``, anywhere in the tree) are named in one InputError.
    """
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
            cfg = compose(config_name=config_name, overrides=list(overrides))
    except (HydraException, OmegaConfBaseException, ValueError) as e:
        raise config_error(e) from None
    finally:
        GlobalHydra.instance().clear()
    missing = missing_keys(cfg)
    if missing:
        raise InputError(f"missing {', '.join(f'{k}=...' for k in missing)} (see configs/{config_name}.yaml)")
    return cfg


def missing_keys(cfg, prefix: str = "") -> list[str]:
    """The dotted keys of ``cfg`` still at ``???`` (MISSING), depth first."""
    out = []
    for key in cfg.keys():
        if OmegaConf.is_missing(cfg, key):
            out.append(f"{prefix}{key}")
            continue
        value = cfg[key]
        if isinstance(value, DictConfig):
            out.extend(missing_keys(value, f"{prefix}{key}."))
    return out


def to_dataclass(section, cls: type | None = None, where: str = "config"):
    """A config section as its dataclass instance.

    A structured section (composed from a registered dataclass) converts to that dataclass; a plain
    mapping needs ``cls`` and is validated against it (unknown keys, wrong types).  A ValueError from
    the dataclass's own validation (``__post_init__``) becomes an InputError naming ``where``.
    """
    try:
        if cls is not None:
            merged = OmegaConf.merge(OmegaConf.structured(cls), section)
        else:
            merged = section
        obj = OmegaConf.to_object(merged)
    except OmegaConfBaseException as e:
        raise InputError(f"{where}: {config_error(e)}") from None
    except ValueError as e:
        raise InputError(f"{where}: {e}") from None
    if not dataclasses.is_dataclass(obj):
        raise TypeError(f"{where}: not a structured config section (give cls=...)")
    unknown = unknown_keys(merged, type(obj))
    if unknown:  # keys forced in with '+key=...' slip past the schema
        raise InputError(f"{where}: unknown keys {unknown}; known: {sorted(f.name for f in dataclasses.fields(obj))}")
    return obj


def unknown_keys(section, cls: type, prefix: str = "") -> list[str]:
    """Dotted keys of ``section`` that are not fields of the dataclass ``cls`` (nested dataclasses too)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    out = []
    for key in section.keys():
        if key not in fields:
            out.append(f"{prefix}{key}")
            continue
        value = section[key]
        factory = fields[key].default_factory
        nested = factory() if factory is not dataclasses.MISSING else None
        if isinstance(value, DictConfig) and dataclasses.is_dataclass(nested):
            out.extend(unknown_keys(value, type(nested), f"{prefix}{key}."))
    return out


def run_cli(config_name: str, run: Callable, argv: Sequence[str] | None = None, doc: str | None = None) -> None:
    """Compose the tool's config from the command line and call ``run(cfg)``; exit 2 on bad input."""
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        if "--help" in argv or "-h" in argv:
            GlobalHydra.instance().clear()
            with initialize_config_dir(config_dir=str(CONFIGS), version_base=None):
                cfg = compose(config_name=config_name)
            GlobalHydra.instance().clear()
            print((doc or "").strip() + f"\n\nSettings (configs/{config_name}.yaml), as key=value:\n")
            print(OmegaConf.to_yaml(cfg))
            return
        cfg = compose_config(config_name, argv)
        if cfg.get("threads"):
            import torch  # here: the shell serves tools that need no torch

            torch.set_num_threads(int(cfg.threads))
        run(cfg)
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)


def as_list(value) -> list:
    """A config value that may be one item or a list (``at=2.0``, ``at=[1,2]``, ``inputs=a.csv``) as a list.

    None is the empty list; a string is one item (not its characters).
    """
    if value is None:
        return []
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        return [value]
    return list(value)
