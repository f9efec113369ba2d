"""Expression -> larynx transformer: streaming decoder, synthetic data, training task, inference CLI."""
from __future__ import annotations

import dataclasses
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir

from data.expressions import EXPRESSION_NAMES
from data.errors import InputError
from data.files import write_csv
from data.tau_track import read_tau_track
from data.pairs import save_pair
from data.synthetic_larynx import (HELDOUT_SUBJECT_START, SWALLOW_PRESS_THRESHOLD, generate_expressions,
                                   larynx_response, make_dataset, make_sequence, split_subjects, subject_params)
from data.synthetic_tau import SWALLOW_LANDMARK_PHASES
from models.checkpoint import save_checkpoint
from models.larynx_transformer import build_model, predict_tau

REPO = Path(__file__).resolve().parents[1]
K = {name: k for k, name in enumerate(EXPRESSION_NAMES)}


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """Tiny tensors: a second thread only adds stalls on a shared CPU (the trainer config uses 1 too)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


TINY_MODEL = {"d_model": 16, "n_heads": 2, "n_layers": 2, "d_ff": 32, "window": 16, "cross_window": 1, "period": 5,
              "expression_layers": 1, "expression_kernel": 3, "dropout": 0.0, "use_eta": False}
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


@pytest.mark.parametrize("cross_window", [1, 3])
def test_cached_decoding_matches_full_recomputation(cross_window):
    model = random_model(cross_window=cross_window, subjects=["anna", "ben"], use_eta=True)
    psi = torch.rand(2, 70, 55, generator=torch.Generator().manual_seed(1))  # 70 frames: the 16-frame window wraps
    subject, eta = torch.tensor([0, 2]), torch.tensor([1.0, 1.15])
    reference = model.generate_uncached(psi, subject, eta) / model.tau_scale
    assert reference.std() > 0.1  # the comparison is not between constants
    cached = model.generate(psi, subject, eta, chunk=9) / model.tau_scale  # chunk boundaries inside
    stream = model.stream(2, subject, eta)
    stepped = torch.stack([stream.step(psi[:, t]) for t in range(70)], dim=1) / model.tau_scale
    assert (cached - reference).abs().max() < 1e-5
    assert (stepped - reference).abs().max() < 1e-5


@pytest.mark.parametrize("cross_window", [1, 3])
def test_every_parameter_gets_a_gradient(cross_window):
    """No dead weights: with a one-frame cross window the cross projection holds values only."""
    model = random_model(cross_window=cross_window).train()
    psi = torch.rand(2, 40, 55, generator=torch.Generator().manual_seed(6))
    previous = 0.02 * torch.randn(2, 40, generator=torch.Generator().manual_seed(7))
    model(psi, previous).pow(2).sum().backward()
    d = TINY_MODEL["d_model"]
    assert model.blocks[0].cross_kv.weight.shape == ((2 if cross_window > 1 else 1) * d, d)
    # Every output row of a weight matrix gets a gradient; a vector as a whole (the key part of an attention
    # bias shifts all scores of a query equally, which softmax ignores: no gradient there in any transformer).
    def rows(p):
        return p.grad.abs().reshape(len(p), -1) if p.ndim == 2 else p.grad.abs()[None]

    dead = [name for name, p in model.named_parameters() if p.grad is None or not (rows(p).amax(1) > 0).all()]
    assert not dead, dead


def test_forward_is_causal():
    model = random_model(cross_window=2)
    psi = torch.rand(1, 50, 55, generator=torch.Generator().manual_seed(2))
    previous = 0.02 * torch.randn(1, 50, generator=torch.Generator().manual_seed(3))
    changed_psi, changed_previous = psi.clone(), previous.clone()
    changed_psi[:, 30] += 0.5
    changed_previous[:, 40] += 0.05
    base = model(psi, previous)
    assert torch.equal(model(changed_psi, previous)[:, :30], base[:, :30])
    assert (model(changed_psi, previous)[:, 30] - base[:, 30]).abs().item() > 1e-4
    assert torch.equal(model(psi, changed_previous)[:, :40], base[:, :40])


@pytest.fixture(scope="module")
def long_stream():
    """10,000 frames through step(); the last 300 timed alternately with a stream at frames 200-500.

    Alternating the two streams step by step exposes both to the same load from other processes.
    """
    model = random_model()
    psi = torch.rand(10_000, 55, generator=torch.Generator().manual_seed(4))
    far, near = model.stream(1), model.stream(1)
    tau = [far.step(psi[t]) for t in range(9_700)]
    sizes = [far.cache_elements()]
    for t in range(200):
        near.step(psi[t])
    near_seconds, far_seconds = [], []
    for t in range(300):
        start = time.perf_counter()
        near.step(psi[200 + t])
        middle = time.perf_counter()
        tau.append(far.step(psi[9_700 + t]))
        far_seconds.append(time.perf_counter() - middle)
        near_seconds.append(middle - start)
    sizes.append(far.cache_elements())
    return model, psi, torch.cat(tau), np.array(near_seconds), np.array(far_seconds), sizes


def test_ten_thousand_frames_bounded_memory(long_stream):
    model, psi, tau, _, _, sizes = long_stream
    assert tau.shape == (10_000,) and torch.isfinite(tau).all()
    assert sizes[0] == sizes[1]  # the cache does not grow with the position
    whole = model.generate(psi[None])[0]  # the whole-sequence API agrees over many cache wrap-arounds
    assert ((whole - tau) / model.tau_scale).abs().max() < 1e-5


def test_per_frame_cost_is_flat(long_stream):
    near_seconds, far_seconds = long_stream[3], long_stream[4]
    ratio = np.median(far_seconds) / np.median(near_seconds)  # frames 9,700-10,000 vs 200-500
    assert ratio < 1.5, (np.median(near_seconds), np.median(far_seconds))


def test_model_config_needs_the_data_fields():
    """fps, subjects and the tau normalisation come from the training data: no silent defaults."""
    with pytest.raises(ValueError, match=r"missing \['fps', 'tau_scale'\], unknown \[\]"):
        build_model({**TINY_MODEL, "subjects": [], "tau_mean": 0.0})
    with pytest.raises(ValueError, match=r"missing \[\], unknown \['tau_std'\]"):
        build_model({**TINY_MODEL, **DATA_FIELDS, "tau_std": 0.02})


def test_predict_tau_and_subjects():
    model = random_model(subjects=["anna", "ben"])
    psi = np.random.default_rng(5).uniform(0, 1, (40, 55)).astype(np.float32)
    tau = predict_tau(model, psi, "ben")
    expected = model.generate_uncached(torch.from_numpy(psi)[None], torch.tensor([2]))[0].numpy()
    np.testing.assert_allclose(tau, expected, atol=1e-7)
    assert np.abs(predict_tau(model, psi) - tau).max() > 1e-4  # the average style differs from ben's
    with pytest.raises(InputError, match="subject 'carl' was not in the training data \\(known: anna, ben\\)"):
        predict_tau(model, psi, "carl")
    with pytest.raises(InputError, match=r"psi of shape \(40, 54\), expected \[T,55\]"):
        predict_tau(model, psi[:, :54])


# --------------------------------------------------------------------------- synthetic data


def test_synthetic_data_deterministic_and_subjects_disjoint():
    train_ids, heldout_ids = split_subjects(5, 3)
    assert not set(train_ids) & set(heldout_ids) and min(heldout_ids) >= HELDOUT_SUBJECT_START
    a, b = make_sequence(3, 1, 300, 30.0, seed=7), make_sequence(3, 1, 300, 30.0, seed=7)
    np.testing.assert_array_equal(a.psi, b.psi)
    np.testing.assert_array_equal(a.tau, b.tau)
    c = make_sequence(3, 1, 300, 30.0, seed=8)
    assert np.abs(c.tau - a.tau).max() > 1e-3
    assert a.psi.shape == (300, 55) and a.psi.min() >= 0 and a.psi.max() <= 1
    dataset = make_dataset(heldout_ids, 2, 10.0, 30.0, seed=7)
    assert len(dataset) == 6 and {s.subject for s in dataset} == {f"s{i}" for i in heldout_ids}


def test_generator_options_come_from_the_config():
    """configs/data_task/larynx_transformer_synthetic.yaml's noise and event rates reach the sequences."""
    from tasks.larynx_transformer import load_sequences

    def data(overrides):
        return tiny_config(data=["data.train_subjects=2", "data.sequences_per_subject=1", "data.seconds=60",
                                 "data.heldout_subjects=1", "data.heldout_sequences_per_subject=1"] + overrides).data

    def noise_free(sequence):
        index = int(sequence.subject[1:])
        return larynx_response(sequence.psi, sequence.fps, subject_params(index, seed=0))

    default, _ = load_sequences(data([]))
    residual = np.concatenate([s.tau - noise_free(s) for s in default])
    assert residual.std() == pytest.approx(0.0005, rel=0.1)  # the config's tau_noise
    idle = K["cheekPuff_L"]  # a weight the generator never drives: tracker noise only (clipped at 0)
    assert all(s.psi[:, idle].max() > 0.02 and s.psi[:, K["eyeBlink_L"]].max() > 0.5 for s in default)
    quiet, _ = load_sequences(data(["data.tau_noise=0", "data.blinks_per_minute=0", "data.expression_noise=0"]))
    for s in quiet:
        np.testing.assert_allclose(s.tau, noise_free(s), atol=1e-6)  # float32 rounding only
        assert s.psi[:, idle].max() == 0.0 and s.psi[:, K["eyeBlink_L"]].max() == 0.0
    busy, _ = load_sequences(data(["data.swallows_per_minute=60"]))
    assert sum(swallow_count(s) for s in busy) > sum(swallow_count(s) for s in default) > 0


