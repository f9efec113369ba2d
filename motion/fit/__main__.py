"""``python -m motion.fit``: see ``motion.fit.cli``."""
from base.cli import run_cli
from motion.fit.cli import __doc__ as doc
from motion.fit.cli import run

run_cli("fit", run, doc=doc)
