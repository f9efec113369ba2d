"""python -m scene.gltf: see the settings in configs/gltf.yaml."""
from base.cli import run_cli
from scene.gltf import __doc__ as doc
from scene.gltf import run

if __name__ == "__main__":
    run_cli("gltf", run, doc=doc)
