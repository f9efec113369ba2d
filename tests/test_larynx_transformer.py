"""Expression -> larynx transformer: streaming decoder, training task, inference CLI (the generator:
test_synthetic_larynx.py)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

import tasks  # noqa: F401  (registers the config schemas)
from base.errors import InputError
from base.files import write_csv
from data.expressions import EXPRESSION_NAMES
from data.pairs import save_pair
from data.synthetic_larynx import (
    make_sequence,
)
from models.checkpoint import load_model, save_checkpoint
from models.larynx import build_model, predict_tau
from tests.larynx_reference import generate_uncached, state_bytes, tensor_bytes

REPO = Path(__file__).resolve().parents[1]
K = {name: k for k, name in enumerate(EXPRESSION_NAMES)}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny tensors: a second thread only adds stalls on a shared CPU (the trainer config uses 1 too)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


TINY_MODEL = {"d_model": 16, "n_heads": 2, "n_layers": 2, "d_ff": 32, "window": 16, "expression_kernel": 3,
              "expression_dilations": [1, 2, 4], "smoothing_frames": 20.0, "recurrent": True, "dropout": 0.0}
DATA_FIELDS = {"fps": 30.0, "subjects": [], "tau_mean": 0.01, "tau_scale": 0.02}  # what the task takes from the data


def random_model(**overrides):
    """A tiny model with non-trivial random weights (the default init keeps the output near tau_mean)."""
    torch.manual_seed(0)
    model = build_model({**TINY_MODEL, **DATA_FIELDS, **overrides}).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return model


# --------------------------------------------------------------------------- streaming decoder


@pytest.mark.parametrize("recurrent, smoothing_frames, n_layers",
                         [(True, 20.0, 2), (False, 20.0, 2), (True, 0.0, 1), (False, 0.0, 1)])
def test_cached_decoding_matches_full_recomputation(recurrent, smoothing_frames, n_layers):
    model = random_model(subjects=["anna", "ben"], recurrent=recurrent, smoothing_frames=smoothing_frames,
                         n_layers=n_layers)
    psi = torch.rand(2, 70, 55, generator=torch.Generator().manual_seed(1))  # 70 frames: the 16-frame window wraps
    subject = torch.tensor([0, 2])
    reference = generate_uncached(model, psi, subject) / model.tau_scale
    assert reference.std() > 0.1  # the comparison is not between constants
    with torch.no_grad():
        assert (model(psi, subject) / model.tau_scale - reference).abs().max() < 1e-5  # causal: one pass is all
    cached = model.generate(psi, subject, chunk=9) / model.tau_scale  # chunk boundaries inside
    stream = model.stream(2, subject)
    stepped = torch.stack([stream.step(psi[:, t]) for t in range(70)], dim=1) / model.tau_scale
    assert (cached - reference).abs().max() < 1e-5
    assert (stepped - reference).abs().max() < 1e-5


@pytest.mark.parametrize("recurrent, smoothing_frames", [(True, 20.0), (False, 0.0)])
def test_every_parameter_gets_a_gradient(recurrent, smoothing_frames):
    """No dead weights (the aligned cross-attention projects values only)."""
    model = random_model(recurrent=recurrent, smoothing_frames=smoothing_frames).train()
    psi = torch.rand(2, 40, 55, generator=torch.Generator().manual_seed(6))
    model(psi, torch.tensor([0, 0])).pow(2).sum().backward()
    d = TINY_MODEL["d_model"]
    assert model.blocks[0].cross.kv.weight.shape == (d, d)
    # Every output row of a weight matrix gets a gradient; a vector as a whole (the key part of an attention
    # bias shifts all scores of a query equally, which softmax ignores: no gradient there in any transformer).
    def rows(p):
        return p.grad.abs().reshape(len(p), -1) if p.ndim == 2 else p.grad.abs()[None]

    dead = [name for name, p in model.named_parameters() if p.grad is None or not (rows(p).amax(1) > 0).all()]
    assert not dead, dead


def test_the_head_reads_how_far_the_stream_goes_without_the_output_norm():
    """No LayerNorm before the head: tau's deviation from the head's bias grows in proportion with the residual
    stream, so a face moving further than in training can move tau further."""
    stream = torch.randn(2, 30, TINY_MODEL["d_model"], generator=torch.Generator().manual_seed(3))
    model = random_model()
    with torch.no_grad():
        def readout(x):
            return model.to_tau(model.head(x)[..., 0] * model.output_gain(2, None))

        bias = model.to_tau(model.head.bias * model.output_gain(2, None))
        once, twice = readout(stream) - bias, readout(2 * stream) - bias
    assert torch.allclose(twice, 2 * once, rtol=1e-5, atol=1e-9)
    assert once.abs().max() > 1e-3  # not a comparison between zeros


# --------------------------------------------------------------------------- checkpoints of removed options


def test_checkpoints_of_removed_options_are_refused_naming_the_option(tmp_path):
    """A checkpoint of an earlier version holding an option this one does not have (a LayerNorm before the head)
    is refused in one line naming it, whatever its value."""
    model = random_model()
    save_checkpoint(tmp_path / "old.pt", {"task": "larynx_transformer", "model_config": {**model.config,
                                          "output_norm": False}, "model": model.state_dict(), "step": 0})
    with pytest.raises(InputError, match=r"old\.pt: checkpoint written by an incompatible version of the code: its "
                                         r"model_config does not build \(.*unknown \['output_norm'\]"):
        load_model(tmp_path / "old.pt", "larynx_transformer")


def test_forward_is_causal():
    model = random_model()
    psi = torch.rand(1, 50, 55, generator=torch.Generator().manual_seed(2))
    changed_psi = psi.clone()
    changed_psi[:, 30] += 0.5
    base = model(psi)
    assert torch.equal(model(changed_psi)[:, :30], base[:, :30])
    assert (model(changed_psi)[:, 30] - base[:, 30]).abs().item() > 1e-4


def test_dilated_encoder_reaches_its_receptive_field():
    """Dilations 1, 2, 4 with kernel 3: the features of frame t see psi[t-14..t] (1 + 2 * 7 frames), not t-15."""
    model = random_model(smoothing_frames=0.0, recurrent=False)  # these two alone reach back to frame 0
    psi = torch.rand(1, 40, 55, generator=torch.Generator().manual_seed(8))
    base, _ = model.expression(psi)
    for back, matters in ((14, True), (15, False)):
        changed = psi.clone()
        changed[:, 30 - back] += 0.5
        moved = (model.expression(changed)[0][:, 30] - base[:, 30]).abs().max().item()
        assert (moved > 1e-4) == matters, (back, moved)


@pytest.fixture(scope="module")
def long_stream():
    """(model, psi, tau, sizes): 10,000 frames through step(); ``sizes``: the ``state_bytes`` of a stream at
    frame 200 and of this one at frame 10,000.  (That a frame costs the same there as at frame 200 is a timing:
    ``benchmarks/bench_larynx_streaming.py`` measures it.)"""
    model = random_model()
    psi = torch.rand(10_000, 55, generator=torch.Generator().manual_seed(4))
    far, near = model.stream(1), model.stream(1)
    tau = [far.step(psi[t]) for t in range(10_000)]
    for t in range(200):
        near.step(psi[t])
    return model, psi, torch.cat(tau), [state_bytes(near), state_bytes(far)]


def test_smoothing_is_a_bank_of_first_order_low_passes():
    """Impulse response (1 - a) a^k per channel, a = exp(-1/tau); a constant input stays constant (it starts at
    the first frame, not at zero); chunks and carried states give the one-pass result."""
    from models.larynx.encoder import Smoothing

    torch.manual_seed(0)
    smoothing = Smoothing(4, max_frames=30.0, chunk=16)
    with torch.no_grad():
        smoothing.mix.weight.copy_(torch.eye(4))  # output = input + smoothed
        smoothing.mix.bias.zero_()
    times = torch.exp(smoothing.log_time.detach())
    np.testing.assert_allclose(times.numpy(), np.geomspace(1.0, 30.0, 4), rtol=1e-5)
    impulse = torch.zeros(1, 50, 4)
    impulse[0, 10] = 1.0
    out, _ = smoothing(impulse, torch.zeros(1, 4))
    a = np.exp(-1.0 / times.numpy())
    k = np.arange(40)[:, None]
    np.testing.assert_allclose((out - impulse)[0, 10:].detach().numpy(), (1 - a) * a ** k, atol=1e-6)
    constant = torch.full((1, 40, 4), 0.3)
    np.testing.assert_allclose(smoothing(constant)[0].detach().numpy(), 0.6, atol=1e-6)
    x = torch.rand(2, 45, 4, generator=torch.Generator().manual_seed(3))
    whole, last = smoothing(x)
    first, state = smoothing(x[:, :7])
    second, again = smoothing(x[:, 7:], state)
    np.testing.assert_allclose(torch.cat([first, second], 1).detach().numpy(), whole.detach().numpy(), atol=1e-6)
    np.testing.assert_allclose(again.detach().numpy(), last.detach().numpy(), atol=1e-6)


def test_tensor_bytes_sees_what_an_object_holds():
    class Holder:
        def __init__(self):
            self.items, self.table = [], {"a": torch.zeros(10)}

    holder = Holder()
    assert tensor_bytes(holder) == 40
    holder.items.append(torch.zeros(5, dtype=torch.float64))
    holder.view = holder.table["a"][2:]  # a view shares its storage: not counted twice
    assert tensor_bytes(holder) == 80
    assert tensor_bytes(holder, exclude=(holder.items,)) == 40


def test_ten_thousand_frames_bounded_memory(long_stream):
    model, psi, tau, sizes = long_stream
    assert tau.shape == (10_000,) and torch.isfinite(tau).all()
    assert sizes[0] == sizes[1]  # what the stream holds at frame 10,000 is what it held at frame 200
    # ... and that is its caches: per block keys and values of 2 x window frames (float32), plus the
    # encoder's convolution history (2 * (1 + 2 + 4) frames of d), its smoothed values (d) and small tables.
    d, window = TINY_MODEL["d_model"], TINY_MODEL["window"]
    caches = TINY_MODEL["n_layers"] * 2 * (2 * window) * d * 4 + 2 * (1 + 2 + 4) * d * 4 + d * 4
    assert caches <= sizes[0] < caches + 8_000, (sizes[0], caches)
    whole = model.generate(psi[None])[0]  # the whole-sequence API agrees over many cache wrap-arounds
    assert ((whole - tau) / model.tau_scale).abs().max() < 1e-5


def test_model_config_needs_the_data_fields():
    """fps, subjects and the tau normalisation come from the training data: no silent defaults."""
    with pytest.raises(ValueError, match=r"missing \['fps', 'tau_scale'\], unknown \[\]"):
        build_model({**TINY_MODEL, "subjects": [], "tau_mean": 0.0})
    with pytest.raises(ValueError, match=r"missing \[\], unknown \['tau_std'\]"):
        build_model({**TINY_MODEL, **DATA_FIELDS, "tau_std": 0.02})
    with pytest.raises(ValueError, match="d_model 16 must split into 3 heads of even size"):
        build_model({**TINY_MODEL, **DATA_FIELDS, "n_heads": 3})
    model = build_model({**TINY_MODEL, **DATA_FIELDS})
    assert build_model(model.config).config == model.config  # the checkpoint's model_config rebuilds it


def test_predict_tau_and_subjects():
    model = random_model(subjects=["anna", "ben"])
    psi = np.random.default_rng(5).uniform(0, 1, (40, 55)).astype(np.float32)
    tau = predict_tau(model, psi, "ben")
    expected = generate_uncached(model, torch.from_numpy(psi)[None], torch.tensor([2]))[0].numpy()
    np.testing.assert_allclose(tau, expected, atol=1e-7)
    assert np.abs(predict_tau(model, psi) - tau).max() > 1e-4  # the average style differs from ben's
    with pytest.raises(InputError, match="subject 'carl' was not in the training data \\(known: anna, ben\\)"):
        predict_tau(model, psi, "carl")
    with pytest.raises(InputError, match=r"psi of shape \(40, 54\), expected \[T,55\]"):
        predict_tau(model, psi[:, :54])


# --------------------------------------------------------------------------- training


# A small model and short runs (train.py overrides).
TINY_LARYNX = ["model.d_model=32", "model.n_heads=4", "model.d_ff=64", "model.window=32",
               "model.expression_dilations=[1,2,4,8]", "model.smoothing_frames=64", "task.crop=96",
               "task.batch_size=12", "task.eval_batch=16", "task.ridge_lambdas=[1,100,10000]", "trainer.eval_every=0",
               "trainer.early_stopping_patience=null", "trainer.restore_best=false",
               "trainer.checkpoint_every=100000", "trainer.log_every=50", "trainer.progress=false",
               "optim.warmup_steps=30", "task.members=1"]


def tiny_config(run_overrides=(), data=None):
    base = TINY_LARYNX
    data = data if data is not None else ["data.train_subjects=12", "data.sequences_per_subject=4", "data.seconds=20",
                    "data.heldout_subjects=4", "data.heldout_sequences_per_subject=2"]
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return compose("train", overrides=base + data + list(run_overrides))


def fit(cfg, run_dir: Path):
    from tasks import loop

    run_dir.mkdir(parents=True, exist_ok=True)
    return loop.fit(cfg, run_dir)


@pytest.mark.slow
def test_tiny_training_learns_the_generator(tmp_path, capsys):
    """600 steps of a small model on data=synthetic.  New recordings of the training people (their style): well
    below ridge on a 1 s window; people from the shifted generator (data.heldout_shift=1: lags, time constants,
    gains and swallows reaching outside the training ranges), whose traits no model can see in the face: no worse
    than ridge by more than a fifth, and well below the training mean."""
    result = fit(tiny_config(["trainer.max_steps=600"]), tmp_path / "run")
    # 0.76 here: a seal within a person's refractory time is no swallow, which a model must time over seconds
    # (data.repeat_seals); ridge cannot tell such seals apart at all.
    assert result["rmse_known_subjects"] < 0.8 * result["ridge_rmse_known_subjects"], result
    assert result["rmse_new_subjects"] < 1.2 * result["ridge_rmse_new_subjects"], result
    assert result["rmse"] < 0.7 * result["mean_rmse"], result
    printed = capsys.readouterr().out
    assert "ridge, 30-frame window" in printed and "training mean" in printed
    assert "new subjects (8 sequences)" in printed
    assert (tmp_path / "run" / "checkpoints" / "last.pt").is_file()


SHORT_DATA = ["data.train_subjects=3", "data.sequences_per_subject=2", "data.seconds=8",
              "data.heldout_subjects=1", "data.heldout_sequences_per_subject=1"]


def test_reproducible_and_exact_resume(tmp_path):
    def weights(run_dir):
        return torch.load(run_dir / "checkpoints" / "last.pt", weights_only=True)["model"]

    once = tiny_config(["trainer.max_steps=12"], SHORT_DATA)
    fit(once, tmp_path / "a")
    fit(once, tmp_path / "b")
    fit(tiny_config(["trainer.max_steps=12", "trainer.stop_after=7"], SHORT_DATA), tmp_path / "c")
    assert not (tmp_path / "c" / "eval.json").exists()
    fit(tiny_config(["trainer.max_steps=12", "resume=true"], SHORT_DATA), tmp_path / "c")
    a, b, c = weights(tmp_path / "a"), weights(tmp_path / "b"), weights(tmp_path / "c")
    start = tiny_config(["trainer.max_steps=12", "trainer.stop_after=1"], SHORT_DATA)
    fit(start, tmp_path / "d")
    assert any((weights(tmp_path / "d")[k] - a[k]).abs().max() > 1e-4 for k in a)  # training moved the weights
    for key in a:
        assert torch.equal(a[key], b[key]), key
        assert torch.equal(a[key], c[key]), key


def test_pairs_folder_split_by_take(tmp_path):
    from tasks.larynx_transformer import Task

    folder = tmp_path / "pairs"
    for take in range(5):
        for clip in range(2):
            sequence = make_sequence(take % 2, 2 * take + clip, 240, 30.0, seed=1)
            sequence.take = f"take{take}"
            save_pair(folder / f"take{take}_clip{clip}.npz", sequence)
    cfg = tiny_config(["data=pairs", f"data.path={folder}", "data.val_fraction=0.4", "task.crop=64",
                       "model.window=16"], data=[])
    task = Task(cfg)
    assert (len(task.train), len(task.val)) == (6, 4)
    assert len({s.take for s in task.val}) == 2 and not {s.take for s in task.train} & {s.take for s in task.val}
    assert task.model.subjects == sorted({s.subject for s in task.train})
    train_mean = np.concatenate([s.tau for s in task.train]).astype(np.float64).mean()
    val_tau = np.concatenate([s.tau for s in task.val]).astype(np.float64)
    metrics = task.evaluate()
    assert metrics["mean_rmse"] == pytest.approx(np.sqrt(np.mean((val_tau - train_mean) ** 2)), rel=1e-6)
    assert metrics["val_loss"] == metrics["rmse"]  # what train.py's early stopping and best checkpoint compare
    batch = task.batch(0, torch.Generator().manual_seed(0))
    assert batch["psi"].shape == (12, 64, 55) and batch["tau"].shape == (12, 64)


def linear_pair_task(tmp_path, overrides):
    """A task on pairs whose tau is a linear function of psi frame by frame (tau = 0.02 * jawOpen - 0.01 * smile),
    so that interpolated crops keep that relation."""
    from tasks.larynx_transformer import Task

    folder = tmp_path / "linear"
    rng = np.random.default_rng(3)
    for take in range(3):
        psi = np.clip(0.5 + 0.3 * np.cumsum(rng.standard_normal((400, 55)), axis=0) / 20, 0, 1).astype(np.float32)
        tau = (0.02 * psi[:, K["jawOpen"]] - 0.01 * psi[:, K["mouthSmile_L"]]).astype(np.float32)
        from data.pairs import LarynxSequence

        save_pair(folder / f"t{take}.npz", LarynxSequence(psi, tau, 30.0, "anna", f"t{take}"))
    return Task(tiny_config(["data=pairs", f"data.path={folder}", "task.crop=64", "model.window=16", *overrides],
                            data=[]))


def test_crops_are_pairs_at_any_start_within_their_sequence(tmp_path):
    task = linear_pair_task(tmp_path, ["task.batch_size=64"])
    batch = task.batch(0, torch.Generator().manual_seed(1))
    assert set(batch) == {"psi", "tau", "subject"}
    psi, tau = batch["psi"].double(), batch["tau"].double()
    # Linear interpolation keeps a linear relation exactly: the interpolated tau is still the pair of the psi.
    np.testing.assert_allclose(tau, 0.02 * psi[..., K["jawOpen"]] - 0.01 * psi[..., K["mouthSmile_L"]], atol=1e-6)
    positions, sequence = task._positions(64, torch.Generator().manual_seed(1))
    np.testing.assert_allclose(np.diff(positions.numpy(), axis=1), 1.0)  # plain crops, one frame a step
    first = positions[:, 0] - task.starts[sequence].double()
    assert (first >= 0).all() and (first + task.crop - 1 <= task.lengths[sequence] - 1).all()
    assert (first != first.floor()).any()  # between frames too


def test_the_default_run_takes_its_length_from_the_data_and_keeps_the_best_weights(tmp_path, capsys):
    """configs/trainer/larynx_transformer.yaml: trainer.max_steps null (the task's Task.steps_for_data), validation
    every 100 steps, early stopping and the best weights restored."""
    from base.cli import compose_config

    default = compose_config("train", ["task=larynx_transformer", "data=pairs", f"data.path={tmp_path}"]).trainer
    assert (default.max_steps, default.eval_every, default.early_stopping_patience, default.restore_best) == (
        None, 100, 6, True)
    cfg = tiny_config(["task.epochs=1", "task.fewest_steps=15", "task.most_steps=15", "trainer.max_steps=null",
                       "trainer.eval_every=5", "trainer.restore_best=true"], SHORT_DATA)
    result = fit(cfg, tmp_path / "run")
    assert "larynx_transformer: 15 training steps for these data" in capsys.readouterr().out
    assert torch.load(tmp_path / "run" / "checkpoints" / "last.pt", weights_only=False)["step"] == 15
    assert result["best_step"] in (5, 10, 15)
    from tools.ship_model import evaluated_checkpoint  # what a shipped run's manifest figures belong to

    assert evaluated_checkpoint(tmp_path / "run") == "best.pt"


def test_training_length_scales_with_the_data(tmp_path):
    task = linear_pair_task(tmp_path, ["task.epochs=100", "task.fewest_steps=10", "task.most_steps=1000",
                                       "task.batch_size=8"])
    frames = sum(len(s) for s in task.train)
    assert task.steps_for_data() == round(100 * frames / (8 * 64))
    capped = linear_pair_task(tmp_path, ["task.epochs=100", "task.fewest_steps=10", "task.most_steps=20"])
    assert capped.steps_for_data() == 20


def test_sequences_shorter_than_a_crop_are_reported_and_left_out(tmp_path, capsys):
    """Their frames would feed the tau normalisation, the ridge baseline and the subject table but never a crop."""
    from tasks.larynx_transformer import Task, load_sequences

    folder = tmp_path / "pairs"
    for i in range(6):
        long = i < 3
        sequence = make_sequence(i % 2 if long else 5, i, 240 if long else 40, 30.0, seed=1)
        sequence.name = f"take{i}"
        if not long:
            sequence.tau = sequence.tau + 1.0  # far from the others: visible in tau_mean if it leaked in
        save_pair(folder / f"take{i}.npz", sequence)
    cfg = tiny_config(["data=pairs", f"data.path={folder}", "data.val_fraction=0.2", "task.crop=64",
                       "model.window=16"], data=[])
    everything, _ = load_sequences(cfg.data)
    short = sorted(s.name for s in everything if len(s) < 64)
    assert len(short) >= 2 and "s5" in {s.subject for s in everything}  # the split leaves short files in training
    task = Task(cfg)
    printed = capsys.readouterr().out
    assert f"{len(short)} of {len(everything)} training sequences are shorter than the crop of 64 frames" in printed
    assert all(f"{name} (40 frames)" in printed for name in short)
    assert sorted(s.name for s in task.train) == sorted(s.name for s in everything if len(s) >= 64)
    assert task.model.subjects == ["s0", "s1"]  # not s5, seen in short files only
    usable_tau = np.concatenate([s.tau for s in everything if len(s) >= 64]).astype(np.float64)
    assert float(task.model.tau_mean) == pytest.approx(usable_tau.mean(), rel=1e-5)
    assert float(task.model.tau_scale) == pytest.approx(usable_tau.std(), rel=1e-4)
    # All shorter than task.crop: crops of the longest (the short files still left out), said so.
    longest = Task(tiny_config(["data=pairs", f"data.path={folder}", "data.val_fraction=0.2", "task.crop=300",
                                "model.window=16"], data=[]))
    printed = capsys.readouterr().out
    assert "every training sequence is shorter than task.crop=300 frames: crops of 240 frames" in printed
    assert longest.crop == 240 and longest.batch(0, torch.Generator().manual_seed(0))["psi"].shape[1] == 240
    assert sorted(s.name for s in longest.train) == sorted(s.name for s in task.train)
    with pytest.raises(InputError, match="no training sequence is longer than model.window=240 frames .longest: 240."):
        Task(tiny_config(["data=pairs", f"data.path={folder}", "data.val_fraction=0.2", "task.crop=300",
                          "model.window=240"], data=[]))


def perturbed(model):
    """``model`` with random weights everywhere (style rows included), so a copied tensor is recognisable."""
    torch.manual_seed(5)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.2 * torch.randn_like(p))
    return model.eval()


def test_warm_start_copies_the_network_and_starts_every_person_at_the_average(tmp_path):
    """task.init_from: all weights from the checkpoint; its people are others, so each style row (the average's
    included) starts from its average person; tau normalisation stays this data's.  The streamed output, in
    normalised units, is then the checkpoint's average person's."""
    plain = linear_pair_task(tmp_path, [])
    source_config = {**plain.model_config(), "subjects": ["p", "q", "r"], "tau_mean": 0.2, "tau_scale": 0.05}
    source = perturbed(build_model(source_config))
    path = tmp_path / "source.pt"
    save_checkpoint(path, {"task": "larynx_transformer", "model_config": source_config,
                           "model": source.state_dict(), "step": 7})
    task = linear_pair_task(tmp_path, [f"task.init_from={path}"])
    model = task.model.eval()
    assert model.subjects == ["anna"] and float(model.tau_mean) != pytest.approx(0.2)
    for name, value in model.state_dict().items():
        expected = source.state_dict()[name]
        if name in ("style.weight", "style_gain.weight"):
            expected = expected[:1].expand_as(value)
        assert torch.equal(value, expected), name
    psi = torch.from_numpy(task.val[0].psi)[None]
    ours = (model.generate(psi, torch.tensor([1])) - model.tau_mean) / model.tau_scale
    theirs = (source.generate(psi, torch.tensor([0])) - source.tau_mean) / source.tau_scale
    torch.testing.assert_close(ours, theirs, atol=1e-5, rtol=1e-4)
    # A plain run starts elsewhere: random init with zero styles.
    assert not torch.equal(plain.model.head.weight, source.head.weight)


def test_warm_start_from_another_frame_rate_says_so(tmp_path, capsys):
    plain = linear_pair_task(tmp_path, [])
    faster = {**plain.model_config(), "fps": 60.0}
    save_checkpoint(tmp_path / "fast.pt", {"task": "larynx_transformer", "model_config": faster,
                                           "model": build_model(faster).state_dict()})
    capsys.readouterr()
    linear_pair_task(tmp_path, [f"task.init_from={tmp_path / 'fast.pt'}"])
    assert "was trained at 60 fps, these data are at 30 fps: its filters, counted in frames, start at 2.00 times " \
           "its durations" in capsys.readouterr().out


def test_warm_start_refuses_what_does_not_fit(tmp_path):
    plain = linear_pair_task(tmp_path, [])
    wider = {**plain.model_config(), "d_ff": 48}
    save_checkpoint(tmp_path / "wider.pt", {"task": "larynx_transformer", "model_config": wider,
                                            "model": build_model(wider).state_dict()})
    with pytest.raises(InputError, match=r"wider.pt does not fit this model: .*blocks.0.mlp.0.weight \(48, 32\) "
                                         r"\(expected \(64, 32\)\).*it was trained with model.d_ff=48"):
        linear_pair_task(tmp_path, [f"task.init_from={tmp_path / 'wider.pt'}"])
    # A checkpoint of an earlier version with a removed option (a LayerNorm before the head).
    normed = {**plain.model_config(), "cross_window": 1, "output_norm": True}
    save_checkpoint(tmp_path / "normed.pt", {"task": "larynx_transformer", "model_config": normed,
                                             "model": plain.model.state_dict()})
    with pytest.raises(InputError, match=r"normed.pt does not fit this model: .*unknown \['cross_window', "
                                         r"'output_norm'\]"):
        linear_pair_task(tmp_path, [f"task.init_from={tmp_path / 'normed.pt'}"])
    save_checkpoint(tmp_path / "h2n.pt", {"task": "head2neck", "model_config": {}, "model": {}})
    with pytest.raises(InputError,
                       match="task.init_from=.*h2n.pt: checkpoint of task 'head2neck', expected 'larynx_transformer'"):
        linear_pair_task(tmp_path, [f"task.init_from={tmp_path / 'h2n.pt'}"])
    (tmp_path / "notes.pt").write_text("not a checkpoint\n")
    with pytest.raises(InputError, match="task.init_from=.*notes.pt: not a readable checkpoint: it is not a PyTorch "
                                         "file, or it holds objects other than tensors"):
        linear_pair_task(tmp_path, [f"task.init_from={tmp_path / 'notes.pt'}"])
    with pytest.raises(InputError, match="task.init_from=.*nowhere.pt: checkpoint not found"):
        linear_pair_task(tmp_path, [f"task.init_from={tmp_path / 'nowhere.pt'}"])


def test_the_shipped_model_fits_the_default_sizes(tmp_path):
    """task.init_from=pretrained starts from models/pretrained/larynx_transformer.pt: it must keep fitting the
    default model config (a change of the defaults needs the shipped model retrained).  The shipped model is an
    ensemble of the default number of members: member k starts from its member k."""
    from base.cli import compose_config
    from models.pretrained import load_default
    from tasks.larynx_transformer import Task

    linear_pair_task(tmp_path, [])  # writes the pairs folder
    cfg = compose_config("train", ["task=larynx_transformer", "data=pairs", f"data.path={tmp_path / 'linear'}",
                                   "task.init_from=pretrained"])
    shipped, _ = load_default("larynx_transformer")
    assert len(shipped.members) == cfg.task.members == 5
    for k in (0, 3):
        cfg.task.member = k
        task = Task(cfg)
        assert torch.equal(task.model.head.weight, shipped.members[k].head.weight)
        assert torch.equal(task.model.style.weight[1], shipped.members[k].style.weight[0])


# --------------------------------------------------------------------------- inference CLI


def test_infer_cli_streams_the_checkpoint(tmp_path):
    """infer.py resamples the take to the model's rate and writes the streamed tau of the subject's style."""
    from data.params import load_params

    model = random_model(subjects=["anna"], fps=30.0)
    checkpoint = tmp_path / "last.pt"
    save_checkpoint(checkpoint, {"task": "larynx_transformer", "model_config": model.config,
                                 "model": model.state_dict(), "step": 0})
    face_time = np.arange(121) / 60  # a 60 fps take, resampled to the model's 30 fps
    jaw = 0.5 + 0.4 * np.sin(2 * np.pi * face_time)
    write_csv(tmp_path / "take.csv", {"time": face_time, "jawOpen": jaw, "mouthPress_L": np.full(121, 0.2)},
              float_format="%.9g")
    out = tmp_path / "out"
    command = [sys.executable, "infer.py", f"checkpoint={checkpoint}", f"expressions={tmp_path / 'take.csv'}",
               "head2neck=none", "plot=false", "allow_missing=true"]
    result = subprocess.run(command + [f"out_dir={out}", "subject=anna"], cwd=REPO, capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr
    params = load_params(out / "params.npz")
    assert params.fps == 30.0 and len(params.tau) == 61
    psi = np.zeros((61, 55), np.float32)
    psi[:, K["jawOpen"]] = 0.5 + 0.4 * np.sin(2 * np.pi * np.arange(61) / 30)
    psi[:, K["mouthPress_L"]] = 0.2
    expected = generate_uncached(model, torch.from_numpy(psi)[None], torch.tensor([1]))[0].numpy()
    np.testing.assert_allclose(params.tau, expected, atol=1e-5 * model.config["tau_scale"])
    unknown = subprocess.run(command + [f"out_dir={tmp_path / 'zoe'}", "subject=zoe"], cwd=REPO,
                             capture_output=True, text=True, timeout=300)
    assert unknown.returncode == 2 and "subject 'zoe' was not in the training data" in unknown.stderr
    assert not (tmp_path / "zoe").exists()


def shifted_channel_pairs(folder: Path, takes: int, frames: int, seed: int, other_level: float) -> list:
    """Pairs whose tau follows two channels (a lagged, low-passed 0.03 * jawOpen - 0.02 * mouthSmile_L) while the
    other 53 move at random around ``other_level``: another capture (another tracker, another face) moves those
    channels elsewhere and the larynx does not care."""
    from scipy.signal import lfilter

    from data.pairs import LarynxSequence

    rng = np.random.default_rng(seed)
    out = []
    for take in range(takes):
        walk = np.cumsum(rng.standard_normal((frames, 55)), axis=0) / 12
        psi = np.clip(other_level + 0.15 * np.sin(walk), 0, 1)
        psi[:, K["jawOpen"]] = 0.35 + 0.3 * np.sin(walk[:, K["jawOpen"]] * 2)
        psi[:, K["mouthSmile_L"]] = 0.3 + 0.25 * np.sin(walk[:, K["mouthSmile_L"]] * 2)
        drive = 0.03 * psi[:, K["jawOpen"]] - 0.02 * psi[:, K["mouthSmile_L"]]
        tau = lfilter([0.2], [1, -0.8], np.concatenate([np.repeat(drive[:1], 4), drive])[:frames])
        sequence = LarynxSequence(psi.astype(np.float32), tau.astype(np.float32), 30.0, "anna", f"t{seed}_{take}")
        if folder is not None:
            save_pair(folder / f"{sequence.name}.npz", sequence)
        out.append(sequence)
    return out


def test_input_sparsity_keeps_the_channels_tau_follows(tmp_path):
    """task.input_sparsity: trained on pairs where tau follows two channels, the group lasso shrinks the other 53
    channels' input weights to under half of an unpenalised run's, and on takes where those channels sit elsewhere
    (a generator shifted in what the larynx ignores) the error is under half of that run's."""
    from tasks.larynx_transformer import rmse

    shifted_channel_pairs(tmp_path / "pairs", 4, 400, seed=1, other_level=0.2)
    heldout = shifted_channel_pairs(None, 2, 400, seed=2, other_level=0.7)
    results = {}
    for weight in (0.0, 0.03):
        cfg = tiny_config(["data=pairs", f"data.path={tmp_path / 'pairs'}", "data.val_fraction=0.25", "task.crop=64",
                           "model.window=16", "trainer.max_steps=250", f"task.input_sparsity={weight}",
                           "model.dropout=0"], data=[])
        fit(cfg, tmp_path / f"run{weight}")
        model = load_model(tmp_path / f"run{weight}" / "checkpoints" / "last.pt", "larynx_transformer")[0]
        norms = model.expression.project.weight.detach().norm(dim=0)
        followed = torch.zeros(55, dtype=torch.bool)
        followed[[K["jawOpen"], K["mouthSmile_L"]]] = True
        results[weight] = (float(norms[~followed].median()), float(norms[followed].min()),
                           rmse([predict_tau(model, s.psi, "anna") for s in heldout], heldout))
    assert results[0.03][0] < 0.5 * results[0.0][0], results  # the 53 channels tau does not follow
    assert results[0.03][2] < 0.5 * results[0.0][2], results
