"""Expression/larynx pairs: the captured training data of the expression -> larynx transformer.

- :mod:`data.pairs.files`: :class:`LarynxSequence` and pair files (read, write, split by take), optionally
  with the voice's F0 per frame (``f0``, for ``python -m motion.voice mode=fit``);
- :mod:`data.pairs.align`: a tau track and an expression recording aligned into a pair;
- :mod:`data.pairs.cli`: ``python -m data.pairs`` (its docstring: the pair file's layout).
"""

from data.pairs.align import align_pair
from data.pairs.cli import run
from data.pairs.files import LarynxSequence, load_pair, load_pairs, save_pair, split_by_take, take_from_name

__all__ = [
    "LarynxSequence",
    "align_pair",
    "load_pair",
    "load_pairs",
    "run",
    "save_pair",
    "split_by_take",
    "take_from_name",
]
