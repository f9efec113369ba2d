"""Drive HACK's cervical spine from head orientations: ``python -m motion.head2neck``.

- :mod:`motion.head2neck.inputs`: head orientation files read as rotations [T,3,3], recentring;
- :mod:`motion.head2neck.loading`: the model and the rig it poses;
- :mod:`motion.head2neck.cli`: the command line (its docstring: inputs, conventions, outputs).
"""

from motion.head2neck.cli import run
from motion.head2neck.inputs import UNITS, head_rotations_from_ypr, read_head_rotations, recentered
from motion.head2neck.loading import load_head2neck

__all__ = ["UNITS", "head_rotations_from_ypr", "load_head2neck", "read_head_rotations", "recentered", "run"]
