"""Head orientation inputs of ``motion.head2neck``: recentring, captures with lost frames, empty files."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from base.errors import InputError
from base.files import save_npy
from motion.head2neck import read_head_rotations, recentered


def test_recentring_removes_the_subjects_offset_from_the_camera():
    """A subject sitting turned 30 degrees from the phone nods 20 degrees: after recentring, the input is a
    pure nod about the head's own left axis (x), not a nod mixed with a tilt."""
    offset = Rotation.from_euler("y", 30, degrees=True)
    nods = [Rotation.from_euler("x", a, degrees=True) for a in (0.0, 10.0, 20.0)]
    captured = torch.tensor(np.stack([(offset * nod).as_matrix() for nod in nods]), dtype=torch.float32)
    relative = recentered(captured).numpy()
    for nod, matrix in zip(nods, relative):
        np.testing.assert_allclose(matrix, nod.as_matrix(), atol=1e-6)
    assert Rotation.from_matrix(relative[2]).magnitude() == pytest.approx(np.radians(20.0), abs=1e-6)


def test_capture_with_lost_rows_is_resampled_to_its_rate(tmp_path):
    """Rows missing from a 30 fps capture (lost tracking) are interpolated: one output frame per 1/30 s
    from the first timestamp, so theta stays aligned with the take."""
    times = np.arange(12) / 30.0
    yaw = np.linspace(0.0, 0.33, 12)                       # a turn at a constant rate
    kept = [i for i in range(12) if i not in (4, 5, 6)]     # 0.1 s of lost tracking
    lines = ["timestamp,jawOpen,HeadYaw,HeadPitch,HeadRoll"]
    lines += [f"{times[i]:.6f},0.2,{yaw[i]:.6f},0.0,0.0" for i in kept]
    path = tmp_path / "take.csv"
    path.write_text("\n".join(lines) + "\n")
    head, description = read_head_rotations(path)
    assert head.shape == (12, 3, 3)
    assert "12 frames" in description and "30 fps" in description
    recovered = Rotation.from_matrix(head.numpy().astype(np.float64)).as_euler("YXZ")[:, 0]
    np.testing.assert_allclose(recovered, yaw, atol=1e-5)


@pytest.mark.parametrize("shape", [(0, 3), (0, 3, 3)])
def test_empty_input_names_the_file(tmp_path, shape):
    save_npy(tmp_path / "empty.npy", np.zeros(shape))
    with pytest.raises(InputError, match=r"empty\.npy: no frames"):
        read_head_rotations(tmp_path / "empty.npy")
