"""python -m models.pretrained: see the settings in configs/pretrained.yaml."""
import torch

from base.cli import run_cli
from models.pretrained import __doc__ as doc
from models.pretrained.cli import run

if __name__ == "__main__":
    torch.set_num_threads(1)
    run_cli("pretrained", run, doc=doc)
