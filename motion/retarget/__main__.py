"""``python -m motion.retarget``: the command line (``motion.retarget.cli``)."""
from base.cli import run_cli
from motion.retarget.cli import __doc__ as doc
from motion.retarget.cli import run

if __name__ == "__main__":
    run_cli("retarget", run, doc=doc)
