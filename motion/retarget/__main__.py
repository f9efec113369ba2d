"""python -m motion.retarget: see the settings in configs/retarget.yaml."""
from base.cli import run_cli
from motion.retarget import __doc__ as doc
from motion.retarget import run

if __name__ == "__main__":
    run_cli("retarget", run, doc=doc)
