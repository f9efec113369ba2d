"""models.fit on the built-in rig: known parameters back from noisy meshes (better than the per-frame
baseline), placement from scans, the shape offset for another person, bad input, windows fitted in parallel.

The sequences here are our own sinusoids in the anatomical frames (not the cervical prior the solver's
settings were measured on); scans and the reshaped person come from ``data.fit_captures``.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from base.errors import InputError
from base.rotations import axis_angle_to_matrix, relative_angle
from data.fit_captures import PersonConfig, ScanConfig, reshaped_person, scan_sequence
from models.fit import FitSettings, fit_meshes, fit_scans
from models.fit.scans import initial_placements, searched_start
from models.fit.windows import spans
from models.rig import HeadNeckModel

FAST = dict(iterations=(1, 2, 6), hessian_vertices=600)
BASELINE = dict(temporal=False, limit_deg=0.0, **FAST)


def sequence(model: HeadNeckModel, frames: int, seed: int, noise_cm: float = 0.1):
    """Smooth nod + turn + tilt shared over the joints, sparse expressions, a tau ramp, a swaying placement."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 30.0
    share = np.array([0.02, 0.1, 0.12, 0.12, 0.12, 0.1, 0.3, 0.12])[:, None]
    head = np.stack([0.5 * np.sin(2.1 * t + 0.3), 0.9 * np.sin(1.3 * t), 0.3 * np.sin(1.7 * t + 1.0)], 1)
    anatomical = torch.tensor(share[None] * head[:, None], dtype=torch.float32)   # [T,J,3] radians
    theta = model.from_anatomical(anatomical)
    psi = torch.zeros(frames, model.num_expressions)
    active = rng.choice(model.num_expressions, 6, replace=False)
    psi[:, active] = torch.tensor(0.5 + 0.4 * np.sin(3 * t[:, None] + rng.uniform(0, 6, 6)), dtype=torch.float32)
    tau = torch.tensor(0.02 * np.sin(2.5 * t), dtype=torch.float32)
    eta = 0.9
    rotation = axis_angle_to_matrix(torch.tensor(np.array([0.4, -1.2, 0.3]) + 0.03 * np.sin(t)[:, None],
                                                 dtype=torch.float32))
    translation = torch.tensor(np.array([5.0, -3.0, 40.0]) + np.sin(t)[:, None], dtype=torch.float32)
    with torch.no_grad():
        posed = model(theta, psi, tau, torch.full((frames,), eta))
    clean = posed @ rotation.transpose(1, 2) + translation[:, None]
    noise = torch.tensor(rng.normal(0, noise_cm, clean.shape), dtype=torch.float32)
    return dict(theta=theta, psi=psi, tau=tau, eta=eta, rotation=rotation, translation=translation, clean=clean,
                noisy=clean + noise)


def joint_error_deg(result, truth) -> float:
    fitted = axis_angle_to_matrix(torch.tensor(result.theta[:, 1:]))
    return math.degrees(float(relative_angle(fitted, axis_angle_to_matrix(truth["theta"][:, 1:])).mean()))


def head_error_deg(model, result, truth) -> float:
    head = torch.tensor(result.root_rotation) @ model.head_rotation(torch.tensor(result.theta))
    return math.degrees(float(relative_angle(head, truth["rotation"] @ model.head_rotation(truth["theta"])).mean()))


def vertex_rms_mm(model, result, truth) -> float:
    with torch.no_grad():
        posed = model(torch.tensor(result.theta), torch.tensor(result.psi), torch.tensor(result.tau),
                      torch.full((len(result.tau),), result.eta))
    placed = posed @ torch.tensor(result.root_rotation).transpose(1, 2) + torch.tensor(result.root_translation)[:, None]
    return 10 * float(((placed - truth["clean"]) ** 2).sum(-1).mean().sqrt())


@pytest.fixture(scope="module")
def meshes(builtin_rig):
    truth = sequence(builtin_rig, 12, seed=5)
    calls = []
    fitted = fit_meshes(builtin_rig, truth["noisy"].numpy(), FitSettings(**FAST), progress=calls.append)
    baseline = fit_meshes(builtin_rig, truth["noisy"].numpy(), FitSettings(**BASELINE))
    return truth, fitted, baseline, calls


