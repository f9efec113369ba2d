"""Characters: the procedural giraffe (topology, neck, weights, expressions, larynx, no self-intersection),
deformation transfer, the self-intersection check, and characters from an OBJ + joints JSON."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from base.cli import run_cli
from base.errors import InputError
from data.assets import JOINT_NAMES, RigData
from data.mesh_io import triangulate, write_obj
from data.procedural_rig import build_procedural_rig
from models.rig import HeadNeckModel
from scene.characters import (
    GiraffeSettings,
    build_giraffe,
    chain_length,
    character_from_obj,
    character_kind,
    deformation_transfer,
    giraffe_geometry,
    load_character,
    new_self_intersections,
    read_joints_json,
    rest_world,
    self_intersections,
)
from scene.characters import (
    run as characters_run,
)

SETTINGS = GiraffeSettings()


@pytest.fixture(scope="module")
def human() -> RigData:
    return build_procedural_rig()


@pytest.fixture(scope="module")
def giraffe(human) -> RigData:
    return build_giraffe(human, SETTINGS)


@pytest.fixture(scope="module")
def geometry(human):
    return giraffe_geometry(human, SETTINGS)


@pytest.fixture(scope="module")
def real_human(real_rig) -> RigData:
    return real_rig.rig


@pytest.fixture(scope="module")
def real_giraffe(real_human) -> RigData:
    return build_giraffe(real_human, SETTINGS)


def _edges(faces: np.ndarray) -> np.ndarray:
    tri = triangulate(faces)
    return np.unique(np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1), axis=0)


def _project_on_chain(points: np.ndarray, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Arc position of each point's nearest point on the joint polyline, and the joints' arc positions."""
    segments = np.diff(joints, axis=0)
    lengths = np.linalg.norm(segments, axis=1)
    starts = np.r_[0.0, np.cumsum(lengths)]
    best, arc = np.full(len(points), np.inf), np.zeros(len(points))
    for k, (segment, length) in enumerate(zip(segments, lengths)):
        t = np.clip((points - joints[k]) @ segment / length**2, 0.0, 1.0)
        distance = np.linalg.norm(points - (joints[k] + t[:, None] * segment), axis=1)
        closer = distance < best
        best[closer], arc[closer] = distance[closer], starts[k] + t[closer] * length
    return arc, starts


# ----------------------------------------------------------------------------- topology and proportions


def _check_topology(source: RigData, character: RigData) -> None:
    assert character.template.shape == source.template.shape
    assert np.array_equal(character.faces, source.faces)
    assert np.array_equal(character.uv_coords, source.uv_coords)
    assert np.array_equal(character.faces_uv, source.faces_uv)
    assert np.array_equal(character.vertex_uv, source.vertex_uv)
    assert list(character.joint_names) == list(JOINT_NAMES)
    assert character.expression_deltas.shape == source.expression_deltas.shape


def test_giraffe_keeps_vertex_count_faces_and_uvs(human, giraffe):
    _check_topology(human, giraffe)
    assert character_kind(giraffe) == "giraffe" and character_kind(human) == "human"


def _neck(rig: RigData) -> tuple[float, np.ndarray, np.ndarray]:
    joints = rest_world(rig)[:, :3, 3]
    return chain_length(joints), np.linalg.norm(np.diff(joints, axis=0), axis=1), joints


def _check_neck(human: RigData, giraffe: RigData) -> None:
    human_length, _, _ = _neck(human)
    length, bones, joints = _neck(giraffe)
    assert length / human_length == pytest.approx(SETTINGS.neck_factor, rel=1e-3)   # several-fold
    # vertebrae re-spaced: C7..C2 one length, the atlas atlas_share of it
    assert np.ptp(bones[:6]) < 1e-3 * bones[0]
    assert bones[6] == pytest.approx(SETTINGS.atlas_share * bones[0], rel=1e-3)
    # the stretched rest neck (the middle vertebrae) leans forward by about incline_deg from vertical
    lean = np.degrees(np.arctan2(np.diff(joints, axis=0)[1:5, 2], np.diff(joints, axis=0)[1:5, 1]))
    assert np.abs(lean - SETTINGS.incline_deg).max() < 5.0
    # the skin follows: the head's lowest point is several times further from T1 along the neck
    head = human.skin_weights[:, -1] > 0.99

    def gap(rig: RigData) -> float:
        chain = rest_world(rig)[:, :3, 3]
        axis = (chain[-1] - chain[0]) / np.linalg.norm(chain[-1] - chain[0])
        return float(((rig.template[head] - chain[0]) @ axis).min())

    assert gap(giraffe) > 3.0 * max(gap(human), 1.0)


def test_giraffe_neck_several_fold_longer_inclined_with_respaced_vertebrae(human, giraffe):
    _check_neck(human, giraffe)