def swallow_count(sequence) -> int:
    """Lip presses (jaw closed) crossing the swallow threshold: how data.synthetic_larynx marks a swallow."""
    press = np.minimum(sequence.psi[:, K["mouthPress_L"]], sequence.psi[:, K["mouthPress_R"]])
    seal = press * (1 - sequence.psi[:, K["jawOpen"]]) >= SWALLOW_PRESS_THRESHOLD
    return int(np.sum(seal[1:] & ~seal[:-1]))


def test_larynx_process_is_causal_and_subject_dependent():
    params = subject_params(2, seed=0)
    psi = generate_expressions(600, 30.0, params, np.random.default_rng(0))
    tau = larynx_response(psi, 30.0, params)
    for t in (50, 311, 599):
        np.testing.assert_array_equal(larynx_response(psi[:t], 30.0, params), tau[:t])
    other = larynx_response(psi, 30.0, subject_params(3, seed=0))
    assert np.abs(other - tau).max() > 1e-3


def test_swallow_pattern_raises_tau():
    """A lip press with the jaw closed starts a swallow: peak at 40% of its duration, amplitude set by the chin."""
    fps = 30.0
    params = dataclasses.replace(subject_params(0, seed=0), rest=0.0, effort_gain=0.0)  # the swallow path alone
    psi = np.zeros((120, 55), np.float32)
    press = np.clip((np.arange(120) - 30) / 10, 0, 1) * 0.8  # ramps 0 -> 0.8 from frame 30 to 40
    psi[:, K["mouthPress_L"]] = psi[:, K["mouthPress_R"]] = press
    psi[:, K["mouthShrugLower"]] = 0.5
    onset = int(np.argmax(press >= SWALLOW_PRESS_THRESHOLD))
    tau = larynx_response(psi, fps, params)
    peak = onset + SWALLOW_LANDMARK_PHASES[2] * params.swallow_duration * fps
    assert abs(np.argmax(tau) - peak) <= 1
    low_chin = psi.copy()
    low_chin[:, K["mouthShrugLower"]] = 0.25
    low_peak = larynx_response(low_chin, fps, params).max()
    assert tau.max() > 1.1 * low_peak  # the chin raise sets the amplitude: higher chin, larger swallow
    assert 0.5 * params.swallow_amplitude < low_peak < tau.max() < 1.5 * params.swallow_amplitude
    assert np.abs(tau[:onset]).max() < 1e-3  # nothing before the press crosses the threshold
    weak = psi.copy()
    weak[:, [K["mouthPress_L"], K["mouthPress_R"]]] = np.minimum(press, 0.9 * SWALLOW_PRESS_THRESHOLD)[:, None]
    assert np.abs(larynx_response(weak, fps, params)).max() < 1e-3  # a bilabial-strength press is no swallow


