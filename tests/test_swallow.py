"""Swallow template (motion/swallow.py): detection, landmark registration, playback, CLI.

Synthetic clips come from a known generating process (data.synthetic_tau):
one swallow shape under random centred monotone time warps, amplitude and
duration scaling, rest offsets and noise, so the truth is the structural mean
``swallow_profile(t, 0, mean duration, mean amplitude)``.
"""
from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from data.errors import InputError

from data.files import save_npy, write_csv

from data.tables import CsvTable

from data.tau_track import TauTrack, read_tau_track, write_tau_track
from data.synthetic_tau import (SWALLOW_AMPLITUDE, SWALLOW_DURATION, SwallowShape, random_monotone_warps,
                                random_tau_trajectory, swallow_landmark_times, swallow_profile,
                                warped_swallow_clips)
from motion.swallow import (LANDMARK_NAMES, PEAK, SwallowConfig, SwallowTemplate, build_template, detect_swallows,
                            insert_swallows, read_template, shift_aligned_error, write_template)

REPO = Path(__file__).resolve().parents[1]


def tracks_of(clips, prefix="clip"):
    return [TauTrack(c.tau, c.time, c.fps, f"{prefix}{i}") for i, c in enumerate(clips)]


def structural_mean(clips):
    """(time [R], tau [R]): the known template the clips were made from, at their mean amplitude and duration."""
    amplitude = np.mean([c.amplitude for c in clips])
    duration = np.mean([c.duration for c in clips])
    time = np.arange(-0.4, duration + 0.4, 0.002)
    return time, swallow_profile(time, 0.0, duration, amplitude), amplitude


def best_shift_max_error(time, values, ref_time, ref_values, max_shift=2.0, step=0.002):
    """min over time shifts of max |curve - reference| on the reference's span (curve 0 outside its own)."""
    errors = [np.max(np.abs(np.interp(ref_time, time + s, values, left=0.0, right=0.0) - ref_values))
              for s in np.arange(-max_shift, max_shift + step / 2, step)]
    return float(min(errors))


def naive_mean(clips):
    """The unaligned mean: clips minus their true rest level, on time since their start, over the common span."""
    span = min(c.time[-1] for c in clips)
    time = np.arange(0.0, span, 1 / 60)
    return time, np.mean([np.interp(time, c.time, c.tau - c.offset) for c in clips], axis=0)


# --------------------------------------------------------------------------- shared generator


def test_random_monotone_warps_are_increasing_and_centred():
    phase, warps = random_monotone_warps(7, seed=3, strength=0.4)
    assert warps.shape == (7, len(phase))
    assert (np.diff(warps, axis=1) > 0).all()
    np.testing.assert_allclose(warps[:, [0, -1]], [[0.0, 1.0]] * 7, atol=1e-12)
    np.testing.assert_allclose(warps.mean(axis=0), phase, atol=1e-9)
    assert np.abs(warps - phase).max() > 0.03  # really warped


# --------------------------------------------------------------------------- registration accuracy


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("warp", ["linear", "pchip"])
def test_template_recovers_known_swallow(seed, warp):
    clips = warped_swallow_clips(12, seed=seed)
    build = build_template(tracks_of(clips), SwallowConfig(warp=warp))
    truth_time, truth, amplitude = structural_mean(clips)
    error = best_shift_max_error(build.template.time, build.template.tau, truth_time, truth)
    naive_error = best_shift_max_error(*naive_mean(clips), truth_time, truth)
    assert len(build.events) >= 10
    assert error < 0.05 * amplitude, f"template max error {error / amplitude:.1%} of the peak"
    assert error < 0.25 * naive_error, f"template {error / amplitude:.1%} vs naive mean {naive_error / amplitude:.1%}"
    assert abs(build.template.peak_height - amplitude) < 0.05 * amplitude
    assert build.template.std.shape == build.template.tau.shape and (build.template.std >= 0).all()