def test_giraffe_keeps_the_anatomical_frames_and_the_head_rotation(turned_rig):
    """Bones keep their own axes relative to anatomy (a turned c1c2, the release-like oc1), so the anatomical
    axes of source and giraffe agree, and the head's rest rotation is the source's."""
    source = turned_rig
    giraffe = HeadNeckModel(build_giraffe(source.rig))
    assert torch.equal(giraffe.anatomical_axes, source.anatomical_axes)
    assert torch.allclose(giraffe.rest_world[-1, :3, :3], source.rest_world[-1, :3, :3], atol=1e-6)


def test_giraffe_from_the_real_rig(real_human, real_giraffe):
    _check_topology(real_human, real_giraffe)
    _check_neck(real_human, real_giraffe)


# ----------------------------------------------------------------------------- self-intersection


def test_self_intersection_check_finds_crossings_and_ignores_contact():
    vertices = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0],                  # a triangle in z = 0
                         [0.5, 0.5, -1], [0.5, 0.5, 1], [1.5, 1.5, 0.5],   # one piercing it
                         [0, 0, 0], [-1, 0, 1], [0, -1, 1]], float)       # touching at (0,0,0) only
    faces = np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]])
    assert self_intersections(vertices, faces).tolist() == [[0, 1]]
    # sharing the vertex (index 0 instead of the coincident 6): contact, not crossing
    assert self_intersections(vertices, np.array([[0, 1, 2], [0, 7, 8]])).tolist() == []


def test_self_intersection_check_on_a_mesh(human):
    """The built-in template has none; pushing the front of the neck through the back makes some."""
    assert len(self_intersections(human.template, human.faces)) == 0
    pushed = human.template.astype(np.float64).copy()
    front = (np.abs(pushed[:, 1] + 10.0) < 1.5) & (pushed[:, 2] > 0) & (np.abs(pushed[:, 0]) < 2.0)
    pushed[front, 2] -= 12.0
    assert len(self_intersections(pushed, human.faces)) > 0


def test_giraffe_does_not_intersect_itself_at_rest(human, giraffe):
    assert len(self_intersections(giraffe.template, giraffe.faces)) == 0
    assert len(new_self_intersections(human.template, giraffe.template, human.faces)) == 0


def test_real_giraffe_adds_no_self_intersection(real_human, real_giraffe):
    # the release's template crosses itself at the lip corners; the giraffe must add nothing
    assert len(new_self_intersections(real_human.template, real_giraffe.template, real_human.faces)) == 0


# ----------------------------------------------------------------------------- skinning


def _check_weights(character: RigData, human: RigData) -> None:
    weights = character.skin_weights
    assert np.allclose(weights.sum(1), 1.0, atol=1e-5) and weights.min() >= 0
    bound = weights > 1e-6
    assert bound.sum(1).max() <= 2
    pairs = bound.sum(1) == 2
    joints_of = np.argsort(-weights[pairs], axis=1)[:, :2]
    assert (np.abs(joints_of[:, 0] - joints_of[:, 1]) == 1).all()          # only adjacent joints share a vertex
    # No far joint: each bound bone's span along the chain is within one bone length of the vertex's
    # projection on the chain; the source's weights on the giraffe mesh fail it (the release binds the
    # neck at C5-C6 level half to the skull, 40 cm up the giraffe's neck).
    joints = rest_world(character)[:, :3, 3]
    arc, starts = _project_on_chain(character.template.astype(np.float64), joints)
    ends = np.r_[starts[1:], np.inf]
    bone = np.diff(starts).max()

    def farthest(w: np.ndarray) -> float:
        gap = [np.where(w[:, j] > 1e-3, np.maximum(starts[j] - arc, 0) + np.maximum(arc - ends[j], 0), 0).max()
               for j in range(len(joints))]
        return float(max(gap))

    assert farthest(weights) < bone
    assert farthest(human.skin_weights) > 2 * bone


def _check_smooth(character: RigData, level: np.ndarray, settings: GiraffeSettings) -> None:
    """Weights change across mesh edges no faster along the chain than the transition slope allows, and
    barely around it (edges at one level)."""
    edges = _edges(character.faces)
    w = character.skin_weights.astype(np.float64)
    dw = np.abs(w[edges[:, 0]] - w[edges[:, 1]]).max(1)
    dl = np.abs(level[edges[:, 0]] - level[edges[:, 1]])
    bones = np.diff(rest_world(character)[:, :3, 3], axis=0)
    narrowest = settings.weight_blend * 0.5 * np.linalg.norm(bones, axis=1).min()
    assert (dw <= 1.5 / narrowest * dl + 1e-5).all()          # smoothstep's slope 1.5 over its width
    assert dw[dl < 0.05].max() < 0.1


