"""Replay a Live Link Face CSV as version-6 datagrams: ``python -m motion.live.send``.

    python -m motion.live.send take=take.csv [host=127.0.0.1] [port=11111] [speed=1.0] [subject=...]
    python -m motion.live.send take=demo                      # the built-in demo take (data.demo_take)

For users without a phone at hand and for the tests.  Each CSV row is one datagram
(``motion.live.packet.encode``) carrying the row's own timecode (``HH:MM:SS:FF.fff`` -> frame number and
sub-frame at ``timecode_fps``, else the smallest standard rate above the largest frame seen, as
``base.timebase.parse_timecode`` guesses) and its 61 values as written (head angles as in the file:
radians in the Live Link Face CSVs we have).  Rows are sent at their timecode's pace divided by
``speed`` (``speed=0``: as fast as possible).  Rows the app wrote for lost tracking (``<timecode>,0``)
are not sent: a gap by frame number, which the receiver fills.
"""
from motion.live.send.cli import run
from motion.live.send.take import Take, read_take

__all__ = ["Take", "read_take", "run"]
