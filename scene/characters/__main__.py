"""python -m scene.characters: see the settings in configs/characters.yaml."""
from base.cli import run_cli
from scene.characters import __doc__ as doc
from scene.characters import run

if __name__ == "__main__":
    run_cli("characters", run, doc=doc)