def test_fit_meshes_recovers_the_sequence(builtin_rig, meshes):
    truth, fitted, _, calls = meshes
    T, J = truth["theta"].shape[:2]
    assert fitted.theta.shape == (T, J, 3) and fitted.theta.dtype == np.float32
    assert np.all(fitted.theta[:, 0] == 0)
    assert fitted.psi.shape == (T, builtin_rig.num_expressions) and fitted.root_rotation.shape == (T, 3, 3)
    assert joint_error_deg(fitted, truth) < 1.0
    assert head_error_deg(builtin_rig, fitted, truth) < 0.2
    assert float(np.sqrt(((fitted.tau - truth["tau"].numpy()) ** 2).mean())) < 0.003
    assert abs(fitted.eta - truth["eta"]) < 0.05
    assert vertex_rms_mm(builtin_rig, fitted, truth) < 0.5
    # The data term's RMS is the noise's (1 mm per axis: sqrt(3) mm per vertex).
    assert abs(float(np.median(fitted.fit_rms_mm)) - math.sqrt(3)) < 0.1 and fitted.fit_rms_mm.max() < 2.5
    assert np.isnan(fitted.joint_uncertainty_deg[0]) and np.all(fitted.joint_uncertainty_deg[1:] > 0)
    assert calls[-1] == T and calls == sorted(calls)


def test_temporal_fit_beats_the_per_frame_baseline(meshes):
    truth, fitted, baseline, _ = meshes
    assert joint_error_deg(fitted, truth) < 0.8 * joint_error_deg(baseline, truth)


def test_fit_scans_recovers_the_placement(builtin_rig):
    truth = sequence(builtin_rig, 3, seed=7, noise_cm=0.0)
    # The scanner looks along +z of the capture: turn the face towards it.
    facing = axis_angle_to_matrix(torch.tensor([[0.0, 0.2, 0.0]])) @ truth["rotation"][:1].transpose(1, 2)
    clean = truth["clean"] @ facing.transpose(1, 2)
    clouds = scan_sequence(clean.numpy(), builtin_rig.rig.faces, seed=1, config=ScanConfig(points=4000))
    result = fit_scans(builtin_rig, clouds, FitSettings(scan_points=2000, **FAST))
    rotation = facing @ truth["rotation"]
    head = torch.tensor(result.root_rotation) @ builtin_rig.head_rotation(torch.tensor(result.theta))
    head_error = relative_angle(head, rotation @ builtin_rig.head_rotation(truth["theta"]))
    assert math.degrees(float(head_error.max())) < 8.0     # the right way round (a flip is 180)
    centre = builtin_rig.template.mean(0)
    with torch.no_grad():
        fitted_centre = torch.tensor(result.root_rotation) @ centre + torch.tensor(result.root_translation)
        true_centre = (facing @ (truth["rotation"] @ centre + truth["translation"])[..., None])[..., 0]
    assert float((fitted_centre - true_centre).norm(dim=-1).max()) < 1.0
    assert np.all(result.fit_rms_mm < 2.0)   # noise-free points; strays within 1.5 cm count


def test_shape_offset_absorbs_another_person(builtin_rig):
    person = HeadNeckModel(reshaped_person(builtin_rig.rig, seed=3, config=PersonConfig()))
    truth = sequence(person, 8, seed=9)
    with_shape = fit_meshes(builtin_rig, truth["noisy"].numpy(), FitSettings(fit_shape=True, **FAST))
    without = fit_meshes(builtin_rig, truth["noisy"].numpy(), FitSettings(**FAST))
    assert with_shape.shape_offset.shape == (builtin_rig.num_vertices, 3) and without.shape_offset is None
    assert joint_error_deg(with_shape, truth) < 0.8 * joint_error_deg(without, truth)
    offset_model = HeadNeckModel(builtin_rig.rig.__class__(**{**builtin_rig.rig.__dict__,
                                                              "template": builtin_rig.rig.template
                                                              + with_shape.shape_offset}))
    assert vertex_rms_mm(offset_model, with_shape, truth) < 0.3 * vertex_rms_mm(builtin_rig, without, truth)


