"""Inference: ``python infer.py checkpoint=runs/.../checkpoints/last.pt expressions=take.csv out=tau.csv [fps=..]``.

Reads an expression recording (any format ``data.expressions.read_expressions`` reads: Live Link
Face, ARKit or HACK-named CSV, header-less CSV or ``.npy`` with ``fps=``), resamples it to the
model's frame rate, streams the expression -> larynx transformer over it and writes the tau track
(``data.io.write_tau_track``: CSV ``frame,time,tau,fps`` with time in seconds on the recording's
clock, or a ``.npy`` vector).  tau is in UV units of the larynx map (+ = up the neck).

The shell is: read the inputs -> one ``predict_*`` function per output -> write the outputs.
Further outputs (head orientation -> cervical theta, mesh export) add their own predict/write pair.
"""
from __future__ import annotations

from pathlib import Path

import hydra
import torch
from omegaconf import DictConfig

from data.expressions import ExpressionTrack, read_expressions
from data.io import InputError, TauTrack, write_tau_track
from models.checkpoint import load_model
from models.larynx_transformer import predict_tau


def predict_larynx(checkpoint: str | Path, expressions: ExpressionTrack, subject: str | None = None) -> TauTrack:
    """The tau track the transformer of ``checkpoint`` predicts for a recording, at the model's rate."""
    model, _ = load_model(checkpoint, task="larynx_transformer")
    resampled = expressions.resampled(model.fps)
    tau = predict_tau(model, resampled.psi, subject)
    return TauTrack(tau, resampled.time, model.fps, source=f"{expressions.source} via {checkpoint}")


@hydra.main(version_base=None, config_path="configs", config_name="infer")
def main(cfg: DictConfig) -> None:
    torch.set_num_threads(int(cfg.threads))
    try:
        expressions = read_expressions(cfg.expressions, fps=cfg.fps)
        larynx = predict_larynx(cfg.checkpoint, expressions, None if cfg.subject is None else str(cfg.subject))
    except InputError as e:
        raise SystemExit(f"error: {e}") from None
    write_tau_track(cfg.out, larynx)
    print(f"{cfg.out}: tau for {len(larynx)} frames at {larynx.fps:g} fps "
          f"({larynx.time[-1] - larynx.time[0]:.2f} s of {cfg.expressions})")


if __name__ == "__main__":
    main()
