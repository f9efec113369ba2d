"""Preview video of a clip: the posed mesh rendered per frame, with tau and the joint angles as a strip.

    python -m scene.preview source=params.npz out=preview.mp4 [size=256] [view=front|side|three_quarter]
        [shading=shaded|normals] [fps=30] [second=giraffe_params.npz]

Each frame is the rig posed by the clip (``rig(theta, psi, tau, eta)``), rendered orthographically with the
project's rasteriser (``scene.render.render_normals``) from a view turned about the vertical axis
(front: from +z; side: from the subject's left, +x; three_quarter: half way), framed on the clip's
posed meshes, and shown shaded (Lambert, a light over the camera's shoulder) or as the normal map.  Under
it a strip plots the clip's tau and the cervical angles summed over the joints (flexion, axial rotation,
lateral bend in the anatomical frames, degrees) with a cursor at the frame, and bars of the 8 joints'
angles at the frame.  ``second=`` adds a second character beside it (e.g. the giraffe retargeted from
the same clip), each with its own strip.  The video is written with OpenCV (mp4v) through a temporary
file renamed when complete.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
from omegaconf import MISSING

from base.cli import register_config, to_dataclass
from base.errors import InputError
from base.files import atomic_path
from data.params import load_params
from scene.characters import resolve_rig
from scene.preview.video import Panel, PreviewReport, preview_image, write_preview
from scene.preview.view import SHADINGS, VIEWS


@dataclass
class PreviewConfig:
    """``python -m scene.preview`` settings (``configs/preview.yaml``).

    source: params.npz; out: the .mp4; rig: a rig file overriding the one recorded in source; size:
    pixels of each render (square, even); view: front | side | three_quarter; shading: shaded | normals;
    fps: video rate (None: the clip's); strip: draw the tau/angle strip; second: a second params.npz shown
    beside the first (e.g. the giraffe retargeted from it), second_rig: its rig override; still: also
    write this PNG of frame ``still_frame``.
    """

    source: str = MISSING
    out: str = MISSING
    rig: str | None = None
    size: int = 256
    view: str = "front"
    shading: str = "shaded"
    fps: float | None = None
    strip: bool = True
    second: str | None = None
    second_rig: str | None = None
    still: str | None = None
    still_frame: int = 0
    threads: int = 1

    def __post_init__(self) -> None:
        if self.view not in VIEWS:
            raise ValueError(f"view={self.view}: expected one of {', '.join(VIEWS)}")
        if self.shading not in SHADINGS:
            raise ValueError(f"shading={self.shading}: expected one of {', '.join(SHADINGS)}")
        if self.size < 32 or self.size % 2:
            raise ValueError(f"size={self.size}: expected an even number of pixels >= 32")
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"fps={self.fps}: expected a positive frame rate")


register_config("preview_schema", PreviewConfig)


def run(cfg) -> PreviewReport:
    """``python -m scene.preview``: render the clip(s) and print the report."""
    settings = to_dataclass(cfg, PreviewConfig, where="scene.preview")
    clips = [(settings.source, settings.rig)] + ([(settings.second, settings.second_rig)] if settings.second else [])
    panels = []
    for source, rig_override in clips:
        params = load_params(source)
        rig = resolve_rig(params, source, rig_override)
        panels.append(Panel.create(rig, params, settings.size, settings.view, settings.shading, settings.strip))
    if settings.still and not 0 <= settings.still_frame < len(panels[0].params):
        raise InputError(f"still_frame={settings.still_frame}: {settings.source} has frames "
                         f"0..{len(panels[0].params) - 1}")
    report = write_preview(settings.out, panels, settings.fps)
    print(report.summary())
    if settings.still:
        with atomic_path(settings.still) as tmp:
            if not cv2.imwrite(str(tmp), preview_image(panels, settings.still_frame)):
                raise OSError(f"{settings.still}: OpenCV could not write the image")
        print(f"wrote {settings.still}")
    return report