def test_different_lengths_and_sampling_rates():
    rng = np.random.default_rng(5)
    clips = warped_swallow_clips(10, seed=11, fps_choices=(24.0, 30.0, 100.0, 120.0), lead=(0.2, 4.0),
                                 tail=(0.35, 5.0))
    tracks = tracks_of(clips)
    # One clip with an irregular time column (a tracker dropping frames): resampled, not misread.
    c = clips[0]
    keep = np.sort(rng.choice(len(c.time), size=int(0.8 * len(c.time)), replace=False))
    keep[0], keep[-1] = 0, len(c.time) - 1
    tracks[0] = TauTrack(c.tau[keep], c.time[keep], c.fps, "irregular")
    assert len({len(t) for t in tracks}) == len(tracks) and len({t.fps for t in tracks}) == 4
    build = build_template(tracks)
    truth_time, truth, amplitude = structural_mean(clips)
    error = best_shift_max_error(build.template.time, build.template.tau, truth_time, truth)
    assert len(build.events) == 10
    assert error < 0.05 * amplitude, f"template max error {error / amplitude:.1%} of the peak"


# --------------------------------------------------------------------------- detection


SEVERAL_AMPLITUDES = np.array([0.9, 1.1, 0.8, 1.0]) * SWALLOW_AMPLITUDE  # of the swallows in several_swallows()


def several_swallows(fps=50.0, seed=0):
    onsets = np.array([1.5, 5.2, 9.0, 14.1])
    durations = np.array([1.0, 1.2, 0.9, 1.1]) * SWALLOW_DURATION
    amplitudes = SEVERAL_AMPLITUDES
    time = np.arange(0, 17.0, 1 / fps)
    rng = np.random.default_rng(seed)
    tau = 0.01 + 0.004 * np.sin(2 * np.pi * time / 25.0) + 0.0008 * rng.standard_normal(len(time))
    for t, d, a in zip(onsets, durations, amplitudes):
        tau += swallow_profile(time, t, d, a)
    truth = np.stack([swallow_landmark_times(t, d) for t, d in zip(onsets, durations)])
    return time, tau, fps, truth


def test_several_swallows_detected_with_landmarks_near_truth():
    time, tau, fps, truth = several_swallows()
    events = detect_swallows(tau, fps)
    assert len(events) == 4
    detected = np.stack([e.times for e in events])
    assert np.isfinite(detected).all(), [e.reason() for e in events]
    # Extrema are located to a frame or two.  Onset and return are tangent intercepts with rest of curves
    # that leave / reach rest with zero slope, so they sit inside the true span by about 1/6 of the
    # neighbouring flank: onset->dip is 0.12 x duration (<= 0.16 s here), undershoot->return 0.32 x
    # duration (<= 0.42 s, i.e. ~0.07 s early) and nearly flat at its end, where noise moves it further.
    tolerance = {"onset": 0.05, "dip": 0.03, "peak": 0.02, "undershoot": 0.05, "return": 0.15}
    for k, name in enumerate(LANDMARK_NAMES):
        error = np.abs(detected[:, k] - truth[:, k]).max()
        assert error < tolerance[name], f"{name}: max error {error:.3f} s"
    heights = np.array([e.height for e in events])
    np.testing.assert_allclose(heights, SEVERAL_AMPLITUDES, rtol=0.06)


def test_track_with_several_swallows_gives_a_template_from_all():
    time, tau, fps, _ = several_swallows(seed=1)
    build = build_template([TauTrack(tau, time, fps, "several.csv")])
    assert build.clips[0].found == 4 and build.clips[0].used == 4
    assert len(build.events) == 4
    # The swallows share one shape: registered by their landmarks, their mean peaks at their mean amplitude.
    assert build.template.peak_height == pytest.approx(SEVERAL_AMPLITUDES.mean(), rel=0.1)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_swallows_found_in_speech_and_drift(seed):
    """random_tau_trajectory: swallows among 2-6 Hz speech wobble and drift; each found once, nothing else."""
    fps = 30.0
    tau, onsets = random_tau_trajectory(int(60 * fps), fps, seed, swallows_per_minute=8.0)
    events = detect_swallows(tau, fps)
    peaks = np.array([e.times[PEAK] for e in events])
    assert len(onsets) >= 3 and len(events) == len(onsets)
    # The peak is at 0.4 of a duration drawn in [0.8, 1.25] x 1.1 s after the onset.
    delay = peaks - onsets
    assert ((delay > 0.4 * 0.8 * SWALLOW_DURATION - 0.05) & (delay < 0.4 * 1.25 * SWALLOW_DURATION + 0.05)).all()