def test_giraffe_weights_smooth_along_the_chain_and_bound_near(human, giraffe, geometry):
    _check_weights(giraffe, human)
    _check_smooth(giraffe, geometry.level, SETTINGS)


def test_real_giraffe_weights(real_human, real_giraffe):
    _check_weights(real_giraffe, real_human)
    _check_smooth(real_giraffe, giraffe_geometry(real_human, SETTINGS).level, SETTINGS)


# ----------------------------------------------------------------------------- deformation transfer


def test_deformation_transfer_of_a_pure_scaling_gives_the_scaled_deltas(human):
    scale = 1.7
    deltas = deformation_transfer(human.template, human.expression_deltas, scale * human.template, human.faces)
    expected = scale * human.expression_deltas.astype(np.float64)
    assert np.abs(deltas - expected).max() < 1e-4 * np.abs(expected).max()


def _check_jaw(human: RigData, giraffe: RigData, geometry) -> None:
    k = list(human.expression_names).index("jawOpen")
    moved = np.linalg.norm(giraffe.expression_deltas[k], axis=1)
    muzzle = geometry.muzzle_shift > 0.5 * geometry.muzzle_shift.max()
    neck = (geometry.level > 0.1 * geometry.chain_cm) & (geometry.level < 0.8 * geometry.head_start)
    assert muzzle.sum() > 50 and neck.sum() > 200
    assert moved[muzzle].mean() > 8.0 * moved[neck].mean()
    assert muzzle[int(np.argmax(moved))]                                # the biggest motion is on the muzzle
    # The mouth opens: the jaw (the 2 % of vertices the human's jawOpen moves most) goes down and away
    # from the nose (noseSneer's most moved vertices), at least as far as on the human.
    source = np.linalg.norm(human.expression_deltas[k], axis=1)
    jaw = np.argsort(source)[-len(source) // 50:]
    nose = np.argsort(np.linalg.norm(human.expression_deltas[list(human.expression_names).index("noseSneer_L")],
                                     axis=1))[-20:]

    def opening(rig: RigData) -> float:
        rest, delta = rig.template.astype(np.float64), rig.expression_deltas[k]
        before = np.linalg.norm(rest[jaw].mean(0) - rest[nose].mean(0))
        return np.linalg.norm((rest + delta)[jaw].mean(0) - (rest + delta)[nose].mean(0)) - before

    assert giraffe.expression_deltas[k][jaw, 1].mean() < -1.0
    assert opening(giraffe) > opening(human) > 1.0


def test_giraffe_jaw_open_opens_the_muzzle_not_the_neck(human, giraffe, geometry):
    _check_jaw(human, giraffe, geometry)


def test_real_giraffe_jaw_open(real_human, real_giraffe):
    _check_jaw(real_human, real_giraffe, giraffe_geometry(real_human, SETTINGS))


# ----------------------------------------------------------------------------- larynx


def _larynx_centre(model: HeadNeckModel, tau: float) -> torch.Tensor:
    with torch.no_grad():
        offsets = model.larynx_offsets(torch.tensor([tau]), torch.ones(1))[0]
        weight = offsets.norm(dim=1)
        return (weight[:, None] * model.template).sum(0) / weight.sum()


def test_larynx_slides_further_on_the_longer_neck(human, giraffe):
    """The map stays in UV space: tau moves the giraffe's larynx the same share of a longer neck."""
    source, target = HeadNeckModel(human), HeadNeckModel(giraffe)
    slide_human = (_larynx_centre(source, 0.03) - _larynx_centre(source, 0.0)).norm()
    slide_giraffe = (_larynx_centre(target, 0.03) - _larynx_centre(target, 0.0)).norm()
    assert slide_giraffe > 3.0 * slide_human
    # still pointing out of the front of the neck: perpendicular-ish to the inclined neck, forward
    direction = giraffe.larynx_direction / np.linalg.norm(giraffe.larynx_direction)
    neck = rest_world(giraffe)[-1, :3, 3] - rest_world(giraffe)[0, :3, 3]
    assert abs(direction @ neck / np.linalg.norm(neck)) < 0.5 and direction[2] > 0


# ----------------------------------------------------------------------------- settings and files


def test_giraffe_settings_reject_bad_values():
    with pytest.raises(ValueError, match="incline_deg"):
        GiraffeSettings(incline_deg=60.0)
    with pytest.raises(ValueError, match="neck_factor"):
        GiraffeSettings(neck_factor=0.5)


def _bones_json(rig: RigData) -> dict:
    """A bones_neutral.json-style dict of ``rig``'s joints (head offsets relative to the parent's tail)."""
    bones, names = {}, [str(n) for n in rig.joint_names]
    lengths = [float(np.linalg.norm(rig.joint_rest_local[j + 1][:3, 3])) if j + 1 < len(names) else 10.0
               for j in range(len(names))]
    for j, name in enumerate(names):
        parent = int(rig.parents[j])
        head = rig.joint_rest_local[j][:3, 3].astype(float).copy()
        if parent >= 0:
            head[1] -= lengths[parent]
        bones[name] = {"matrix": rig.joint_rest_local[j][:3, :3].tolist(), "head": head.tolist(),
                       "length": lengths[j], "parent": names[parent] if parent >= 0 else None}
    return bones


def test_character_from_obj_and_joints_json(tmp_path, human):
    scale = 1.3
    obj = tmp_path / "big.obj"
    write_obj(obj, scale * human.template, human.faces, human.uv_coords, human.faces_uv)
    bones = _bones_json(human)
    for bone in bones.values():
        bone["head"] = [scale * c for c in bone["head"]]
        bone["length"] *= scale
    joints = tmp_path / "bones.json"
    joints.write_text(json.dumps(bones))
    character = character_from_obj(obj, joints, human)
    _check_topology(human, character)
    assert np.allclose(character.template, scale * human.template, atol=1e-5)
    expected_joints = scale * rest_world(human)[:, :3, 3]
    assert np.allclose(rest_world(character)[:, :3, 3], expected_joints, atol=1e-4)
    assert np.array_equal(character.skin_weights, human.skin_weights)
    assert np.abs(character.expression_deltas - scale * human.expression_deltas).max() < 1e-3


def test_obj_with_wrong_vertex_count_names_the_file(tmp_path, human):
    obj = tmp_path / "short.obj"
    write_obj(obj, human.template[:-10], human.faces[:100])
    joints = tmp_path / "bones.json"
    joints.write_text(json.dumps(_bones_json(human)))
    with pytest.raises(InputError, match=r"short\.obj: 5751 vertices, expected the template's 5761"):
        character_from_obj(obj, joints, human)


def test_obj_with_other_faces_names_the_file(tmp_path, human):
    obj = tmp_path / "shuffled.obj"
    write_obj(obj, human.template, human.faces[::-1])
    joints = tmp_path / "bones.json"
    joints.write_text(json.dumps(_bones_json(human)))
    with pytest.raises(InputError, match=r"shuffled\.obj: faces differ"):
        character_from_obj(obj, joints, human)


@pytest.mark.parametrize("content, message", [
    ("{not json", "malformed JSON"),
    ("[1, 2, 3]", "expected an object of bones"),
    (json.dumps({"c7t1": {"matrix": np.eye(3).tolist(), "head": [0, 0, 0], "length": 1, "parent": None}}),
     "bones \\['c7t1'\\], expected"),
])
def test_bad_joints_json_names_the_file(tmp_path, content, message):
    path = tmp_path / "bad_bones.json"
    path.write_text(content)
    with pytest.raises(InputError, match=rf"bad_bones\.json: .*{message}"):
        read_joints_json(path)


def test_joints_json_with_a_bad_matrix_names_the_bone(tmp_path, human):
    bones = _bones_json(human)
    bones["c4c5"]["matrix"] = [[1, 0], [0, 1]]
    path = tmp_path / "bones.json"
    path.write_text(json.dumps(bones))
    with pytest.raises(InputError, match=r"bones\.json: bone 'c4c5' 'matrix' has shape \[2, 2\]"):
        read_joints_json(path)


def test_load_character_names(human, giraffe, tmp_path):
    assert load_character("human", human) is human
    path = tmp_path / "g.npz"
    giraffe.save(path)
    loaded = load_character(str(path), human)
    assert character_kind(loaded) == "giraffe" and np.array_equal(loaded.template, giraffe.template)
    with pytest.raises(InputError, match="giraffe.obj: an OBJ character needs its joints"):
        load_character("giraffe.obj", human)
    with pytest.raises(InputError, match="character=zebra"):
        load_character("zebra", human)


def test_cli_builds_a_giraffe_and_rejects_bad_settings(tmp_path, capsys, human, giraffe):
    out = tmp_path / "giraffe.npz"
    run_cli("characters", characters_run,
            argv=["kind=giraffe", f"out={out}", "check=false"])
    saved = RigData.load(out)
    assert np.array_equal(saved.template, giraffe.template)
    assert "x5.00" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exit_info:
        run_cli("characters", characters_run,
                argv=["kind=giraffe", f"out={tmp_path / 'x.npz'}", "giraffe.incline_deg=70"])
    assert exit_info.value.code == 2
    assert "incline_deg" in capsys.readouterr().err


def test_settings_change_the_giraffe(human, giraffe):
    plain = build_giraffe(human, dataclasses.replace(SETTINGS, ossicones=False, muzzle_factor=1.0))
    assert plain.template[:, 1].max() < giraffe.template[:, 1].max() - 1.0      # ossicones on the crown
    assert plain.template[:, 2].max() < giraffe.template[:, 2].max() - 3.0      # the muzzle
