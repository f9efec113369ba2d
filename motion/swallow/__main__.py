"""``python -m motion.swallow``: the command line (``motion.swallow.cli``)."""
from base.cli import run_cli
from motion.swallow.cli import __doc__ as doc
from motion.swallow.cli import run

if __name__ == "__main__":
    run_cli("swallow", run, doc=doc)
