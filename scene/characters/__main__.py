"""``python -m scene.characters``: the command line (``scene.characters.cli``)."""
from base.cli import run_cli
from scene.characters.cli import __doc__ as doc
from scene.characters.cli import run

if __name__ == "__main__":
    run_cli("characters", run, doc=doc)
