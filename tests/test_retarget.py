"""Retargeting: identity on the same character, anatomical rotations carried exactly, giraffe gains and
limits, the command line's outputs, and dual-quaternion skinning on the giraffe's twisted neck."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from base.cli import run_cli
from base.rotations import axis_angle_to_euler, euler_to_axis_angle, matrix_to_axis_angle
from data.assets import RigData
from data.joint_limits import RANGES_DEG, euler_limits
from data.mesh_io import read_obj, triangulate
from data.params import AnimationParams, check_rig, load_params, rig_checksum, save_params
from models.rig import HeadNeckModel
from motion.retarget import (
    GIRAFFE_GAINS,
    giraffe_limits,
    pose,
    reference_theta,
    retarget_params,
    retarget_theta,
    supports_skinning,
)
from motion.retarget import run as retarget_run
from scene.characters import build_giraffe


@pytest.fixture(scope="module")
def giraffe(builtin_rig) -> HeadNeckModel:
    return HeadNeckModel(build_giraffe(builtin_rig.rig))


def _random_theta(rig: HeadNeckModel, frames: int, seed: int = 0, margin: float = 0.9) -> torch.Tensor:
    """theta [T,J,3] in ``rig``'s bone frames with anatomical Euler angles uniform inside the human limits."""
    generator = torch.Generator().manual_seed(seed)
    lower, upper = euler_limits(margin)
    euler = lower + (upper - lower) * torch.rand(frames, rig.num_joints, 3, generator=generator)
    return rig.from_anatomical(euler_to_axis_angle(euler))


def _params(rig: HeadNeckModel, theta: torch.Tensor, rig_label: str, seed: int = 0) -> AnimationParams:
    frames = len(theta)
    rng = np.random.default_rng(seed)
    psi = rng.uniform(0, 1, (frames, len(rig.expression_names))) * (rng.uniform(size=(frames, 55)) < 0.1)
    with torch.no_grad():
        head = rig.head_rotation(theta).numpy()
    return AnimationParams(time=np.arange(frames) / 30.0, fps=30.0, psi=psi, tau=rng.uniform(-0.02, 0.04, frames),
                           eta=rng.uniform(0.5, 1.5, frames), theta=theta.numpy(), head_rotation=head,
                           joint_names=rig.joint_names, expression_names=rig.expression_names, rig=rig_label,
                           rig_checksum=rig_checksum(rig.rig), producers={"tool": "test"})


def _read_ply(path) -> np.ndarray:
    """Vertices [N,3] of a binary little-endian PLY as written by data.mesh_io.write_ply."""
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode("ascii")
    count = int(header.split("element vertex ")[1].split()[0])
    return np.frombuffer(raw[end:end + 12 * count], dtype="<f4").reshape(count, 3)


def _run(argv: list[str]) -> None:
    run_cli("retarget", retarget_run, argv=argv)


# ----------------------------------------------------------------------------- identity and frames


def test_human_to_the_same_human_is_the_identity(tmp_path, turned_rig, turned_rig_file):
    """Through the command line, on a rig whose bone frames are not anatomical (oc1 and c1c2 turned): the
    written theta is the source's and every written mesh is the rig's own forward pass (float32 PLY)."""
    theta = _random_theta(turned_rig, 6)
    params = _params(turned_rig, theta, str(turned_rig_file))
    source = tmp_path / "params.npz"
    save_params(source, params)
    _run([f"source={source}", "character=human", f"out_dir={tmp_path / 'out'}"])
    result = load_params(tmp_path / "out" / "params.npz")
    assert np.array_equal(result.theta, params.theta)
    assert np.array_equal(result.psi, params.psi) and np.array_equal(result.tau, params.tau)
    assert result.rig_checksum == params.rig_checksum
    with torch.no_grad():
        expected = turned_rig(theta, torch.as_tensor(params.psi), torch.as_tensor(params.tau),
                              torch.as_tensor(params.eta)).numpy()
    for frame in range(len(theta)):
        written = _read_ply(tmp_path / "out" / "meshes" / f"frame_{frame:05d}.ply")
        assert np.abs(written - expected[frame]).max() < 1e-5


