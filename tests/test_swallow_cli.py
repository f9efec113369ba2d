"""Swallow playback (motion/swallow/play.py), template files (files.py) and ``python -m motion.swallow`` (cli.py)."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from base.cli import compose_config, run_cli
from base.errors import InputError
from base.files import save_npy, write_csv
from base.tables import CsvTable
from data.synthetic_tau import (
    SWALLOW_AMPLITUDE,
    SWALLOW_DURATION,
    random_tau_trajectory,
    swallow_profile,
    warped_swallow_clips,
)
from data.tau_track import TauTrack, read_tau_track, write_tau_track
from motion.swallow import (
    PlaybackConfig,
    SwallowTemplate,
    build_template,
    insert_swallows,
    read_template,
    read_tracks,
    write_template,
)
from motion.swallow.cli import run

REPO = Path(__file__).resolve().parents[1]


def tracks_of(clips, prefix="clip"):
    return [TauTrack(c.tau, c.time, c.fps, f"{prefix}{i}") for i, c in enumerate(clips)]


def compose(overrides):
    return compose_config("swallow", overrides)


def known_template(fps=60.0) -> SwallowTemplate:
    time = np.arange(-0.3, SWALLOW_DURATION + 0.3, 1 / fps)
    return SwallowTemplate(time, swallow_profile(time), np.zeros(len(time)), fps)


# --------------------------------------------------------------------------- playback


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
    added = insert_swallows(batch, time, template, [1.0, 3.5], [1.0, 0.8], [1.0, 1.2], PlaybackConfig(blend="add"))
    expected = swallow_profile(time, 1.0) + 1.2 * swallow_profile(time, 3.5, 0.8 * SWALLOW_DURATION)
    # The template is sampled at 60 fps: interpolating it at 25 fps shaves at most a fraction of a percent.
    np.testing.assert_allclose(added - batch, np.broadcast_to(expected, batch.shape), atol=5e-3 * SWALLOW_AMPLITUDE)
    replaced = insert_swallows(batch, time, template, [1.0])
    np.testing.assert_allclose(replaced[1], insert_swallows(batch[1], time, template, [1.0]))
    with pytest.raises(ValueError, match="outside the track"):
        insert_swallows(batch, time, template, [20.0])
    with pytest.raises(ValueError, match="duration_scale has 3 values for 2 inserts"):
        insert_swallows(batch, time, template, [1.0, 3.5], [1.0, 1.0, 1.0])


def test_playback_config_is_validated():
    with pytest.raises(ValueError, match=r"PlaybackConfig\.fade_seconds must be positive, got -0\.1"):
        PlaybackConfig(fade_seconds=-0.1)
    with pytest.raises(ValueError, match=r"PlaybackConfig\.blend must be 'replace' or 'add', got 'mix'"):
        PlaybackConfig(blend="mix")


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


def test_cli_settings_sections_reach_the_tools(tmp_path):
    """detection.*, registration.* and playback.* change what the tool does (structured config sections)."""
    clips = warped_swallow_clips(4, seed=23, fps_choices=(30.0,))
    paths = write_clips(tmp_path, clips)[1:]
    out = tmp_path / "t.csv"
    at_60 = run(compose([f"inputs=[{','.join(paths)}]", f"out={out}"]))
    at_100 = run(compose([f"inputs=[{','.join(paths)}]", f"out={out}", "registration.template_fps=100"]))
    assert at_60.template.fps == 60.0 and at_100.template.fps == 100.0
    assert np.diff(at_100.template.time).mean() == pytest.approx(0.01, rel=1e-6)
    strict = run(compose([f"inputs=[{','.join(paths)}]", f"out={out}", "detection.crossing_levels=[0.5]"]))
    assert not any(n.startswith("rise") and n[4:].isdigit() and n != "rise50" for n in strict.template.landmark_names)
    track = tmp_path / "rest.csv"
    write_tau_track(track, TauTrack(np.full(120, 0.01), np.arange(120) / 30.0, 30.0))
    added = run(compose(["mode=play", f"track={track}", f"template={out}", "at=1.0", "playback.blend=add",
                         f"out={tmp_path / 'a.csv'}"]))
    np.testing.assert_allclose(added.tau - 0.01, insert_swallows(np.zeros(120), np.arange(120) / 30.0,
                                                                 read_template(out), [1.0],
                                                                 config=PlaybackConfig(blend="add")), atol=1e-8)


def test_cli_exit_status_2_and_one_line_naming_the_file(tmp_path):
    """Run as a command: success writes the template; bad input exits 2 with one line naming the file."""
    clips = warped_swallow_clips(3, seed=22)
    paths = write_clips(tmp_path, clips)[1:]
    out, plot = tmp_path / "t.csv", tmp_path / "t.png"
    done = subprocess.run([sys.executable, "-m", "motion.swallow", f"inputs=[{','.join(paths)}]", f"out={out}",
                           f"plot={plot}"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert CsvTable(out).header == ["time", "tau", "std"] and plot.stat().st_size > 20_000
    bad = tmp_path / "bad.csv"
    write_csv(bad, {"time": [0.0, 0.1], "height": [0.0, 0.1]})
    failed = subprocess.run([sys.executable, "-m", "motion.swallow", f"inputs=[{paths[0]},{bad}]",
                             f"out={tmp_path / 'bad_template.csv'}"], cwd=REPO, capture_output=True, text=True,
                            timeout=120)
    assert failed.returncode == 2
    lines = failed.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and f"{bad}: no column 'tau'" in lines[0], failed.stderr
    assert not (tmp_path / "bad_template.csv").exists()


def test_cli_shell_exit_status_2_on_bad_settings(tmp_path, capsys):
    """The same shell in-process (base.cli.run_cli): a bad setting or value exits 2 with one line naming it."""
    clips = warped_swallow_clips(1, seed=24, fps_choices=(30.0,))
    path = write_clips(tmp_path, [clips[0], clips[0]])[1]
    for overrides, expected in ((["playback.fade_seconds=0"], "PlaybackConfig.fade_seconds must be positive"),
                                (["detection.split_fraction=0.7"], "DetectionConfig.split_fraction must be in"),
                                (["registration.warp=cubic"], "RegistrationConfig.warp must be 'linear' or 'pchip'"),
                                (["detection.min_height=high"], "detection.min_height")):
        with pytest.raises(SystemExit) as exit_info:
            run_cli("swallow", run, [f"inputs=[{path}]", f"out={tmp_path / 't.csv'}", *overrides])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("error: ") and expected in err[0], err
    assert not (tmp_path / "t.csv").exists()


def test_bad_inputs_name_file_and_what_was_expected(tmp_path):
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
    with pytest.raises(InputError, match=r"detection\.typo.*Key 'typo' not in 'DetectionConfig'"):
        compose([f"inputs=[{bad_number}]", f"out={tmp_path / 'o.csv'}", "detection.typo=1"])
    with pytest.raises(InputError, match=r"min_height"):
        compose([f"inputs=[{bad_number}]", f"out={tmp_path / 'o.csv'}", "detection.min_height=abc"])
    with pytest.raises(InputError, match=r"playback \(configs/swallow\.yaml\): PlaybackConfig\.fade_seconds must be "
                                         r"positive, got 0"):
        run(compose(["mode=play", f"track={bad_number}", f"template={negative}", "at=1", f"out={tmp_path / 'o.csv'}",
                     "playback.fade_seconds=0"]))
    with pytest.raises(InputError, match=r"mode=mix: expected 'template' or 'play'"):
        run(compose(["mode=mix"]))


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
    clip = warped_swallow_clips(1, seed=32, fps_choices=(30.0,))[0]
    path = tracker_csv(tmp_path / "uncal.csv", clip.tau, clip.fps, px_per_tau=None)
    with pytest.raises(InputError, match=r"uncal\.csv: .*no calibration.*motion\.track.*px_per_tau=.*cm_per_px=.*"
                                         r"kernel=rig"):
        run(compose([f"inputs=[{path}]", f"out={tmp_path / 't.csv'}"]))


def test_fps_key_gives_the_rate_of_frame_only_csvs(tmp_path):
    """fps= applies to .npy and to CSVs with frame,tau but no time or fps column."""
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
        with pytest.raises(InputError, match=rf"{re.escape(name)}: {expected}.*: column 'time' runs"):
            read_template(tmp_path / name)


def test_cli_takes_one_input_and_one_onset_without_brackets(tmp_path):
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
