"""python -m data.pairs: see the settings in configs/pairs.yaml."""
from base.cli import run_cli
from data.pairs import __doc__ as doc
from data.pairs import run

if __name__ == "__main__":
    run_cli("pairs", run, doc=doc)