def test_real_human_to_itself_is_the_identity(real_rig):
    theta = _random_theta(real_rig, 4, seed=3)
    params = _params(real_rig, theta, "real")
    result = retarget_params(params, real_rig, real_rig, "real")
    with torch.no_grad():
        expected = real_rig(theta, torch.as_tensor(params.psi), torch.as_tensor(params.tau),
                            torch.as_tensor(params.eta))
    posed = torch.cat([vertices for _, vertices in pose(real_rig, result)])
    assert (posed - expected).abs().max() < 1e-5


# ----------------------------------------------------------------------------- anatomical frames and gains


def test_anatomical_rotations_are_carried_exactly_with_unit_gains(turned_rig, giraffe):
    """Source: the built-in rig with turned oc1/c1c2 bone frames; target: the giraffe of the plain built-in
    rig.  Their bone axes differ, the anatomical rotations are equal."""
    theta = _random_theta(turned_rig, 50, seed=1)
    with torch.no_grad():
        out = retarget_theta(theta, turned_rig, giraffe)
    assert not torch.allclose(out, theta, atol=1e-3)                 # other bone axes
    assert torch.allclose(giraffe.to_anatomical(out), turned_rig.to_anatomical(theta), atol=1e-7)


def test_a_flexion_stays_a_flexion_on_the_giraffe(turned_rig, giraffe):
    """A nod (flexion at every joint) turns both heads about the lateral +x axis, face down."""
    for source, target in ((turned_rig, giraffe),):
        anatomical = torch.zeros(1, 8, 3)
        anatomical[0, :, 0] = 0.05
        theta = source.from_anatomical(anatomical)
        with torch.no_grad():
            for rig, value in ((source, theta), (target, retarget_theta(theta, source, target))):
                axis_angle = matrix_to_axis_angle(rig.head_rotation(value))[0]
                assert axis_angle[0] > 0.3 and axis_angle[1:].abs().max() < 1e-4 * axis_angle[0].item() + 1e-5


def test_giraffe_gains_move_the_base_more_and_keep_the_head_turn(builtin_rig, giraffe):
    """For a motion spread by the human ranges of motion, c7t1 takes 3x (flexion) / 2x (lateral) its human
    share and the chain's total stays the human's."""
    for pose_name, axis in (("flexion", 0), ("side-bend", 2), ("twist", 1)):
        theta = reference_theta(builtin_rig, pose_name)
        with torch.no_grad():
            out = retarget_theta(theta, builtin_rig, giraffe, GIRAFFE_GAINS, giraffe_limits())
            source_euler = axis_angle_to_euler(builtin_rig.to_anatomical(theta.double()))[0, :, axis]
            target_euler = axis_angle_to_euler(giraffe.to_anatomical(out.double()))[0, :, axis]
        fulcrum = {0: 3.0, 2: 2.0, 1: 1.0}[axis]
        assert target_euler[0].item() == pytest.approx(fulcrum * source_euler[0].item(), rel=1e-3)
        assert target_euler.sum().item() == pytest.approx(source_euler.sum().item(), rel=0.02)
    # the gains table itself: the other joints' common factor keeps sum(gain * range) per axis
    ranges = np.stack([RANGES_DEG[:, 0] + RANGES_DEG[:, 1], RANGES_DEG[:, 3], RANGES_DEG[:, 2]], 1)
    assert np.allclose((GIRAFFE_GAINS * ranges).sum(0), ranges.sum(0))


def test_gains_clamp_to_the_target_limits(builtin_rig, giraffe):
    anatomical = torch.zeros(3, 8, 3)
    anatomical[0, :, 0] = np.radians(30.0)      # far past every joint's flexion range
    anatomical[1, :, 2] = np.radians(-25.0)     # lateral bend past the ranges
    anatomical[2, :, 1] = np.radians(20.0)      # axial rotation
    theta = builtin_rig.from_anatomical(anatomical)
    lower, upper = giraffe_limits()
    with torch.no_grad():
        clamped = axis_angle_to_euler(giraffe.to_anatomical(
            retarget_theta(theta, builtin_rig, giraffe, GIRAFFE_GAINS, (lower, upper)).double())).float()
        free = axis_angle_to_euler(giraffe.to_anatomical(
            retarget_theta(theta, builtin_rig, giraffe, GIRAFFE_GAINS).double())).float()
    assert ((clamped >= lower - 1e-4) & (clamped <= upper + 1e-4)).all()
    assert not ((free >= lower - 1e-4) & (free <= upper + 1e-4)).all()
    # the fulcrum's limit is the human C7-T1 range x3: 13.5 degrees of flexion
    assert np.degrees(clamped[0, 0, 0].item()) == pytest.approx(3 * RANGES_DEG[0, 0], abs=0.05)


