"""``python -m scene.preview``: the command line (``scene.preview.cli``)."""
from base.cli import run_cli
from scene.preview.cli import __doc__ as doc
from scene.preview.cli import run

if __name__ == "__main__":
    run_cli("preview", run, doc=doc)