def test_clip_without_swallow_is_reported_not_averaged():
    clips = warped_swallow_clips(6, seed=4)
    speech, _ = random_tau_trajectory(300, 30.0, seed=9, swallows_per_minute=0.0)
    quiet = TauTrack(speech + 0.02, np.arange(300) / 30.0, 30.0, "speech_only.csv")
    with_quiet = build_template(tracks_of(clips) + [quiet])
    without = build_template(tracks_of(clips))
    report = with_quiet.clips[-1]
    assert not report.is_used and report.found == 0
    assert "no swallow" in report.reasons[0] and "prominence" in report.reasons[0]
    assert "rejected speech_only.csv: no swallow" in with_quiet.report()
    np.testing.assert_allclose(with_quiet.template.tau, without.template.tau, atol=1e-12)
    with pytest.raises(InputError, match="speech_only.csv: no swallow"):
        build_template([quiet])


def test_different_landmark_sets_matched_or_rejected():
    no_dip = SwallowShape(levels=[0.0, 0.0, 1.0, -0.22, 0.0])
    with_dip = warped_swallow_clips(5, seed=6, noise=0.0005)
    without_dip = warped_swallow_clips(2, seed=7, noise=0.0005, shape=no_dip)
    # Most swallows have a dip: the template uses all five landmarks, the dip-less ones are rejected.
    build = build_template(tracks_of(with_dip, "dip") + tracks_of(without_dip, "nodip"))
    assert build.template.landmark_names == LANDMARK_NAMES
    assert [c.is_used for c in build.clips] == [True] * 5 + [False] * 2
    assert all("has no dip" in c.reasons[0] for c in build.clips[5:])
    # Most have none: the dip is dropped from the landmarks and every swallow is used.
    build = build_template(tracks_of(with_dip[:2], "dip") + tracks_of(
        warped_swallow_clips(4, seed=8, noise=0.0005, shape=no_dip), "nodip"))
    assert build.template.landmark_names == ("onset", "peak", "undershoot", "return")
    assert all(c.is_used for c in build.clips)


def test_outlier_duration_rejected_with_reason():
    clips = warped_swallow_clips(5, seed=12, noise=0.0005)
    long = warped_swallow_clips(1, seed=13, noise=0.0005, duration_range=(2.6, 2.6), tail=(2.0, 2.0))
    build = build_template(tracks_of(clips) + tracks_of(long, "long"))
    assert not build.clips[-1].is_used
    assert "max_duration_ratio" in build.clips[-1].reasons[0]


# --------------------------------------------------------------------------- playback


def known_template(fps=60.0) -> SwallowTemplate:
    time = np.arange(-0.3, SWALLOW_DURATION + 0.3, 1 / fps)
    return SwallowTemplate(time, swallow_profile(time), np.zeros(len(time)), fps,
                           swallow_landmark_times(), LANDMARK_NAMES)


