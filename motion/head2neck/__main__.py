"""python -m motion.head2neck: see the settings in configs/head2neck.yaml."""
from base.cli import run_cli
from motion.head2neck import __doc__ as doc
from motion.head2neck import run

if __name__ == "__main__":
    run_cli("head2neck", run, doc=doc)
