"""``python -m motion.track``: see ``motion.track.cli``."""
from base.cli import run_cli
from motion.track.cli import __doc__ as doc
from motion.track.cli import run

run_cli("track", run, doc=doc)
