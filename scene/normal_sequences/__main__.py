"""python -m scene.normal_sequences: see the settings in configs/normal_sequences.yaml."""
from base.cli import run_cli
from scene.normal_sequences import __doc__ as doc
from scene.normal_sequences import run

if __name__ == "__main__":
    run_cli("normal_sequences", run, doc=doc)
