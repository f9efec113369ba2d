"""``python -m motion.voice``: the command line (``motion.voice.cli``)."""
from base.cli import run_cli
from motion.voice.cli import __doc__ as doc
from motion.voice.cli import run

if __name__ == "__main__":
    run_cli("voice", run, doc=doc)