# --------------------------------------------------------------------------- training


def tiny_config(run_overrides=(), data=None):
    base = ["model.d_model=32", "model.n_heads=4", "model.d_ff=64", "model.window=32", "model.period=10",
            "model.expression_layers=2", "task.crop=96", "task.batch_size=12", "task.eval_batch=16",
            "trainer.eval_every=0", "trainer.checkpoint_every=100000", "trainer.log_every=50",
            "trainer.progress=false", "optim.warmup_steps=30"]
    data = data if data is not None else ["data.train_subjects=12", "data.sequences_per_subject=4", "data.seconds=20",
                    "data.heldout_subjects=4", "data.heldout_sequences_per_subject=2"]
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return compose("train", overrides=base + data + list(run_overrides))


def fit(cfg, run_dir: Path):
    import train

    run_dir.mkdir(parents=True, exist_ok=True)
    return train.fit(cfg, run_dir)


def test_tiny_training_beats_ridge_and_mean(tmp_path, capsys):
    result = fit(tiny_config(["trainer.max_steps=300"]), tmp_path / "run")
    assert result["rmse"] < 0.85 * result["ridge_rmse"], result
    assert result["rmse"] < 0.5 * result["mean_rmse"], result
    printed = capsys.readouterr().out
    assert "ridge, 30-frame window" in printed and "training mean" in printed
    assert (tmp_path / "run" / "checkpoints" / "last.pt").is_file()


