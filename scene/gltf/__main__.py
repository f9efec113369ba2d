"""``python -m scene.gltf``: the command line (``scene.gltf.cli``)."""
from base.cli import run_cli
from scene.gltf.cli import __doc__ as doc
from scene.gltf.cli import run

if __name__ == "__main__":
    run_cli("gltf", run, doc=doc)