def test_shape_offset_takes_bone_region_translations_not_the_neck(builtin_rig):
    # Another person whose neck's bone regions sit a few mm apart (each bone's skin moved by its own 3 mm
    # translation, blended by the skin weights): shape, not pose.  Holding every bone region's rigid motion of
    # the offset at zero put these translations into the neck's joints (4.3 deg, no better than no offset).
    rig = builtin_rig.rig
    moves = np.random.default_rng(0).normal(0.0, 0.3, (builtin_rig.num_joints, 3))
    person = HeadNeckModel(dataclasses.replace(rig, template=(rig.template + rig.skin_weights @ moves)
                                               .astype(np.float32)))
    truth = sequence(person, 8, seed=9)
    with_shape = fit_meshes(builtin_rig, truth["noisy"].numpy(), FitSettings(fit_shape=True, **FAST))
    without = fit_meshes(builtin_rig, truth["noisy"].numpy(), FitSettings(**FAST))
    assert joint_error_deg(with_shape, truth) < 0.5 * joint_error_deg(without, truth)
    assert head_error_deg(builtin_rig, with_shape, truth) < 0.25


def test_bad_input_names_the_frame(builtin_rig):
    vertices = np.zeros((3, builtin_rig.num_vertices, 3), np.float32)
    vertices[2, 10, 1] = np.nan
    with pytest.raises(InputError, match="frame 2 holds NaN"):
        fit_meshes(builtin_rig, vertices)
    with pytest.raises(InputError, match=f"100 vertices per frame, the rig has {builtin_rig.num_vertices}"):
        fit_meshes(builtin_rig, np.zeros((2, 100, 3)))
    clouds = [np.random.default_rng(0).normal(size=(500, 3)), np.zeros((50, 3))]
    with pytest.raises(InputError, match="frame 1 has 50 points, expected at least 100"):
        fit_scans(builtin_rig, clouds)
    with pytest.raises(InputError, match=r"frame 0 has shape \[500, 2\]"):
        fit_scans(builtin_rig, [np.zeros((500, 2))])