def test_playback_matches_scaled_template_and_blends_continuously():
    fps, at, stretch, gain = 30.0, 3.0, 1.3, 0.7
    time = np.arange(0, 8.0, 1 / fps)
    rest = 0.02 + 0.001 * time
    template = known_template()
    expected = gain * swallow_profile(time, at, stretch * SWALLOW_DURATION)
    out = insert_swallows(rest, time, template, [at], stretch, gain)
    middle = (time > at) & (time < at + stretch * SWALLOW_DURATION)
    assert np.abs(out - rest - expected)[middle].max() < 0.01 * gain * SWALLOW_AMPLITUDE
    assert np.abs(out - rest)[(time < at - 0.4 * stretch) | (time > at + stretch * 1.45)].max() < 1e-12

    # On a track with its own (speech) motion, replacing it must not create a jump: no frame step larger
    # than the largest step of the input track or of the inserted curve.
    wobble, _ = random_tau_trajectory(len(time), fps, seed=3, swallows_per_minute=0.0)
    track = rest + wobble
    out = insert_swallows(track, time, template, [at], stretch, gain)
    limit = max(np.abs(np.diff(track)).max(), np.abs(np.diff(expected)).max())
    assert np.abs(np.diff(out)).max() <= limit
    np.testing.assert_allclose(out[time < at - 0.4 * stretch], track[time < at - 0.4 * stretch])


def test_playback_add_mode_and_batched_tracks():
    fps = 25.0
    time = np.arange(0, 6.0, 1 / fps)
    template = known_template()
    batch = np.stack([0.01 * np.sin(time), np.full(len(time), -0.02)])
    added = insert_swallows(batch, time, template, [1.0, 3.5], [1.0, 0.8], [1.0, 1.2], SwallowConfig(blend="add"))
    expected = swallow_profile(time, 1.0) + 1.2 * swallow_profile(time, 3.5, 0.8 * SWALLOW_DURATION)
    # The template is sampled at 60 fps: interpolating it at 25 fps shaves at most a fraction of a percent.
    np.testing.assert_allclose(added - batch, np.broadcast_to(expected, batch.shape), atol=5e-3 * SWALLOW_AMPLITUDE)
    replaced = insert_swallows(batch, time, template, [1.0])
    np.testing.assert_allclose(replaced[1], insert_swallows(batch[1], time, template, [1.0]))
    with pytest.raises(ValueError, match="outside the track"):
        insert_swallows(batch, time, template, [20.0])


def test_template_file_round_trip(tmp_path):
    template = known_template()
    template.std[:] = 0.001
    write_template(tmp_path / "t.csv", template)
    assert CsvTable(tmp_path / "t.csv").header == ["time", "tau", "std"]
    back = read_template(tmp_path / "t.csv")
    np.testing.assert_allclose(back.tau, template.tau, atol=1e-7)
    np.testing.assert_allclose(back.time, template.time, atol=1e-6)
    assert back.fps == pytest.approx(60.0, rel=1e-4)
    assert back.peak_height == pytest.approx(SWALLOW_AMPLITUDE, rel=0.01)  # sampled at 60 fps


# --------------------------------------------------------------------------- CLI and bad input


def compose(overrides):
    from hydra import compose as hydra_compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return hydra_compose("swallow", overrides=overrides)


def test_yaml_mirrors_config_dataclass():
    with open(REPO / "configs" / "swallow.yaml") as f:
        section = yaml.safe_load(f)["swallow"]
    assert section == dataclasses.asdict(SwallowConfig())


def write_clips(tmp_path, clips):
    paths = []
    for i, c in enumerate(clips):
        if i == 0:
            save_npy(tmp_path / "c0.npy", c.tau)
            paths.append(str(tmp_path / "c0.npy"))
        else:
            write_tau_track(tmp_path / f"c{i}.csv", TauTrack(c.tau, c.time, c.fps))
            paths.append(str(tmp_path / f"c{i}.csv"))
    return paths


