"""``python -m motion.live.send``: the command line (``motion.live.send``)."""
from base.cli import run_cli
from motion.live.send import __doc__ as doc
from motion.live.send import run

if __name__ == "__main__":
    run_cli("live_send", run, doc=doc)