SHORT_DATA = ["data.train_subjects=3", "data.sequences_per_subject=2", "data.seconds=8",
              "data.heldout_subjects=1", "data.heldout_sequences_per_subject=1"]


def test_reproducible_and_exact_resume(tmp_path):
    def weights(run_dir):
        return torch.load(run_dir / "checkpoints" / "last.pt", weights_only=True)["model"]

    # 12 steps: scheduled sampling switches on at step 2 (10% of max_steps), so its passes are covered.
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


def test_pairs_folder_split_by_file(tmp_path):
    from tasks.larynx_transformer import Task

    folder = tmp_path / "pairs"
    for i in range(5):
        sequence = make_sequence(i % 2, i, 240, 30.0, seed=1)
        sequence.name = f"take{i}"
        save_pair(folder / f"take{i}.npz", sequence)
    cfg = tiny_config(["data=pairs", f"data.path={folder}", "data.val_fraction=0.4", "task.crop=64",
                       "model.window=16"], data=[])
    task = Task(cfg)
    assert (len(task.train), len(task.val)) == (3, 2)
    assert not {s.name for s in task.train} & {s.name for s in task.val}
    assert task.model.subjects == sorted({s.subject for s in task.train})
    train_mean = np.concatenate([s.tau for s in task.train]).astype(np.float64).mean()
    val_tau = np.concatenate([s.tau for s in task.val]).astype(np.float64)
    metrics = task.evaluate()
    assert metrics["mean_rmse"] == pytest.approx(np.sqrt(np.mean((val_tau - train_mean) ** 2)), rel=1e-6)
    batch = task.batch(0, torch.Generator().manual_seed(0))
    assert batch["psi"].shape == (12, 64, 55) and batch["tau"].shape == (12, 64)


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
    assert f"{len(short)} of {len(everything)} training sequences are shorter than task.crop=64" in printed
    assert all(f"{name} (40 frames)" in printed for name in short)
    assert sorted(s.name for s in task.train) == sorted(s.name for s in everything if len(s) >= 64)
    assert task.model.subjects == ["s0", "s1"]  # not s5, seen in short files only
    usable_tau = np.concatenate([s.tau for s in everything if len(s) >= 64]).astype(np.float64)
    assert float(task.model.tau_mean) == pytest.approx(usable_tau.mean(), rel=1e-5)
    assert float(task.model.tau_scale) == pytest.approx(usable_tau.std(), rel=1e-4)
    with pytest.raises(InputError, match="no training sequence has task.crop=300 frames .longest: 240."):
        Task(tiny_config(["data=pairs", f"data.path={folder}", "data.val_fraction=0.2", "task.crop=300"], data=[]))


# --------------------------------------------------------------------------- inference CLI


def test_infer_cli_writes_tau_track(tmp_path):
    model = random_model(subjects=["anna"], fps=30.0)
    checkpoint = tmp_path / "last.pt"
    save_checkpoint(checkpoint, {"task": "larynx_transformer", "model_config": model.config,
                                 "model": model.state_dict(), "step": 0})
    face_time = np.arange(121) / 60  # a 60 fps take, resampled to the model's 30 fps
    jaw = 0.5 + 0.4 * np.sin(2 * np.pi * face_time)
    write_csv(tmp_path / "take.csv", {"time": face_time, "jawOpen": jaw, "mouthPress_L": np.full(121, 0.2)},
              float_format="%.9g")
    out = tmp_path / "tau.csv"
    result = subprocess.run([sys.executable, "infer.py", f"checkpoint={checkpoint}",
                             f"expressions={tmp_path / 'take.csv'}", f"out={out}", "subject=anna"],
                            cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    track = read_tau_track(out)
    assert track.fps == 30.0 and len(track) == 61
    np.testing.assert_allclose(track.time, np.arange(61) / 30, atol=1e-5)
    psi = np.zeros((61, 55), np.float32)
    psi[:, K["jawOpen"]] = 0.5 + 0.4 * np.sin(2 * np.pi * np.arange(61) / 30)
    psi[:, K["mouthPress_L"]] = 0.2
    expected = model.generate_uncached(torch.from_numpy(psi)[None], torch.tensor([1]))[0].numpy()
    np.testing.assert_allclose(track.tau, expected, atol=1e-5 * model.config["tau_scale"])

    import infer

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        unknown = compose("infer", overrides=[f"checkpoint={checkpoint}", f"expressions={tmp_path / 'take.csv'}",
                                              f"out={tmp_path / 'zoe.csv'}", "subject=zoe"])
    with pytest.raises(InputError, match="subject 'zoe' was not in the training data"):
        infer.run(unknown)
    assert not (tmp_path / "zoe.csv").exists()
