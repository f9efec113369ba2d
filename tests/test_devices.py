"""Tasks and models follow the device they are moved to (trainer.device=cuda).

These machines have no GPU.  PyTorch's ``meta`` device stands in for it on the CPU: tensors there carry a shape,
a dtype and a device but no data, and an operation mixing a meta tensor with a CPU tensor (other than a scalar)
raises, so running the models' and tasks' tensor code on meta finds every tensor made on the CPU behind the
caller's back (the failure CUDA would give).  Where a GPU is present, the last test trains both tasks on it
and compares with the CPU.
"""
from __future__ import annotations

import pytest
import torch
from test_train import config as head2neck_config

import tasks  # noqa: F401  (registers the config schemas)
from base.cli import compose_config
from base.rotations import axis_angle_to_matrix, relative_angle
from data.joint_limits import adjacent_similarity_energy, rotation_limit_energy, within_limits
from models.head2neck import chain_head_rotation, correct_to_head, head_error_deg, split_head_rotation
from models.larynx import LarynxDataFields, LarynxTransformer, LarynxTransformerConfig
from tasks.distributed import to_device
from tasks.head2neck import Task as Head2NeckTask
from tasks.larynx_transformer import Task as LarynxTask
from tasks.loop import fit

META = torch.device("meta")
LARYNX = ["task=larynx_transformer", "task.members=1", "model.d_model=16", "model.n_heads=2", "model.d_ff=16",
          "model.window=8",
          "task.crop=16", "task.batch_size=4", "data.train_subjects=2", "data.sequences_per_subject=1",
          "data.heldout_subjects=1", "data.heldout_sequences_per_subject=1", "data.seconds=4"]


@pytest.mark.parametrize("n_layers", [1, 2])
def test_the_transformer_runs_where_its_weights_are(n_layers):
    """forward (banded attention, smoothing chunks), generate and the live stream on the meta device."""
    model = LarynxTransformer(LarynxTransformerConfig(n_layers=n_layers, window=16),
                              LarynxDataFields(30.0, ["a", "b"], 0.01, 0.02)).eval().to(META)
    psi = torch.rand(2, 150, 55).to(META)
    subject = torch.tensor([1, 2]).to(META)
    assert model(psi, subject).device == META
    tau = model.generate(psi, subject, chunk=40)
    assert tau.shape == (2, 150) and tau.device == META
    stream = model.stream(2, subject)
    assert stream.step(torch.rand(2, 55)).device == META  # live frames given on the CPU go to the model


def test_the_larynx_task_moves_its_model_and_decodes_there():
    task = LarynxTask(compose_config("train", LARYNX))
    assert task.to(META) is task and task.device == META
    batch = to_device(task.batch(0, torch.Generator().manual_seed(0)), META)
    prediction = task.model(batch["psi"], batch["subject"])
    assert prediction.shape == batch["tau"].shape and prediction.device == META


def test_the_head2neck_task_moves_model_rig_and_validation_frames():
    """The loss's and the evaluation's tensor code on the moved task.  The exact correction is float64 numpy
    on the CPU (``models.head2neck.correct_to_head``: it copies to the CPU and back), which a meta tensor,
    having no values, cannot give: it runs on CPU copies here and its result goes back to the device."""
    task = Head2NeckTask(head2neck_config())
    batch = to_device(task.batch(0, torch.Generator().manual_seed(0)), META)
    assert task.to(META) is task
    theta = task.model(batch["head"], task.rest)
    assert theta.device == META and chain_head_rotation(theta, task.rig).shape == batch["head"].shape
    assert rotation_limit_energy(theta).device == adjacent_similarity_energy(theta, task.rig.parents).device == META
    head = task.val["head"]
    assert head.device == META
    raw = task.model(head, task.rest)
    cpu_task = Head2NeckTask(head2neck_config())
    corrected = correct_to_head(torch.zeros(raw.shape), torch.eye(3).expand(len(head), 3, 3), cpu_task.rig)
    assert corrected.shape == (len(head), task.rig.num_joints, 3) and corrected.device.type == "cpu"
    corrected = corrected.to(META)
    for split in ("uniform", "rom", "invivo"):
        assert split_head_rotation(head, task.rest, split).device == META
    assert head_error_deg(corrected, head, task.rig).shape == (len(head),)
    assert within_limits(corrected).shape == (len(head), task.rig.num_joints)
    assert relative_angle(axis_angle_to_matrix(corrected), task.val["rotations"]).device == META


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device on this machine")
@pytest.mark.parametrize("task", ["head2neck", "larynx_transformer"])
def test_training_on_cuda_gives_the_cpu_figures(tmp_path, task):
    def config(device):
        if task == "head2neck":
            return head2neck_config(f"trainer.device={device}")
        return compose_config("train", [*LARYNX, "trainer.max_steps=20", "trainer.eval_every=10",
                                        "trainer.progress=false", f"trainer.device={device}"])
    cpu = fit(config("cpu"), tmp_path / "cpu")
    cuda = fit(config("cuda"), tmp_path / "cuda")
    for key, value in cpu.items():
        assert cuda[key] == pytest.approx(value, rel=1e-3, abs=1e-5), key
