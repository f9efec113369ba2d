"""Figures: matplotlib on the file-only Agg backend, saved atomically."""
from __future__ import annotations

import os

from base.files import atomic_path


def figure(**subplots):
    """A matplotlib figure and its axes (``plt.subplots(**subplots)``) on the file-only Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(**subplots)


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> None:
    """Save a figure atomically (format from the suffix) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
