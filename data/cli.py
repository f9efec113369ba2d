"""The shell every command-line tool shares: hydra config from ``configs/<name>.yaml``, clean errors.

A tool's module ends with ``if __name__ == "__main__": run_cli("<name>", run)``; ``run(cfg)`` does
the work.  Bad input (``data.io.InputError``) prints ``error: <message>`` on stderr and exits with
status 2, without a traceback.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Callable

from data.io import InputError

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def run_cli(config_name: str, run: Callable) -> None:
    import hydra

    @hydra.main(version_base=None, config_path=str(CONFIGS), config_name=config_name)
    def main(cfg) -> None:
        try:
            run(cfg)
        except InputError as e:
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)

    main()
