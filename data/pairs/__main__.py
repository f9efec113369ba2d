"""``python -m data.pairs``: the command line (``data.pairs.cli``)."""
from base.cli import run_cli
from data.pairs.cli import __doc__ as doc
from data.pairs.cli import run

if __name__ == "__main__":
    run_cli("pairs", run, doc=doc)