# ----------------------------------------------------------------------------- command line


def test_cli_retargets_onto_the_giraffe(tmp_path, builtin_rig):
    theta = _random_theta(builtin_rig, 5, seed=2)
    params = _params(builtin_rig, theta, "builtin")
    source = tmp_path / "params.npz"
    save_params(source, params)
    out = tmp_path / "giraffe"
    _run([f"source={source}", "character=giraffe", f"out_dir={out}", "mesh_format=obj"])
    character = RigData.load(out / "character.npz")
    result = load_params(out / "params.npz")
    check_rig(result, character, out / "params.npz")                    # its theta is in the giraffe's frames
    assert result.rig == str((out / "character.npz").resolve())
    target = HeadNeckModel(character)
    with torch.no_grad():
        expected_theta = retarget_theta(theta.double(), builtin_rig, target, GIRAFFE_GAINS, giraffe_limits()).float()
        expected = target(expected_theta, torch.as_tensor(result.psi), torch.as_tensor(result.tau),
                          torch.as_tensor(result.eta)).numpy()
    assert np.allclose(result.theta, expected_theta.numpy(), atol=1e-6)
    meshes = sorted((out / "meshes").glob("frame_*.obj"))
    assert [m.name for m in meshes] == [f"frame_{k:05d}.obj" for k in range(5)]
    mesh = read_obj(meshes[3])
    assert np.abs(mesh.vertices - expected[3]).max() < 1e-5                # written with 6 decimals
    assert mesh.uv_coords is not None and len(mesh.uv_coords) == len(character.uv_coords)
    assert np.array_equal(result.head_rotation, target.head_rotation(torch.as_tensor(result.theta)).detach().numpy())


def test_cli_writes_the_glb(tmp_path, builtin_rig):
    params = _params(builtin_rig, _random_theta(builtin_rig, 3, seed=4), "builtin")
    save_params(tmp_path / "params.npz", params)
    _run([f"source={tmp_path / 'params.npz'}", "character=giraffe", f"out_dir={tmp_path / 'out'}", "meshes=false",
          "export=[glb]"])
    glb = tmp_path / "out" / "animation.glb"
    assert glb.read_bytes()[:4] == b"glTF"


def test_cli_refuses_a_source_rig_that_does_not_match(tmp_path, capsys, builtin_rig, turned_rig_file):
    params = _params(builtin_rig, _random_theta(builtin_rig, 2), "builtin")
    save_params(tmp_path / "params.npz", params)
    with pytest.raises(SystemExit) as exit_info:
        _run([f"source={tmp_path / 'params.npz'}", f"rig={turned_rig_file}", f"out_dir={tmp_path / 'out'}"])
    assert exit_info.value.code == 2
    assert f"{tmp_path / 'params.npz'}: made with rig 'builtin'" in capsys.readouterr().err


def test_cli_rejects_bad_settings(tmp_path, capsys):
    for argv, message in ((["mode=picture"], "mode=picture needs out="),
                          (["source=a.npz", "out_dir=o", "skinning=cubic"], "skinning=cubic"),
                          (["source=a.npz", "out_dir=o", "joint_gains=[1,2]"], "joint_gains has 2 values"),
                          (["source=missing.npz", f"out_dir={tmp_path / 'o'}"], "missing.npz: file not found")):
        with pytest.raises(SystemExit):
            _run(argv)
        assert message in capsys.readouterr().err


# ----------------------------------------------------------------------------- DQS on the giraffe