def test_fit_scans_finds_a_turned_half_head(builtin_rig):
    # Not data.fit_captures' scanner: the face's half of the posed vertices plus 3 % strays in a 30 cm box,
    # the capture turned by 50 degrees about a skew axis (a flipped head scored best with point-to-point ICP).
    truth = sequence(builtin_rig, 2, seed=3, noise_cm=0.0)
    axis = torch.tensor([1.0, 2.0, -1.5]) / math.sqrt(7.25)
    turn = axis_angle_to_matrix(math.radians(50.0) * axis[None])[0]
    with torch.no_grad():
        posed = builtin_rig(truth["theta"], truth["psi"], truth["tau"], torch.full((2,), truth["eta"]))
        head = turn @ builtin_rig.head_rotation(truth["theta"])
    rng = np.random.default_rng(4)
    clouds = []
    for vertices, facing in zip((posed @ turn.T + torch.tensor([12.0, -40.0, 150.0])).numpy(), head.numpy()):
        centre = vertices.mean(0)
        front = vertices[(vertices - centre) @ facing[:, 2] > 0]
        clouds.append(np.concatenate([front, centre + rng.uniform(-15, 15, (len(front) // 33, 3))]))
    result = fit_scans(builtin_rig, clouds, FitSettings(scan_points=2000, **FAST))
    fitted = torch.tensor(result.root_rotation) @ builtin_rig.head_rotation(torch.tensor(result.theta))
    assert math.degrees(float(relative_angle(fitted, head).max())) < 3.0


def test_scan_start_finds_the_torso_under_a_bent_neck(builtin_rig):
    # fit_app_check's kind of capture: the face's half of the posed vertices, the head bent ~45 degrees from
    # the torso (nod growing up the neck, an even turn).  The rigid start follows the head and leaves the
    # torso 30-40 degrees off; the neck search (head held, the turn split over the joints) finds it.  (With
    # other noise seeds, 2 of 4, the rigid start turns this capture over: not the search's to fix.)
    frames = 2
    anatomical = np.zeros((frames, builtin_rig.num_joints, 3))
    anatomical[:, 1:, 0] = 0.15 * np.linspace(0.5, 1.0, 7)
    anatomical[:, 1:, 1] = (0.1 + 0.05 * np.arange(frames) / 30)[:, None]
    theta = builtin_rig.from_anatomical(torch.tensor(anatomical, dtype=torch.float32))
    turn = axis_angle_to_matrix(torch.tensor([0.3, -0.8, 0.2]))
    with torch.no_grad():
        posed = builtin_rig(theta, torch.zeros(frames, builtin_rig.num_expressions), torch.zeros(frames),
                            torch.ones(frames))
        head = turn @ builtin_rig.head_rotation(theta)
    torso = turn @ builtin_rig.joint_transforms(theta)[:, 0, :3, :3] @ builtin_rig.rest_world[0, :3, :3].T
    rng = np.random.default_rng(2)
    clouds = []
    for vertices, facing in zip((posed @ turn.T + torch.tensor([12.0, -40.0, 150.0])).double().numpy(),
                                head.double().numpy()):
        front = vertices[(vertices - vertices.mean(0)) @ facing[:, 2] > 0]
        strays = vertices.mean(0) + rng.uniform(-15, 15, (len(front) // 33, 3))
        clouds.append(np.concatenate([front + rng.normal(0, 0.1, front.shape), strays]))
    rotation, translation = initial_placements(builtin_rig, clouds)
    assert math.degrees(float(relative_angle(rotation, torso).min())) > 25.0
    rotation, _, theta_start = searched_start(builtin_rig, clouds, rotation, translation)
    assert math.degrees(float(relative_angle(rotation, torso).max())) < 12.0
    fitted_head = rotation @ builtin_rig.head_rotation(theta_start)
    assert math.degrees(float(relative_angle(fitted_head, head).max())) < 1.0


def test_windows_tile_the_sequence():
    for frames, parts, overlap in ((60, 2, 12), (61, 3, 8), (20, 2, 12), (5, 4, 2)):
        windows = spans(frames, parts, overlap)
        kept = [(keep_start, keep_stop) for _, _, keep_start, keep_stop in windows]
        assert kept[0][0] == 0 and kept[-1][1] == frames
        assert all(a[1] == b[0] for a, b in zip(kept, kept[1:]))
        assert all(start <= keep_start < keep_stop <= stop for start, stop, keep_start, keep_stop in windows)
        assert all(stop - start >= 2 * overlap or len(windows) == 1 for start, stop, _, _ in windows)
    assert len(spans(20, 2, 12)) == 1     # too short to split
    assert spans(60, 2, 12) == [(0, 36, 0, 30), (24, 60, 30, 60)]


def test_windows_in_processes_match_the_whole_sequence(builtin_rig):
    truth = sequence(builtin_rig, 16, seed=11)
    calls = []
    whole = fit_meshes(builtin_rig, truth["noisy"].numpy(), FitSettings(**FAST))
    windowed = fit_meshes(builtin_rig, truth["noisy"].numpy(), FitSettings(workers=2, window_overlap=4, **FAST),
                          progress=calls.append)
    assert len(windowed.report["windows"]) == 2 and windowed.theta.shape == whole.theta.shape
    gap = relative_angle(axis_angle_to_matrix(torch.tensor(windowed.theta[:, 1:])),
                         axis_angle_to_matrix(torch.tensor(whole.theta[:, 1:])))
    assert math.degrees(float(gap.max())) < 0.5
    assert joint_error_deg(windowed, truth) < 1.0 and head_error_deg(builtin_rig, windowed, truth) < 0.2
    assert abs(windowed.eta - truth["eta"]) < 0.05 and vertex_rms_mm(builtin_rig, windowed, truth) < 0.5
    assert calls[-1] == 16 and calls == sorted(calls)
