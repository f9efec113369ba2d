"""infer.py end to end: expressions -> tau, head rotation -> theta, swallows inserted, meshes written."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from data.files import write_csv

from data.tau_track import read_tau_track
from data.synthetic_tau import swallow_profile
from models.checkpoint import save_checkpoint
from models.head2neck import build_model
from motion.swallow import SwallowTemplate, write_template

REPO = __import__("pathlib").Path(__file__).resolve().parents[1]


def test_capture_to_meshes(tmp_path, builtin_rig):
    # An untrained head2neck model is the range-of-motion split; the correction makes it exact.
    head2neck = tmp_path / "h2n.pt"
    config = {"rest_rotations": builtin_rig.anatomical_rest_rotations.tolist(), "hidden": [16, 16],
              "activation": "silu", "residual_scale": 0.1}
    save_checkpoint(head2neck, {"task": "head2neck", "model_config": config, "model": build_model(config).state_dict(),
                                "step": 0})
    time = np.arange(90) / 30.0
    yaw = 0.4 * np.sin(2 * np.pi * time / 3.0)  # head turns left and right, radians
    write_csv(tmp_path / "take.csv", {"time": time, "jawOpen": 0.3 + 0.2 * np.sin(time * 5), "HeadYaw": yaw,
                                      "HeadPitch": np.full(90, 0.1), "HeadRoll": np.zeros(90)}, float_format="%.9g")
    template_time = np.arange(0, 1.2, 1 / 60)
    write_template(tmp_path / "swallow.csv", SwallowTemplate(template_time, swallow_profile(template_time),
                                                             np.zeros_like(template_time), 60.0))
    result = subprocess.run(
        [sys.executable, "infer.py", f"expressions={tmp_path / 'take.csv'}", f"out={tmp_path / 'tau.csv'}",
         f"head2neck={head2neck}", f"theta_out={tmp_path / 'theta.npy'}",
         f"swallow_template={tmp_path / 'swallow.csv'}", "swallow_at=[1.0]", f"meshes={tmp_path / 'meshes'}"],
        cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    track = read_tau_track(tmp_path / "tau.csv")
    assert len(track) == 90 and track.fps == 30.0
    peak = track.time[np.argmax(track.tau)]
    assert abs(peak - (1.0 + 0.4 * 1.1)) < 0.1  # the swallow's peak sits 40% into its 1.1 s
    assert 0.045 < track.tau.max() < 0.065 and abs(track.tau[:20]).max() < 1e-6  # no larynx model: rest elsewhere
    theta = np.load(tmp_path / "theta.npy")
    assert theta.shape == (90, 8, 3)
    head = builtin_rig.head_rotation(torch.tensor(theta)).numpy()
    target = Rotation.from_euler("YX", np.stack([yaw, np.full(90, 0.1)], 1)).as_matrix()
    angle = np.degrees(Rotation.from_matrix(np.einsum("tji,tjk->tik", head, target)).magnitude())
    assert angle.max() < 0.1
    meshes = sorted((tmp_path / "meshes").glob("frame_*.ply"))
    assert len(meshes) == 90
    body = meshes[45].read_bytes().split(b"end_header\n", 1)[1]
    vertices = np.frombuffer(body[: builtin_rig.num_vertices * 12], dtype="<f4").reshape(-1, 3)
    psi = torch.zeros(1, 55)
    psi[0, builtin_rig.expression_names.index("jawOpen")] = 0.3 + 0.2 * np.sin(1.5 * 5)
    expected = builtin_rig(torch.tensor(theta[45:46]), psi, torch.tensor([track.tau[45]], dtype=torch.float32))[0]
    assert np.abs(vertices - expected.numpy()).max() < 1e-3


def compose_infer(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return compose("infer", overrides=overrides)


@pytest.mark.parametrize("overrides, message", [
    ([], "nothing to write"),
    (["out=OUT", "swallow_at=[0.5]"], r"swallows need both swallow_template=.* and swallow_at=.*got swallow_template=None"),
    (["out=OUT", "swallow_template=TEMPLATE"], r"swallows need both .*swallow_at=\[\]"),
    (["out=OUT", "swallow_template=TEMPLATE", "swallow_at=20.0"],              # one onset without brackets
     r"swallow_at=\[20\.0\] in .*take\.csv: .*a swallow at 20 s"),
    (["meshes=OUT", "mesh_format=stl"], r"mesh_format=stl: expected one of ply, obj"),
    (["out=OUT/tau.csv", "meshes=USED"], r"meshes=.*used: already holds 1 output file\(s\) of an earlier run"),
    (["out=OUT", "swallow_template=TEMPLATE", "swallow_at=[20.0]"],
     r"swallow_at=\[20\.0\] in .*take\.csv: .*a swallow at 20 s spans .* outside the track \[0\.00, 2\.97\] s"),
    (["out=OUT", "swallow_template=TEMPLATE", "swallow_at=[1.0]", "swallow_playback.blend=mix"],
     r"swallow_playback \(configs/infer\.yaml\): SwallowConfig\.blend must be 'replace' or 'add', got 'mix'"),
])
def test_bad_requests_are_named_and_nothing_is_written(tmp_path, overrides, message):
    from data.errors import InputError
    from infer import run

    write_csv(tmp_path / "take.csv", {"time": np.arange(90) / 30, "jawOpen": np.zeros(90)})  # a neutral face
    template_time = np.arange(0, 1.2, 1 / 60)
    write_template(tmp_path / "template.csv", SwallowTemplate(template_time, swallow_profile(template_time),
                                                              np.zeros_like(template_time), 60.0))
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "frame_00000.ply").write_text("")
    paths = {"OUT": str(tmp_path / "out"), "TEMPLATE": str(tmp_path / "template.csv"), "USED": str(tmp_path / "used")}
    overrides = [o.replace("OUT", paths["OUT"]).replace("TEMPLATE", paths["TEMPLATE"]).replace("USED", paths["USED"])
                 for o in overrides]
    with pytest.raises(InputError, match=message):
        run(compose_infer([f"expressions={tmp_path / 'take.csv'}", *overrides]))
    assert not (tmp_path / "out").exists()


def test_playback_settings_mirror_the_swallow_config():
    """configs/infer.yaml's swallow_playback holds SwallowConfig's playback fields at their defaults."""
    import dataclasses

    import yaml

    from motion.swallow import SwallowConfig

    with open(REPO / "configs" / "infer.yaml") as f:
        playback = yaml.safe_load(f)["swallow_playback"]
    defaults = dataclasses.asdict(SwallowConfig())
    assert playback == {k: defaults[k] for k in ("fade_seconds", "blend", "rest_window_seconds")}


def test_missing_required_keys_are_named_with_exit_status_2():
    result = subprocess.run([sys.executable, "-m", "data.pairs", "out=x.npz"], cwd=REPO, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 2 and "error: missing track=..., expressions=... (see configs/pairs.yaml)" in result.stderr