def test_cli_round_trip_in_process(tmp_path, capsys):
    from motion.swallow import run

    clips = warped_swallow_clips(6, seed=21, fps_choices=(30.0,))
    paths = write_clips(tmp_path, clips)
    out, plot = tmp_path / "template.csv", tmp_path / "template.png"
    build = run(compose([f"inputs=[{','.join(paths)}]", "fps=30", f"out={out}", f"plot={plot}"]))
    table = CsvTable(out)
    assert table.header == ["time", "tau", "std"]
    np.testing.assert_allclose(table.numeric("tau"), build.template.tau, rtol=1e-5, atol=1e-9)
    assert plot.stat().st_size > 20_000
    printed = capsys.readouterr().out
    assert "6 swallow(s) from 6 of 6 clip(s)" in printed and "peak height" in printed and "duration" in printed

    # Played into a track at rest (a level plus tracker noise), the swallow rises half the template's peak.
    played, track = tmp_path / "played.csv", tmp_path / "rest.csv"
    rest_time = np.arange(90) / 30.0
    rest_tau = 0.01 + 0.0003 * np.random.default_rng(0).standard_normal(len(rest_time))
    write_tau_track(track, TauTrack(rest_tau, rest_time, 30.0))
    run(compose(["mode=play", f"track={track}", f"template={out}", "at=[1.0]", "amplitude_scale=0.5",
                 f"out={played}"]))
    before, after = read_tau_track(track), read_tau_track(played)
    np.testing.assert_allclose(after.time, before.time, atol=1e-6)
    assert after.tau.max() - 0.01 == pytest.approx(0.5 * build.template.peak_height, rel=0.05)
    untouched = before.time < 1.0 + build.template.time[0]  # before the insert's span (its padding included)
    np.testing.assert_allclose(after.tau[untouched], before.tau[untouched], atol=1e-9)


