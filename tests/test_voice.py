"""The voice moves the larynx (issue 45): audio decoding (data/audio.py), F0, the voice term (motion/voice/),
its place in infer.py and params.npz, the fit, and bad input.

Expectations come from outside the code under test: synthetic voices of known F0 contours (numpy), the
published mapping re-implemented here from its description (``reference_height``), Praat's own reading of
espeak-ng speech (parselmouth called directly on the file), and synthetic pairs of known parameters.
"""
from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from scipy.io import wavfile

from base.cli import compose_config, run_cli
from base.errors import InputError
from base.files import write_csv
from data.audio import read_audio, track_f0
from data.pairs import LarynxSequence, load_pair, save_pair
from data.params import load_params

try:
    import parselmouth
except ImportError:  # the voice needs it; tests skip with the reason
    parselmouth = None

needs_praat = pytest.mark.skipif(parselmouth is None, reason="praat-parselmouth not installed "
                                                             "(pip install praat-parselmouth==0.4.7)")
needs_espeak = pytest.mark.skipif(shutil.which("espeak-ng") is None, reason="espeak-ng not on PATH (apt install "
                                                                            "espeak-ng)")
needs_ffmpeg = pytest.mark.skipif(shutil.which("ffmpeg") is None, reason="ffmpeg not on PATH (apt install ffmpeg)")

TAU_PER_MM = 0.003   # issue 45: tau 0.03 is about 1 cm on HACK
RATE = 16000


# --------------------------------------------------------------------------- references, made here