def test_dqs_keeps_the_twisted_giraffe_neck_fuller_than_lbs(giraffe):
    """A 60-degree axial twist at a mid-neck joint (c4c5) of the giraffe: DQS loses at most half the volume
    and girth that LBS loses.  Volume: of the two bones' band of skin (signed tetrahedra from the joint);
    girth: the transition ring's distance from the twist axis (its circumference).  (Spread over all seven
    joints, 8.6 degrees each, LBS loses ~0.1 % of the neck's volume: too little to matter either way.)"""
    if not supports_skinning(giraffe, "dqs"):
        pytest.skip("models.rig has no dual-quaternion skinning yet (skinning='dqs')")
    joint = giraffe.joint_names.index("c4c5")
    anatomical = torch.zeros(1, 8, 3)
    anatomical[0, joint, 1] = np.radians(60.0)
    theta = giraffe.from_anatomical(anatomical)
    weights = giraffe.skin_weights.numpy()
    band = weights[:, joint - 1] + weights[:, joint] > 0.999               # skin of c5c6 and c4c5 only
    tri = triangulate(giraffe.rig.faces)
    tri = torch.as_tensor(tri[band[tri].all(1)], dtype=torch.long)
    ring = torch.as_tensor(band & (weights[:, joint] > 0.2) & (weights[:, joint] < 0.8))
    origin, axis = giraffe.rest_world[joint, :3, 3], giraffe.rest_world[joint, :3, 1]

    def measures(vertices: torch.Tensor) -> tuple[float, torch.Tensor]:
        corners = vertices[tri] - origin
        volume = torch.einsum("ti,ti->t", corners[:, 0], torch.cross(corners[:, 1], corners[:, 2], dim=-1)).sum() / 6
        rel = vertices[ring] - origin
        return float(volume), (rel - (rel @ axis)[:, None] * axis).norm(dim=-1)

    with torch.no_grad():
        volume0, radius0 = measures(giraffe(giraffe.neutral(1), eta=torch.zeros(1), skinning="lbs")[0])
        losses = {}
        for skinning in ("lbs", "dqs"):
            volume, radius = measures(giraffe(theta, eta=torch.zeros(1), skinning=skinning)[0])
            losses[skinning] = ((volume0 - volume) / abs(volume0), float(((radius0 - radius) / radius0).mean()))
    assert int(ring.sum()) >= 20 and len(tri) >= 100
    assert losses["lbs"][0] > 0.05 and losses["lbs"][1] > 0.03          # LBS collapses the twisted neck
    assert losses["dqs"][0] <= 0.5 * losses["lbs"][0]
    assert losses["dqs"][1] <= 0.5 * losses["lbs"][1]


def test_a_fitted_clip_keeps_its_fields_and_poses_the_person(tmp_path, builtin_rig):
    """A motion.fit clip onto character=human: placement, residual and shape_offset are kept and the meshes
    are the person's (template + offset) posed; onto the giraffe the offset is dropped, the placement kept."""
    import dataclasses

    from data.assets import with_shape_offset

    theta = _random_theta(builtin_rig, 3, seed=5)
    theta[:, 0] = 0.0
    rng = np.random.default_rng(3)
    offset = (0.4 * np.sin(builtin_rig.rig.template[:, [1, 2, 0]] / 7.0)).astype(np.float32)
    rotation = np.stack([np.eye(3)] * 3).astype(np.float32)
    params = dataclasses.replace(_params(builtin_rig, theta, "builtin"), root_rotation=rotation,
                                 root_translation=rng.normal(0, 10, (3, 3)), fit_rms_mm=rng.uniform(0, 1, 3),
                                 shape_offset=offset)
    save_params(tmp_path / "params.npz", params)
    _run([f"source={tmp_path / 'params.npz'}", "character=human", f"out_dir={tmp_path / 'human'}"])
    result = load_params(tmp_path / "human" / "params.npz")
    for name in ("root_rotation", "root_translation", "fit_rms_mm", "shape_offset"):
        assert np.array_equal(getattr(result, name), getattr(params, name)), name
    person = HeadNeckModel(with_shape_offset(builtin_rig.rig, offset))
    with torch.no_grad():
        expected = person(theta, torch.as_tensor(params.psi), torch.as_tensor(params.tau),
                          torch.as_tensor(params.eta)).numpy()
    written = _read_ply(tmp_path / "human" / "meshes" / "frame_00002.ply")
    assert np.abs(written - expected[2]).max() < 1e-5 and np.abs(offset).max() > 0.3
    _run([f"source={tmp_path / 'params.npz'}", "character=giraffe", f"out_dir={tmp_path / 'giraffe'}",
          "meshes=false"])
    giraffe = load_params(tmp_path / "giraffe" / "params.npz")
    assert giraffe.shape_offset is None and np.array_equal(giraffe.root_translation, params.root_translation)
    assert "shape_offset_dropped" in giraffe.producers