def test_cli_subprocess_and_error_naming_the_file(tmp_path):
    from motion.swallow import run

    clips = warped_swallow_clips(3, seed=22)
    paths = write_clips(tmp_path, clips)[1:]
    out, plot = tmp_path / "t.csv", tmp_path / "t.png"
    done = subprocess.run([sys.executable, "-m", "motion.swallow", f"inputs=[{','.join(paths)}]", f"out={out}",
                           f"plot={plot}"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert CsvTable(out).header == ["time", "tau", "std"] and plot.stat().st_size > 20_000
    bad = tmp_path / "bad.csv"
    write_csv(bad, {"time": [0.0, 0.1], "height": [0.0, 0.1]})
    with pytest.raises(InputError, match=re.escape(f"{bad}: no column 'tau'")):
        run(compose([f"inputs=[{paths[0]},{bad}]", f"out={tmp_path / 'bad_template.csv'}"]))


def test_bad_inputs_name_file_and_what_was_expected(tmp_path):
    from motion.swallow import read_tracks, run

    save_npy(tmp_path / "a.npy", np.zeros(50))
    with pytest.raises(InputError, match=r"a\.npy: a \.npy tau track carries no frame rate; give fps=\.\.\."):
        read_tracks([tmp_path / "a.npy"])
    bad_number = tmp_path / "n.csv"
    bad_number.write_text("time,tau\n0,0.1\n0.1,oops\n")
    with pytest.raises(InputError, match=r"n\.csv: column 'tau', line 3: expected a number, found 'oops'"):
        read_tracks([bad_number])
    negative = tmp_path / "neg.csv"
    negative.write_text("time,tau,std\n0,0,0.1\n0.1,0.01,-1\n0.2,0,0\n")
    with pytest.raises(InputError, match=r"neg\.csv: column 'std', line 3: negative"):
        read_template(negative)
    with pytest.raises(InputError, match="mode=play needs at="):
        run(compose(["mode=play", f"track={bad_number}", f"template={negative}", f"out={tmp_path / 'o.csv'}"]))
    with pytest.raises(InputError, match=r"swallow \(configs/swallow\.yaml\): unknown keys \['typo'\]"):
        run(compose([f"inputs=[{bad_number}]", f"out={tmp_path / 'o.csv'}", "+swallow.typo=1"]))
    with pytest.raises(InputError, match=r"swallow\.fade_seconds\) must be positive, got 0"):
        run(compose([f"inputs=[{bad_number}]", f"out={tmp_path / 'o.csv'}", "swallow.fade_seconds=0"]))
    with pytest.raises(ValueError, match=r"SwallowConfig\.fade_seconds .* must be positive, got -0\.1"):
        SwallowConfig(fade_seconds=-0.1)


def tracker_csv(path, tau, fps, lost_before=0, rejected=(), px_per_tau=3000.0):
    """A motion.track CSV: frame,time,x_px,y_px,tau_px,tau,confidence, NaN and confidence 0 for the first
    ``lost_before`` frames (not found yet), confidence 0 at ``rejected`` frames (their tau held, here made
    obviously wrong); px_per_tau=None: no calibration (tau NaN)."""
    tau = np.array(tau, dtype=np.float64)
    confidence = np.full(len(tau), 0.8)
    confidence[:lost_before] = 0.0
    tau[:lost_before] = np.nan
    for i in rejected:
        tau[i], confidence[i] = 0.5, 0.0  # 15 cm: a value no larynx takes
    tau_px = tau * (px_per_tau or 3000.0)
    write_csv(path, {"frame": np.arange(len(tau)), "time": np.arange(len(tau)) / fps, "x_px": np.full(len(tau), 64.0),
                     "y_px": 200 - tau_px, "tau_px": tau_px, "tau": tau if px_per_tau else np.full(len(tau), np.nan),
                     "confidence": confidence}, float_format="%.9g")
    return path


def test_tracker_csvs_drop_lost_and_rejected_frames(tmp_path):
    from motion.swallow import run

    clips = warped_swallow_clips(4, seed=31, fps_choices=(30.0,))
    paths = [tracker_csv(tmp_path / f"track{i}.csv", c.tau, c.fps, lost_before=4) for i, c in enumerate(clips)]
    out = tmp_path / "template.csv"
    build = run(compose([f"inputs=[{','.join(map(str, paths))}]", f"out={out}"]))  # min_confidence: 0.3
    kept = [TauTrack(c.tau[4:], c.time[4:], c.fps, f"clip{i}") for i, c in enumerate(clips)]
    np.testing.assert_allclose(build.template.tau, build_template(kept).template.tau, atol=1e-6)
    with pytest.raises(InputError, match=r"track0\.csv: column 'tau', line 2: value is nan"):
        run(compose([f"inputs=[{','.join(map(str, paths))}]", f"out={out}", "min_confidence=null"]))

    # Playback into a tracker CSV: the rejected frames' held values do not reach the output, which is a
    # complete uniform track over the frames the tracker found.
    time = np.arange(120) / 30.0
    rest = tracker_csv(tmp_path / "rest.csv", np.full(120, 0.01), 30.0, lost_before=3, rejected=(50, 51, 90))
    played = tmp_path / "played.csv"
    run(compose(["mode=play", f"track={rest}", f"template={out}", "at=[2.0]", f"out={played}"]))
    result = read_tau_track(played)
    np.testing.assert_allclose(result.time, time[3:], atol=1e-6)
    assert result.tau.max() == pytest.approx(0.01 + build.template.peak_height, rel=0.05)
    np.testing.assert_allclose(result.tau[:20], 0.01, atol=1e-9)  # rest before the insert: nothing else changed


def test_tracker_csv_without_calibration_is_named(tmp_path):
    from motion.swallow import run

    clip = warped_swallow_clips(1, seed=32, fps_choices=(30.0,))[0]
    path = tracker_csv(tmp_path / "uncal.csv", clip.tau, clip.fps, px_per_tau=None)
    with pytest.raises(InputError, match=r"uncal\.csv: .*no calibration.*motion\.track.*px_per_tau=.*cm_per_px=.*kernel=rig"):
        run(compose([f"inputs=[{path}]", f"out={tmp_path / 't.csv'}"]))


def test_fps_key_gives_the_rate_of_frame_only_csvs(tmp_path):
    """fps= applies to .npy and to CSVs with frame,tau but no time or fps column."""
    from motion.swallow import run

    clips = warped_swallow_clips(3, seed=33, fps_choices=(30.0,))
    paths = []
    for i, c in enumerate(clips):
        write_csv(tmp_path / f"f{i}.csv", {"frame": np.arange(len(c.tau)), "tau": c.tau}, float_format="%.9g")
        paths.append(str(tmp_path / f"f{i}.csv"))
    out = tmp_path / "template.csv"
    with pytest.raises(InputError, match=r"f0\.csv: column 'frame' without a 'time' or 'fps' column; give fps=\.\.\."):
        run(compose([f"inputs=[{','.join(paths)}]", f"out={out}"]))
    build = run(compose([f"inputs=[{','.join(paths)}]", f"out={out}", "fps=30"]))
    np.testing.assert_allclose(build.template.tau, build_template(tracks_of(clips)).template.tau, atol=1e-6)


def test_read_template_rejects_files_that_are_not_templates(tmp_path):
    from motion.swallow import run

    clip = warped_swallow_clips(1, seed=34, fps_choices=(30.0,))[0]
    track = tmp_path / "track.csv"
    write_tau_track(track, TauTrack(clip.tau, clip.time, clip.fps))  # frame,time,tau,fps: a tau track
    expected = r"not a swallow template written by python -m motion\.swallow"
    with pytest.raises(InputError, match=rf"track\.csv: {expected}.*no column 'std'"):
        read_template(track)
    with pytest.raises(InputError, match=rf"track\.csv: {expected}"):
        run(compose(["mode=play", f"track={track}", f"template={track}", "at=[1.0]", f"out={tmp_path / 'o.csv'}"]))
    assert not (tmp_path / "o.csv").exists()
    for name, start in (("late.csv", 0.5), ("early.csv", -2.0)):  # the onset (time 0) not inside
        time = start + np.arange(60) / 60.0
        write_csv(tmp_path / name, {"time": time, "tau": np.zeros(60), "std": np.zeros(60)})
        with pytest.raises(InputError, match=rf"{name}: {expected}.*: column 'time' runs"):
            read_template(tmp_path / name)


def test_cli_takes_one_input_and_one_onset_without_brackets(tmp_path):
    from motion.swallow import run

    clip = warped_swallow_clips(1, seed=35, fps_choices=(30.0,))[0]
    write_tau_track(tmp_path / "one.csv", TauTrack(clip.tau, clip.time, clip.fps))
    out = tmp_path / "template.csv"
    build = run(compose([f"inputs={tmp_path / 'one.csv'}", f"out={out}"]))
    assert len(build.events) == 1 and len(build.clips) == 1 and build.clips[0].source.endswith("one.csv")
    np.testing.assert_allclose(build.template.tau, build_template(tracks_of([clip])).template.tau, atol=1e-6)

    rest = tmp_path / "rest.csv"
    write_tau_track(rest, TauTrack(np.full(90, 0.01), np.arange(90) / 30.0, 30.0))
    scalar = run(compose(["mode=play", f"track={rest}", f"template={out}", "at=1.0", "duration_scale=1.2",
                          f"out={tmp_path / 'a.csv'}"]))
    listed = run(compose(["mode=play", f"track={rest}", f"template={out}", "at=[1.0]", "duration_scale=[1.2]",
                          f"out={tmp_path / 'b.csv'}"]))
    np.testing.assert_array_equal(scalar.tau, listed.tau)
    assert scalar.tau.max() > 0.01 + 0.9 * build.template.peak_height  # the swallow is in
    at_zero = run(compose(["mode=play", f"track={rest}", f"template={out}", "at=0", f"out={tmp_path / 'c.csv'}"]))
    assert at_zero.tau.max() > 0.01 + 0.5 * build.template.peak_height  # at=0 is an onset, not "no onsets"


def test_shift_aligned_error_recovers_a_known_shift():
    time = np.arange(-0.5, 2.0, 1 / 60)
    reference = swallow_profile(time)
    rms, worst, shift = shift_aligned_error(time - 0.137, reference, time, reference, max_shift=0.5,
                                            resolution=0.001)
    assert shift == pytest.approx(0.137, abs=0.0015)
    assert rms < 0.01 * SWALLOW_AMPLITUDE and worst < 0.03 * SWALLOW_AMPLITUDE
