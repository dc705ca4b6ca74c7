"""`jitterguard eval --mcap`: every evaluated frame recorded for Foxglove through the bridge's own sink, read back
with the ``mcap`` reader and Google's protobuf runtime (not jitterguard's code) and checked against the run's
metrics.json and the scenario's ground truth."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from jitterguard.services.foxglove.scene import DETECTIONS, GROUNDTRUTH, MOTION, TF, TRACKS
from jitterguard.sim import make_scenario

from .test_foxglove_run import _meta, _read_mcap


def test_eval_records_each_run_to_mcap_and_the_recording_matches_the_scores(tmp_path: Path) -> None:
    out = tmp_path / "ev"
    out.mkdir()
    (out / "run-2000.mcap").write_bytes(b"an earlier run's frames")  # would sit beside metrics it does not match
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "eval", "--scenario", "parking-street",
                          "--seed", "3", "--runs", "2", "--duration", "3", "--out", str(out), "--mcap", "--json"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    metrics = json.loads(res.stdout)
    assert sorted(p.name for p in out.glob("*.mcap")) == ["run-3.mcap", "run-4.mcap"]  # one per run: clocks restart
    decided_rows = 0
    for seed in (3, 4):
        schemas, msgs = _read_mcap(out / f"run-{seed}.mcap")
        assert {TF, DETECTIONS, TRACKS, GROUNDTRUTH, MOTION} <= set(schemas)
        scenario = make_scenario("parking-street", seed, 3.0, 10.0)
        truth = {t: len(m.get("entities", [])) for t, m in msgs[GROUNDTRUTH]}
        assert len(truth) >= 25  # every frame the tracker and classifier decided, not a frame or two
        assert sorted(truth.values()) == sorted(scenario.frame(i).num_objects for i in range(len(scenario))
                                                 if scenario.frame(i).stamp_ns in truth)
        for t, m in msgs[MOTION]:
            rows = m["tracks"]
            decided_rows += sum(1 for r in rows if r.get("decided_seq") == m["seq"])
            assert sum(m["counts"].values()) == len(rows)
        # the tracks scene states what the motion message says, track by track
        for (t1, scene), (t2, m) in zip(msgs[TRACKS], msgs[MOTION]):
            assert t1 == t2
            states = {e["id"]: _meta(e)["state"] for e in scene.get("entities", [])}
            assert states == {r["id"]: r["state"] for r in m["tracks"]}
    # the recording holds exactly the rows the evaluator scored: one decision per observed track and frame
    assert decided_rows == metrics["run"]["rows"] > 0


def test_render_mcap_reads_a_recording_whose_writer_was_killed(tmp_path: Path) -> None:
    """A writer killed mid-run leaves no summary or footer: the seeking reader refuses the file, and `render-mcap`
    said so; it now reads it from the start as far as its records are whole (the frames before the kill)."""
    from jitterguard.services.foxglove.render import read_frames

    out = tmp_path / "ev"
    out.mkdir()
    (out / "run-2000.mcap").write_bytes(b"an earlier run's frames")  # would sit beside metrics it does not match
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "eval", "--scenario", "parking-street", "--seed", "3",
                          "--duration", "3", "--out", str(out), "--mcap"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    whole = out / "run-3.mcap"
    data = whole.read_bytes()
    cut = tmp_path / "killed.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])  # no summary, footer or closing magic; a record cut in two
    from mcap.reader import make_reader

    with cut.open("rb") as f:
        try:
            list(make_reader(f).iter_messages())
            seeking_reads_it = True
        except Exception:
            seeking_reads_it = False
    assert not seeking_reads_it  # what the fallback is for
    got, full = read_frames(cut), read_frames(whole)
    assert 0 < len(got) < len(full)
    assert [f.log_time for f in got] == [f.log_time for f in full[: len(got)]]  # the same frames, from the start
    png = tmp_path / "k.png"
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "render-mcap", str(cut), "--out", str(png)],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and png.stat().st_size > 0, res.stderr


def test_render_mcap_of_a_ros2_bag_is_one_line_not_a_traceback(tmp_path: Path) -> None:
    """A ROS 2 bag's MCAP (what `jitterguard record --ros2` writes) has a /tf channel too, in ros2msg: render-mcap
    parsed its schema as protobuf and died with a DecodeError traceback (exit 1)."""
    import pytest

    pytest.importorskip("rosbags")
    from replay.bagfixture import write_bag

    bag = write_bag(tmp_path / "run bag", storage="mcap", n=2, with_tf=True)
    [mcap] = list(bag.path.glob("*.mcap"))
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "render-mcap", str(mcap), "--out",
                          str(tmp_path / "x.png")], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr[-2000:]
    assert "Traceback" not in res.stderr and res.stderr.count("jitterguard: error:") == 1, res.stderr
    assert f"no {TRACKS} messages" in res.stderr
    assert not (tmp_path / "x.png").exists()


def test_render_mcap_of_a_folder_says_it_is_a_folder(tmp_path: Path) -> None:
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "render-mcap", str(tmp_path), "--out",
                          str(tmp_path / "x.png")], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and res.stderr.strip().endswith("a folder, not an MCAP file"), res.stderr


def test_an_interrupted_eval_leaves_no_recording_beside_an_earlier_runs_metrics(tmp_path: Path) -> None:
    """Ctrl-C in the middle of `eval --mcap` closed the recording into a whole, valid MCAP of the frames run so far
    (a footer, a summary whose counts matched): it sat as run-SEED.mcap beside the metrics.json and report.md of the
    earlier run in that folder, and looked like their frames. A run's recording is named only once its metrics are
    written; an interrupted run leaves none."""
    import signal
    import time

    out = tmp_path / "ev"
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "eval", "--scenario", "parking-street", "--seed", "3",
                          "--duration", "2", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    earlier = (out / "metrics.json").read_text()
    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "eval", "--scenario", "parking-street", "--seed",
                             "3", "--duration", "600", "--out", str(out), "--mcap"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            # Ctrl-C as at a terminal (a background job's shell hands its children SIGINT ignored)
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))

    def frames_written() -> bool:  # under whichever name the recording is being written
        return any(p.stat().st_size > 200_000 for p in out.glob("run-3.mcap*"))

    deadline = time.monotonic() + 240
    while not frames_written():
        assert proc.poll() is None and time.monotonic() < deadline, "the run wrote no frames"
        time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=120)
    assert proc.returncode != 0  # interrupted, not finished
    assert (out / "metrics.json").read_text() == earlier
    assert sorted(p.name for p in out.iterdir() if "mcap" in p.name) == []


def test_a_run_too_short_to_decide_anything_records_its_channels_and_says_nothing_was_decided(tmp_path: Path
                                                                                             ) -> None:
    """Two frames are too few for any track to be confirmed and decided: the recording had no channel and no
    schema at all (Foxglove opened an empty file, its layout's panels bound to nothing), and report.md and
    metrics.json read like any run's. The file now holds the channels every frame has, with their schemas, read back
    by the independent ``mcap`` reader; metrics.json and report.md say that no decision was made."""
    from mcap.reader import make_reader

    out = tmp_path / "ev"
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "eval", "--scenario", "parking-street", "--seed", "3",
                          "--duration", "0.2", "--out", str(out), "--mcap", "--json"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    metrics = json.loads(res.stdout)
    assert metrics["run"]["rows"] == 0
    assert metrics["run"]["no_decision"] and "no track was decided" in metrics["run"]["no_decision"]
    assert "No decision was made" in (out / "report.md").read_text()
    with open(out / "run-3.mcap", "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    topics = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
    assert {TF, TRACKS, MOTION} <= set(topics), topics
    assert topics[TRACKS].name == "foxglove.SceneUpdate" and topics[TRACKS].encoding == "protobuf"
    assert topics[MOTION].encoding == "jsonschema" and topics[TF].name == "foxglove.FrameTransforms"
    assert summary.statistics.message_count == 0  # channels to bind to, no made-up frames


def test_a_run_whose_rows_are_all_undecided_says_nothing_was_decided_and_reports_no_latency(tmp_path: Path) -> None:
    """Three frames: tracks confirmed and observed, none for min_window frames, so every row is undecided. The run
    had not said it decided nothing (``no_decision`` null: rows existed), and every group read "never correct" by
    the z-test (1.0) and 0 s by the speed rule, from rows no rate scores."""
    out = tmp_path / "ev"
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "eval", "--duration", "0.3", "--out", str(out),
                          "--json"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    metrics = json.loads(res.stdout)
    assert metrics["run"]["rows"] > 0  # the case: rows, none of them decided
    assert "no track was decided" in (metrics["run"]["no_decision"] or "")
    assert "No decision was made" in (out / "report.md").read_text()
    for group in ("vehicle", "pedestrian"):
        m = metrics["motion"][group]
        assert m["never_correct_fraction_z"] is None and m["time_to_first_correct_s_median_speed"] is None, m


def _fsize_capped(limit: int):
    """A child whose files cannot grow past ``limit`` bytes (RLIMIT_FSIZE; Python ignores SIGXFSZ, so a write past
    it fails with EFBIG): a disk that fills while a picture is written."""
    import resource

    return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))


def test_a_picture_that_fails_mid_write_leaves_the_earlier_one_whole(tmp_path: Path) -> None:
    """`render-mcap` and `sim bev` saved onto their --out itself: a write that failed part way (a full disk, a
    Ctrl-C) had left a truncated PNG where the earlier good one was, and render-mcap a traceback."""
    out = tmp_path / "ev"
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "eval", "--scenario", "parking-street", "--seed", "3",
                          "--duration", "3", "--out", str(out), "--mcap"], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-2000:]
    for args in (["render-mcap", str(out / "run-3.mcap")], ["sim", "bev", "mixed", "--seed", "1", "--frame", "5"]):
        png = tmp_path / "pictures ü" / "frame.png"
        png.parent.mkdir(exist_ok=True)
        ok = subprocess.run([sys.executable, "-m", "jitterguard.cli", *args, "--out", str(png)], capture_output=True,
                            text=True, timeout=300)
        assert ok.returncode == 0, ok.stderr[-2000:]
        earlier = png.read_bytes()
        assert earlier.startswith(b"\x89PNG") and len(earlier) > 40_000
        res = subprocess.run([sys.executable, "-m", "jitterguard.cli", *args, "--out", str(png)], capture_output=True,
                             text=True, timeout=300, preexec_fn=_fsize_capped(20_000))
        assert res.returncode == 2 and res.stderr.strip() == f"jitterguard: error: --out: cannot write {png}: File too"\
            " large", res.stderr[-2000:]
        assert png.read_bytes() == earlier
        assert sorted(p.name for p in png.parent.iterdir()) == ["frame.png"]  # no temporary file left either
