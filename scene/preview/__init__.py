"""Preview video of a clip (``python -m scene.preview``): the posed mesh rendered per frame, with a strip of tau
and the joint angles.

- :mod:`scene.preview.view`: views, framing camera, shading;
- :mod:`scene.preview.strip`: the strip under the render;
- :mod:`scene.preview.video`: panels, frames, the mp4 file;
- :mod:`scene.preview.cli`: the command line (its docstring: what a frame shows).
"""

from scene.preview.cli import PreviewConfig, run
from scene.preview.strip import (
    ANGLE_COLOURS_BGR,
    BAR_RANGE_DEG,
    STRIP_BOTTOM,
    STRIP_TOP,
    TAU_COLOUR_BGR,
    Strip,
    anatomical_degrees,
    make_strip,
)
from scene.preview.video import STRIP_FRACTION, Panel, PreviewReport, output_frames, preview_image, write_preview
from scene.preview.view import (
    ALBEDO_BGR,
    AMBIENT,
    BACKGROUND_BGR,
    LIGHT,
    MARGIN,
    SHADINGS,
    VIEWS,
    framing_camera,
    posed_vertices,
    shade,
    view_rotation,
)

__all__ = [
    "ALBEDO_BGR",
    "AMBIENT",
    "ANGLE_COLOURS_BGR",
    "BACKGROUND_BGR",
    "BAR_RANGE_DEG",
    "LIGHT",
    "MARGIN",
    "Panel",
    "PreviewConfig",
    "PreviewReport",
    "SHADINGS",
    "STRIP_BOTTOM",
    "STRIP_FRACTION",
    "STRIP_TOP",
    "Strip",
    "TAU_COLOUR_BGR",
    "VIEWS",
    "anatomical_degrees",
    "framing_camera",
    "make_strip",
    "output_frames",
    "posed_vertices",
    "preview_image",
    "run",
    "shade",
    "view_rotation",
    "write_preview",
]
