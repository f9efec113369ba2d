"""Live: drive the neck and larynx from the Live Link Face stream while the face is being captured.

- :mod:`motion.live.packet`: one v6 datagram parsed (or refused with a reason) and encoded;
- :mod:`motion.live.stream`: one phone's stream, resampled causally, larynx step and head2neck per frame;
- :mod:`motion.live.receiver`: the UDP socket, routing, counting what is refused, bounded state;
- :mod:`motion.live.outputs`: params.npz, capture.csv and summary.json;
- :mod:`motion.live.config`, :mod:`motion.live.cli`: ``python -m motion.live``;
- :mod:`motion.live.send`: ``python -m motion.live.send``, a Live Link Face CSV replayed as datagrams.
"""
