"""The shell every command-line tool shares: hydra config from ``configs/<name>.yaml``, clean errors.

A tool's module ends with ``if __name__ == "__main__": run_cli("<name>", run)``; ``run(cfg)`` does
the work.  Required keys are ``???`` in the tool's config.  Bad input (``data.errors.InputError``) or a
missing required key prints ``error: <message>`` on stderr and exits with status 2, without a
traceback.  A config's ``threads`` key sets torch's thread count.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Callable, Iterable, Sequence, TypeVar

from data.errors import InputError

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
Config = TypeVar("Config")


def config_dataclass(cls: type[Config], section, where: str, other_keys: Iterable[str] = ()) -> Config:
    """The settings dataclass ``cls`` from a config section (a DictConfig or a mapping).

    Every key of ``section`` must be a field of ``cls`` or one of ``other_keys`` (the section's settings
    for something else, not passed to ``cls``); any other key is an InputError naming ``where``, the
    unknown and the known keys.  Lists become tuples where the field's default is a tuple; a ValueError from the dataclass's
    own validation becomes an InputError naming ``where``.
    """
    from omegaconf import DictConfig, OmegaConf

    values = OmegaConf.to_container(section, resolve=True) if isinstance(section, DictConfig) else dict(section)
    known = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(known) - set(other_keys))
    if unknown:
        raise InputError(f"{where}: unknown keys {unknown}; known: {sorted(set(known) | set(other_keys))}")
    values = {k: v for k, v in values.items() if k in known}
    for name, value in values.items():
        if isinstance(value, list) and isinstance(known[name].default, tuple):
            values[name] = tuple(value)
    try:
        return cls(**values)
    except ValueError as e:  # a value out of range: bad input, reported without a traceback
        raise InputError(f"{where}: {e}") from None


def missing_keys(cfg, keys: tuple[str, ...] | None = None) -> list[str]:
    """The top-level keys of ``cfg`` (or of ``keys``) still at ``???``."""
    from omegaconf import OmegaConf

    return [k for k in (keys or cfg.keys()) if OmegaConf.is_missing(cfg, k)]


def run_cli(config_name: str, run: Callable) -> None:
    import hydra

    @hydra.main(version_base=None, config_path=str(CONFIGS), config_name=config_name)
    def main(cfg) -> None:
        try:
            missing = missing_keys(cfg)
            if missing:
                raise InputError(f"missing {', '.join(f'{k}=...' for k in missing)} "
                                 f"(see configs/{config_name}.yaml)")
            if cfg.get("threads"):
                import torch

                torch.set_num_threads(int(cfg.threads))
            run(cfg)
        except InputError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)

    main()


def as_list(value) -> list:
    """A config value that may be one item or a list (``at=2.0``, ``at=[1,2]``, ``inputs=a.csv``) as a list.

    None is the empty list; a string is one item (not its characters).
    """
    if value is None:
        return []
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        return [value]
    return list(value)
