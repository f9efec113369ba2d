"""``python -m motion.live``: the command line (``motion.live.cli``)."""
from base.cli import run_cli
from motion.live.cli import __doc__ as doc
from motion.live.cli import run

if __name__ == "__main__":
    run_cli("live", run, doc=doc)