def semitone_error(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """|12 log2(estimate / truth)|; inf where the estimate is unvoiced (0)."""
    with np.errstate(divide="ignore"):
        return np.where(estimate > 0, np.abs(12 * np.log2(np.maximum(estimate, 1e-9) / truth)), np.inf)


def reference_height(f0, dt, slope, knee, high_ratio, hold, rise, fall):
    """The documented mapping, written from its description (docs/voice.md), sample by sample."""
    centre = np.median(f0[f0 > 0])
    out, y, last, unvoiced_for = [], 0.0, None, 0.0
    for value in f0:
        if value > 0:
            s = 12 * np.log2(value / centre)
            last = slope * s if s <= knee else slope * knee + slope * high_ratio * (s - knee)
            target, unvoiced_for = last, 0.0
        else:
            unvoiced_for += dt
            target = last if last is not None and unvoiced_for <= hold + 1e-9 else 0.0
        constant = rise if target > y else fall
        y = y + (target - y) * (1 - np.exp(-dt / constant))
        out.append(y)
    return np.array(out)


def voiced_signal(f0_at, seconds: float, rate: int = RATE, seed: int = 0) -> np.ndarray:
    """A buzz with 1/k harmonics below 4 kHz at the F0 contour ``f0_at(t)`` (0 = silence, with faint noise)."""
    t = np.arange(int(seconds * rate)) / rate
    f0 = f0_at(t)
    phase = 2 * np.pi * np.cumsum(f0) / rate
    harmonics = sum(np.sin(k * phase) / k * (k * f0 < 4000) for k in range(1, 30))
    rng = np.random.default_rng(seed)
    return (0.3 * np.where(f0 > 0, harmonics, 0.0) + 1e-4 * rng.standard_normal(len(t))).astype(np.float32)


def glide(t):       # a male voice gliding 90 -> 180 Hz and back, gaps of silence
    f = 90 * 2 ** (np.abs(((t / 2) % 2) - 1))
    return np.where((t % 1.0) < 0.8, f, 0.0)


def vibrato(t):     # a sung 220 Hz note, +-1 semitone vibrato at 5.5 Hz, a rest at 2-2.4 s
    f = 220 * 2 ** (np.sin(2 * np.pi * 5.5 * t) / 12)
    return np.where((t < 2.0) | (t > 2.4), f, 0.0)


def speech_like(t):  # syllables at 4 Hz over a falling declination, 110-320 Hz
    f = 250 * 2 ** ((4 * np.sin(2 * np.pi * 0.7 * t) - 1.5 * t / 4 + 3 * np.sin(2 * np.pi * 2.1 * t)) / 12)
    return np.where(np.sin(2 * np.pi * 4 * t) > -0.5, f, 0.0)


SIGNALS = {"glide": glide, "vibrato": vibrato, "speech_like": speech_like}


def write_wav(path: Path, samples: np.ndarray, rate: int = RATE) -> Path:
    wavfile.write(path, rate, (np.clip(samples, -1, 1) * 32767).astype(np.int16))
    return path


def espeak(path: Path, voice: str, pitch: int, pitch_range: str = "x-high") -> Path:
    """espeak-ng speech: pitch with -p; pitch range with -P where this espeak-ng has it (1.52+), else SSML."""
    text = "The quick brown fox jumps over the lazy dog. Is it raining in Berlin today?"
    has_range = "-P" in subprocess.run(["espeak-ng", "--help"], capture_output=True, text=True).stdout
    if has_range:
        levels = {"x-low": "5", "medium": "50", "x-high": "99"}
        command = ["espeak-ng", "-w", str(path), "-v", voice, "-p", str(pitch), "-P", levels[pitch_range], text]
    else:
        ssml = f'<speak><prosody range="{pitch_range}">{text}</prosody></speak>'
        command = ["espeak-ng", "-m", "-w", str(path), "-v", voice, "-p", str(pitch), ssml]
    subprocess.run(command, check=True, capture_output=True)
    return path


def take_csv(path: Path, seconds: float, fps: float = 30.0) -> Path:
    t = np.arange(int(round(seconds * fps))) / fps
    write_csv(path, {"time": t, "jawOpen": 0.3 + 0.2 * np.sin(5 * t)}, float_format="%.9g")
    return path


def infer(*overrides):
    from infer import run

    return run(compose_config("infer", [*overrides, "allow_missing=true", "checkpoint=none", "head2neck=none"]))


# --------------------------------------------------------------------------- decoding and F0


@needs_praat
@pytest.mark.parametrize("name", sorted(SIGNALS))
def test_f0_of_known_contours_within_half_a_semitone(tmp_path, name):
    audio = read_audio(write_wav(tmp_path / f"{name}.wav", voiced_signal(SIGNALS[name], 4.0)))
    assert audio.rate == RATE and audio.duration == pytest.approx(4.0)
    time, f0 = track_f0(audio)
    truth = SIGNALS[name](time)
    # frames whose 40 ms analysis window (3 periods of the 60 Hz floor) lies wholly in a voiced stretch
    window = np.stack([SIGNALS[name](time + d) for d in np.linspace(-0.025, 0.025, 11)])
    voiced = (window > 0).all(axis=0)
    within = semitone_error(f0[voiced], truth[voiced]) < 0.5
    assert within.mean() >= 0.9, f"{name}: {within.mean():.3f} of voiced frames within half a semitone"
    silent = (window == 0).all(axis=0)
    assert (f0[silent] == 0).mean() >= 0.9  # silence is unvoiced


@needs_praat
def test_voice_term_follows_the_reference_mapping_of_the_true_contour(tmp_path):
    from motion.voice import VoiceConfig, analyse_voice

    voice = VoiceConfig()
    term = analyse_voice(read_audio(write_wav(tmp_path / "s.wav", voiced_signal(speech_like, 6.0))), voice)
    frames = np.arange(0, 6.0, 1 / 30)
    _, tau_voice = term.on_frames(frames)
    assert abs(float(tau_voice.mean())) < 1e-6  # zero-mean over the take by construction
    dt = 0.01
    grid = np.arange(0, 6.0, dt)
    reference = reference_height(speech_like(grid), dt, voice.slope, voice.knee, voice.high_ratio, voice.hold,
                                 voice.rise, voice.fall)
    expected = np.interp(frames, grid, reference) * TAU_PER_MM
    corr = np.corrcoef(tau_voice, expected)[0, 1]
    assert corr >= 0.95, corr
    assert np.std(tau_voice) == pytest.approx(np.std(expected), rel=0.15)  # the size too, not only the shape


@needs_praat
def test_height_is_flat_above_the_knee():
    from motion.voice import VoiceConfig, height_target

    voice = VoiceConfig(slope=2.0, knee=4.0, high_ratio=0.25)
    heights = height_target(np.array([-12.0, 0.0, 4.0, 8.0]), voice)
    np.testing.assert_allclose(heights, [-24.0, 0.0, 8.0, 8.0 + 0.25 * 2.0 * 4.0])


@needs_praat
@needs_espeak
@needs_ffmpeg
@pytest.mark.parametrize("voice", ["en", "en+f3", "de"])
def test_espeak_speech_matches_praats_own_reading(tmp_path, voice):
    from motion.voice import VoiceConfig, analyse_voice

    low, high = espeak(tmp_path / "low.wav", voice, 30), espeak(tmp_path / "high.wav", voice, 70)
    medians = []
    for path in (low, high):
        time, f0 = track_f0(read_audio(path))
        praat = parselmouth.Sound(str(path)).to_pitch_ac(time_step=0.01, pitch_floor=60.0, pitch_ceiling=700.0)
        theirs = praat.selected_array["frequency"]
        np.testing.assert_allclose(time, praat.xs(), atol=1e-9)
        voiced = theirs > 0
        assert voiced.mean() > 0.3
        assert (semitone_error(f0[voiced], theirs[voiced]) < 0.5).mean() >= 0.9
        medians.append(np.median(theirs[voiced]))
    assert medians[1] > medians[0] * 2 ** (3 / 12)  # -p 70 speaks higher than -p 30
    # through ffmpeg (.mp4, AAC): the same F0 as Praat's reading of the WAV
    mp4 = tmp_path / "high.mp4"
    subprocess.run(["ffmpeg", "-v", "error", "-i", str(high), "-c:a", "aac", str(mp4)], check=True)
    time, f0 = track_f0(read_audio(mp4))
    praat = parselmouth.Sound(str(high)).to_pitch_ac(time_step=0.01, pitch_floor=60.0, pitch_ceiling=700.0)
    theirs = praat.selected_array["frequency"]
    n = min(len(f0), len(theirs))
    voiced = theirs[:n] > 0
    assert (semitone_error(f0[:n][voiced], theirs[:n][voiced]) < 0.5).mean() >= 0.9
    # a wider pitch range moves the larynx more; the term is zero-mean over the take
    narrow = analyse_voice(read_audio(espeak(tmp_path / "narrow.wav", voice, 50, "x-low")), VoiceConfig())
    wide = analyse_voice(read_audio(espeak(tmp_path / "wide.wav", voice, 50, "x-high")), VoiceConfig())
    frames = np.arange(0, 4.0, 1 / 30)
    spreads = [np.std(t.on_frames(frames)[1]) for t in (narrow, wide)]
    assert spreads[1] > 2 * spreads[0]
    assert all(abs(float(t.on_frames(frames)[1].mean())) < 1e-6 for t in (narrow, wide))


# --------------------------------------------------------------------------- infer.py and params.npz


@needs_praat
@needs_ffmpeg
def test_infer_adds_the_voice_term_and_nothing_without_audio(tmp_path, capsys):
    from motion.voice import VoiceConfig

    takes = tmp_path / "takes"
    takes.mkdir()
    take_csv(takes / "a.csv", 4.0)
    take_csv(takes / "b.csv", 4.0)
    wav = write_wav(tmp_path / "a.wav", voiced_signal(speech_like, 4.0))
    subprocess.run(["ffmpeg", "-v", "error", "-f", "lavfi", "-i", "color=size=32x32:rate=30", "-i", str(wav),
                    "-shortest", "-c:v", "libx264", "-c:a", "aac", str(takes / "a.mov")], check=True)
    infer(f"expressions={takes / 'a.csv'}", f"out_dir={tmp_path / 'none'}", "audio=none")
    infer(f"expressions={takes}", f"out_dir={tmp_path / 'folder'}")
    assert "a.mov (the file beside the take" in capsys.readouterr().out
    silent = load_params(tmp_path / "none" / "params.npz")
    voiced = load_params(tmp_path / "folder" / "a" / "params.npz")
    plain = load_params(tmp_path / "folder" / "b" / "params.npz")          # no audio beside b.csv
    assert silent.f0 is None and silent.tau_voice is None and plain.f0 is None
    np.testing.assert_array_equal(plain.tau, silent.tau)
    assert sorted(np.load(tmp_path / "folder" / "b" / "params.npz").files) == \
        sorted(np.load(tmp_path / "none" / "params.npz").files)
    np.testing.assert_allclose(voiced.tau, silent.tau + voiced.tau_voice, atol=1e-7)
    truth = speech_like(voiced.time)
    assert (semitone_error(voiced.f0[truth > 0], truth[truth > 0]) < 0.5).mean() > 0.8
    expected = np.interp(voiced.time, np.arange(0, 4.0, 0.01), reference_height(
        speech_like(np.arange(0, 4.0, 0.01)), 0.01, **{k: getattr(VoiceConfig(), k) for k in
                                                        ("slope", "knee", "high_ratio", "hold", "rise", "fall")}))
    assert np.corrcoef(voiced.tau_voice, expected)[0, 1] >= 0.95
    assert "f0" in (tmp_path / "folder" / "a" / "params.csv").read_text().splitlines()[0].split(",")


@needs_praat
def test_silent_audio_gives_no_voice_term_and_a_note(tmp_path, capsys):
    take = take_csv(tmp_path / "take.csv", 3.0)
    wav = write_wav(tmp_path / "quiet.wav", np.zeros(3 * RATE, np.float32))
    infer(f"expressions={take}", f"out_dir={tmp_path / 'out'}", f"audio={wav}", "plot=false")
    assert "no voiced frames" in capsys.readouterr().out
    params = load_params(tmp_path / "out" / "params.npz")
    assert params.tau_voice is None and (params.f0 == 0).all()
    np.testing.assert_array_equal(params.tau, 0.0)  # no larynx model, no voice: tau rests


@needs_praat
def test_voice_json_sets_the_slope(tmp_path):
    take = take_csv(tmp_path / "take.csv", 4.0)
    wav = write_wav(tmp_path / "a.wav", voiced_signal(speech_like, 4.0))
    (tmp_path / "voice.json").write_text(json.dumps({"slope": 0.5}))
    infer(f"expressions={take}", f"out_dir={tmp_path / 'default'}", f"audio={wav}", "plot=false")
    infer(f"expressions={take}", f"out_dir={tmp_path / 'half'}", f"audio={wav}", "plot=false",
          f"voice={tmp_path / 'voice.json'}")
    full, small = (load_params(tmp_path / d / "params.npz").tau_voice for d in ("default", "half"))
    hirai = (19.4 + 29.9 + 10.8) / 3 / 12  # the default: Hirai et al. 1994's mean, mm per semitone
    np.testing.assert_allclose(small, full * 0.5 / hirai, atol=1e-6)


# --------------------------------------------------------------------------- fit


def synthetic_pairs(folder: Path, slope: float, rise: float, fall: float, seed: int = 3) -> None:
    """Pairs of random F0 contours (glides, syllables, pauses) and the tau they give under known parameters."""
    rng = np.random.default_rng(seed)
    folder.mkdir()
    fps = 50.0
    for k in range(3):
        frames = int(20 * fps)
        steps = np.repeat(rng.normal(0, 3, frames // 10), 10)               # a new pitch every 0.2 s
        pitch = np.convolve(steps, np.ones(4) / 4, mode="same")
        f0 = 120 * 2 ** (pitch / 12)
        pauses = np.repeat(rng.random(frames // 10) < 0.2, 10)
        f0[pauses] = 0.0
        height = reference_height(f0, 1 / fps, slope, 4.0, 0.25, 0.15, rise, fall)
        tau = 0.01 + height * TAU_PER_MM + 1e-4 * rng.standard_normal(frames)
        save_pair(folder / f"take{k}.npz", LarynxSequence(np.zeros((frames, 55), np.float32), tau.astype(np.float32),
                                                          fps, "synthetic", f"take{k}", f0=f0.astype(np.float32)))


@needs_praat
def test_fit_recovers_slope_and_time_constants(tmp_path, capsys):
    from motion.voice.cli import run

    synthetic_pairs(tmp_path / "pairs", slope=2.2, rise=0.12, fall=0.07)
    assert load_pair(tmp_path / "pairs" / "take0.npz").f0 is not None
    out = tmp_path / "voice.json"
    run(compose_config("voice", [f"pairs={tmp_path / 'pairs'}", f"out={out}", "checkpoint=none"]))
    fitted = json.loads(out.read_text())["voice"]
    assert fitted["slope"] == pytest.approx(2.2, rel=0.1)
    assert fitted["rise"] == pytest.approx(0.12, rel=0.1)
    assert fitted["fall"] == pytest.approx(0.07, rel=0.1)
    from motion.voice import load_voice

    assert load_voice(out).slope == pytest.approx(fitted["slope"])


@needs_praat
def test_pairs_with_audio_carry_f0(tmp_path):
    from data.pairs import run

    take = take_csv(tmp_path / "take.csv", 4.0)
    write_csv(tmp_path / "track.csv", {"time": np.arange(120) / 30, "tau": np.zeros(120)})
    wav = write_wav(tmp_path / "a.wav", voiced_signal(vibrato, 4.0))
    run(compose_config("pairs", [f"track={tmp_path / 'track.csv'}", f"expressions={take}", f"audio={wav}",
                                 f"out={tmp_path / 'pair.npz'}"]))
    pair = load_pair(tmp_path / "pair.npz")
    time = np.arange(len(pair)) / pair.fps
    inside = (vibrato(time) > 0) & (np.abs(time - 2.2) > 0.3) & (time > 0.05) & (time < 3.9)
    assert (semitone_error(pair.f0[inside], vibrato(time[inside])) < 0.5).mean() >= 0.9


# --------------------------------------------------------------------------- bad input


def exit_two(capsys, main, argv) -> str:
    with pytest.raises(SystemExit) as stop:
        run_cli(*main, argv=argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: ")
    return err


@needs_praat
@pytest.mark.parametrize("case", ["unreadable", "low_rate", "short"])
def test_bad_audio_is_one_line_exit_two_and_nothing_written(tmp_path, capsys, case):
    from infer import run

    take = take_csv(tmp_path / "take.csv", 4.0)
    audio = tmp_path / "audio.wav"
    if case == "unreadable":
        audio.write_text("this is not a sound\n")
    elif case == "low_rate":
        write_wav(audio, voiced_signal(glide, 4.0, rate=4000), rate=4000)
    else:
        write_wav(audio, voiced_signal(glide, 1.0))
    out = tmp_path / "out"
    err = exit_two(capsys, ("infer", run), [f"expressions={take}", f"audio={audio}", f"out_dir={out}",
                                            "checkpoint=none", "head2neck=none", "allow_missing=true"])
    assert str(audio) in err
    expected = {"unreadable": "not a readable audio", "low_rate": "4000 Hz, expected at least 8000 Hz",
                "short": f"shorter than the capture {take}"}[case]
    assert expected in err
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["audio.wav", "take.csv"]


def test_fit_refuses_pairs_without_f0(tmp_path, capsys):
    from motion.voice.cli import run

    (tmp_path / "pairs").mkdir()
    save_pair(tmp_path / "pairs" / "p.npz", LarynxSequence(np.zeros((10, 55), np.float32), np.zeros(10, np.float32),
                                                           30.0, None, "p"))
    err = exit_two(capsys, ("voice", run), [f"pairs={tmp_path / 'pairs'}", f"out={tmp_path / 'v.json'}",
                                            "checkpoint=none"])
    assert "without f0" in err and not (tmp_path / "v.json").exists()


def test_audio_file_not_found_names_the_key(tmp_path):
    with pytest.raises(InputError, match="audio=.*missing.wav: audio file not found"):
        read_audio(tmp_path / "missing.wav")


@needs_ffmpeg
def test_audio_beside_a_take(tmp_path):
    from data.audio import find_audio_beside

    take_csv(tmp_path / "a.csv", 1.0)
    assert find_audio_beside(tmp_path / "a.csv") is None
    write_wav(tmp_path / "a.wav", voiced_signal(glide, 1.0))
    assert find_audio_beside(tmp_path / "a.csv") == tmp_path / "a.wav"
    mute = tmp_path / "mute.mp4"  # a video take without a sound track has no audio (not an error)
    subprocess.run(["ffmpeg", "-v", "error", "-f", "lavfi", "-i", "color=size=32x32:rate=30:d=1", "-c:v", "libx264",
                    str(mute)], check=True)
    assert find_audio_beside(mute) is None
    with pytest.raises(InputError, match="no audio stream"):
        read_audio(mute)


FAKE_FFMPEG = """#!{python}
import json, sys
with open({log!r}, "a") as log:
    log.write(json.dumps(sys.argv) + "\\n")
if sys.argv[0].endswith("ffprobe"):
    print("1" if "csv=p=0" in sys.argv else json.dumps({{"streams": [{{"sample_rate": "16000", "channels": 1}}]}}))
else:
    sys.stdout.buffer.write(bytes(4 * 16000))    # one second of float32 silence
"""


def test_ffmpeg_and_ffprobe_get_files_as_absolute_paths(tmp_path, monkeypatch):
    """A file named ``-y.mp4`` or ``-report.mov`` reaches ffmpeg / ffprobe as a file, never as an option:
    recorded by stand-in executables on PATH (so this runs without ffmpeg)."""
    import os
    import sys

    from data.audio import has_sound

    bin_dir, log = tmp_path / "bin", tmp_path / "argv.jsonl"
    bin_dir.mkdir()
    for name in ("ffmpeg", "ffprobe"):
        (bin_dir / name).write_text(FAKE_FFMPEG.format(python=sys.executable, log=str(log)))
        (bin_dir / name).chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}{os.pathsep}{os.environ['PATH']}")
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    for name in ("-y.mp4", "-report.mov"):
        (work / name).write_bytes(b"not decoded by the stand-ins")
    audio = read_audio("-y.mp4")
    assert audio.rate == 16000 and audio.duration == pytest.approx(1.0)
    assert has_sound(Path("-report.mov"))
    calls = [json.loads(line) for line in log.read_text().splitlines()]
    assert [Path(argv[0]).name for argv in calls] == ["ffprobe", "ffmpeg", "ffprobe"]
    for argv, name in zip(calls, ("-y.mp4", "-y.mp4", "-report.mov")):
        assert str(work / name) in argv and name not in argv, argv
        assert not any(arg.startswith("-") and arg.endswith(name) for arg in argv), argv


@needs_ffmpeg
def test_a_file_named_like_an_option_is_decoded(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    write_wav(tmp_path / "a.wav", voiced_signal(glide, 1.0))
    subprocess.run(["ffmpeg", "-v", "error", "-i", "a.wav", "-c:a", "aac", "./-y.mp4"], check=True)
    audio = read_audio("-y.mp4")
    assert audio.rate == RATE and audio.duration == pytest.approx(1.0, abs=0.05)
