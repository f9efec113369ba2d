"""``python -m scene.normal_sequences``: the command line (``scene.normal_sequences.cli``)."""
from base.cli import run_cli
from scene.normal_sequences.cli import __doc__ as doc
from scene.normal_sequences.cli import run

if __name__ == "__main__":
    run_cli("normal_sequences", run, doc=doc)
