"""python -m data.assets: see the settings in configs/assets.yaml."""
from base.cli import run_cli
from data.assets import __doc__ as doc
from data.assets import run

if __name__ == "__main__":
    run_cli("assets", run, doc=doc)
