"""``python -m motion.head2neck``: the command line (``motion.head2neck.cli``)."""
from base.cli import run_cli
from motion.head2neck.cli import __doc__ as doc
from motion.head2neck.cli import run

if __name__ == "__main__":
    run_cli("head2neck", run, doc=doc)
