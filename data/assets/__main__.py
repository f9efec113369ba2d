"""``python -m data.assets``: the command line (``data.assets.cli``)."""
from base.cli import run_cli
from data.assets.cli import __doc__ as doc
from data.assets.cli import run

if __name__ == "__main__":
    run_cli("assets", run, doc=doc)
