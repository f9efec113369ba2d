"""python -m scene.preview: see the settings in configs/preview.yaml."""
from base.cli import run_cli
from scene.preview import __doc__ as doc
from scene.preview import run

if __name__ == "__main__":
    run_cli("preview", run, doc=doc)
