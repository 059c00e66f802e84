"""Observability: the rerun bridge (read back from .rrd), the run recording, the static report, `--viz save` end to end,
and (slow) a real headless rerun viewer screenshotted during a real run."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time

import pyarrow as pa
import pytest

import helpers
from ebrl.messages import EpisodeBatch, Event, Span, SpanBatch, StatsReport, encode_message
from ebrl import keys
from ebrl.viz import record, report, timeline

T0 = 1_800_000_000.0


def span(lane, start, end, label, service="sim"):
    return Span(lane=lane, start=T0 + start, end=T0 + end, label=label, service=service, instance=0)


def scripted_stream():
    """Two sim groups chunk/wait, gen forwards (two overlapping), train updates, weights publishes, stats, an event."""
    spans, stats = [], []
    for i in range(10):
        t = float(i)
        spans += [span("sim.g0", t, t + 0.5, "chunk"), span("sim.g0", t + 0.5, t + 1.0, "wait"),
                  span("sim.g1", t + 0.25, t + 0.75, "chunk"),
                  span("gen", t + 0.5, t + 0.6, "forward", "gen")]
        stats.append(StatsReport(run="r", service="sim", instance=0, time=T0 + t, seq=i,
                                 metrics={"sim/segments_per_s": 2.0, "sim/env_steps_per_s": 100.0 + i,
                                          "busy/sim.g0": 0.5, "cpu/core0_percent": 50.0, "other/x": 1.0}))
        stats.append(StatsReport(run="r", service="train", instance=0, time=T0 + t, seq=i,
                                 metrics={"train/policy_loss": 0.1, "train/policy_version": float(i)}))
    spans.append(span("gen", 3.55, 3.65, "forward", "gen"))  # overlaps the gen forward at 3.5-3.6
    spans += [span("train", 2.0, 4.0, "update", "train"), span("weights", 4.0, 4.01, "v1", "train"),
              span("train", 6.0, 7.0, "update", "train"), span("weights", 7.0, 7.01, "v2", "train")]
    events = [Event(time=T0 + 0.1, service="launcher", instance=0, kind="live", text="all live")]
    return spans, stats, events


# --- timeline arithmetic ------------------------------------------------------------------


def test_union_intersect_and_lane_order():
    merged = timeline.union([(3, 4), (0, 1), (0.5, 2), (5, 9)], lo=0.0, hi=6.0)
    assert merged == [(0, 2), (3, 4), (5, 6)] and timeline.total(merged) == 4
    assert timeline.intersect(merged, [(1, 3.5), (5.5, 7)]) == [(1, 2), (3, 3.5), (5.5, 6)]
    lanes = ["weights", "gen", "sim.g10", "custom", "train", "sim.g2", "alloc"]
    assert sorted(lanes, key=timeline.lane_order) == ["sim.g2", "sim.g10", "gen", "train", "weights", "alloc",
                                                       "custom"]
    assert timeline.state_of(span("weights", 0, 1, "v7", "train")) == "publish"
    assert not timeline.is_busy(span("sim.g0", 0, 1, "wait"))


# --- the rerun bridge ---------------------------------------------------------------------


def states_by_entity(path):
    """{entity: [(seconds from T0, state), ...]} of every StateChange in a saved .rrd."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        if "StateChange:state" not in batch.schema.names or chunk.is_static:
            continue
        times = batch.column("wall").cast(pa.int64()).to_pylist()
        states = [v[0] if v else None for v in batch.column("StateChange:state").to_pylist()]
        out.setdefault(str(chunk.entity_path), []).extend(
            (round(t / 1e9 - T0, 3), s) for t, s in zip(times, states))
    return {k: sorted(v) for k, v in out.items()}


def chunks_by_entity(path) -> dict[str, int]:
    from rerun.chunk import RrdReader

    out: dict[str, int] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        if not chunk.is_static:
            out[str(chunk.entity_path)] = out.get(str(chunk.entity_path), 0) + 1
    return out


def scalars_by_entity(path) -> dict[str, list]:
    """{entity: [(seconds from T0, [values]), ...]} of every Scalars row in a saved .rrd."""
    from rerun.chunk import RrdReader

    out: dict[str, list] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        batch = chunk.to_record_batch()
        if "Scalars:scalars" not in batch.schema.names or chunk.is_static:
            continue
        times = batch.column("wall").cast(pa.int64()).to_pylist()
        out.setdefault(str(chunk.entity_path), []).extend(
            (round(t / 1e9 - T0, 3), v) for t, v in zip(times, batch.column("Scalars:scalars").to_pylist()))
    return {k: sorted(v) for k, v in out.items()}


def bridge_to_file(path, every_s: float):
    import rerun as rr

    from ebrl.viz.rerun_bridge import FAMILIES, Outlet, RerunBridge, make_blueprint

    rec = rr.RecordingStream("ebrl", recording_id="test")
    rec.save(path, default_blueprint=make_blueprint(15.0))
    return rec, RerunBridge(Outlet(rec, dict.fromkeys(FAMILIES, every_s)))


def test_bridge_turns_spans_stats_and_events_into_entities(tmp_path):
    from ebrl.viz.rerun_bridge import describe_recording

    path = str(tmp_path / "t.rrd")
    rec, bridge = bridge_to_file(path, 0.0)  # every flush sends what it holds
    spans, stats, events = scripted_stream()
    g1 = [s for s in spans if s.lane == "sim.g1"]
    bridge.on_spans(SpanBatch(lane="sim.g1", service="sim", instance=0, start=[s.start for s in g1],
                              end=[s.end for s in g1], label=[s.label for s in g1]))  # as services publish them
    for i, s in enumerate(x for x in spans if x.lane != "sim.g1"):
        bridge.on_span(s)
        if i % 7 == 0:
            bridge.flush(T0)  # spans of one lane split across flushes
    for r in stats:
        bridge.on_stats(r)
    for e in events:
        bridge.on_event(e)
    bridge.flush(T0, force=True)
    rec.flush()
    rec.disconnect()

    entities = describe_recording(path)
    for lane in ("/timeline/1_sim/g00", "/timeline/1_sim/g01", "/timeline/2_gen", "/timeline/2_gen_1",
                 "/timeline/3_train", "/timeline/4_weights", "/plots/traj_per_s", "/plots/env_steps_per_s",
                 "/plots/busy", "/plots/cpu", "/plots/losses", "/plots/policy_version", "/metrics/sim0/other",
                 "/events"):
        assert lane in entities, (lane, sorted(entities))
    states = states_by_entity(path)
    assert states["/timeline/3_train"] == [(2.0, "update"), (4.0, ""), (6.0, "update"), (7.0, "")]
    assert states["/timeline/4_weights"] == [(4.0, "publish"), (4.01, ""), (7.0, "publish"), (7.01, "")]
    assert states["/timeline/2_gen_1"] == [(3.55, "forward"), (3.65, "")]  # the overlapping span got a sub-lane
    assert len(states["/timeline/2_gen"]) == 20
    # back-to-back chunk and wait spans: one row each, the lane's gap only after the last
    sim = states["/timeline/1_sim/g00"]
    assert sim[:3] == [(0.0, "chunk"), (0.5, "wait"), (1.0, "chunk")] and sim[-1] == (10.0, "") and len(sim) == 21
    assert len(states["/timeline/1_sim/g01"]) == 20
    # one series per service instance and metric, the series of one plot in one entity
    values = scalars_by_entity(path)
    assert values["/plots/policy_version"][:2] == [(0.0, [0.0]), (1.0, [1.0])]
    assert values["/plots/env_steps_per_s"][3] == (3.0, [103.0])
    assert values["/metrics/sim0/other"][0] == (0.0, [1.0])
    assert entities["/events"] >= 3  # the event and two weights publications


def test_bridge_sends_each_entity_in_columns_at_its_outlets_pace(tmp_path):
    """The file outlet sends what it holds once a minute: a 10 s stream, one chunk per entity; a span that
    follows the last one within GAP_S shares its row, a longer gap is drawn; a series that joins a plot later
    keeps the others' places and the others' latest values."""
    from ebrl.viz.rerun_bridge import FILE_EVERY_S, GAP_S, RerunBridge

    path = str(tmp_path / "t.rrd")
    rec, bridge = bridge_to_file(path, FILE_EVERY_S["plots"])
    spans, stats, events = scripted_stream()
    start = T0
    for s in spans:
        bridge.on_span(s)
        bridge.flush(start)
    for r in stats:
        bridge.on_stats(r)
        bridge.flush(start)
    bridge.on_span(span("train", 7.0 + GAP_S / 2, 8.0, "update", "train"))  # back to back with 6-7
    bridge.on_span(span("train", 8.0 + 2 * GAP_S, 8.5, "update", "train"))  # a gap of 2 GAP_S: drawn
    bridge.on_stats(StatsReport(run="r", service="gen", instance=0, time=T0 + 10.5, seq=1,
                                metrics={"gen/policy_version": 9.0}))  # joins train's series
    bridge.on_stats(StatsReport(run="r", service="train", instance=0, time=T0 + 11.0, seq=11,
                                metrics={"train/policy_version": 10.0}))
    bridge.flush(start + 59.0)  # nothing sent yet ...
    bridge.flush(start + 60.0)  # ... then everything, in one chunk per entity
    bridge.flush(start + 61.0, force=True)  # the run's end: what is left (the open lanes' ends)
    rec.flush()
    rec.disconnect()
    chunks = chunks_by_entity(path)
    assert chunks["/plots/env_steps_per_s"] == 1 and chunks["/plots/policy_version"] == 1, chunks
    # the first flush sends at once (the first span of sim.g0), then nothing until a minute later
    assert chunks["/timeline/1_sim/g00"] == 2 and chunks["/timeline/3_train"] == 1, chunks
    assert states_by_entity(path)["/timeline/3_train"] == [(2.0, "update"), (4.0, ""), (6.0, "update"),
                                                           (7.001, "update"), (8.0, ""), (8.004, "update"),
                                                           (8.5, "")]
    versions = scalars_by_entity(path)["/plots/policy_version"]
    assert versions[-2:] == [(10.5, [9.0, 9.0]), (11.0, [10.0, 9.0])], versions[-3:]
    assert isinstance(bridge, RerunBridge)


# --- recording and report ---------------------------------------------------------------------


def write_recording(path, spans, stats, events, garbage=True):
    rec = record.Recorder(path)
    for s in spans:  # one span per batch here; services batch per lane (test_service)
        rec.write(keys.spans("r", s.lane), encode_message(SpanBatch(lane=s.lane, service=s.service, instance=s.instance,
                                                                    start=[s.start], end=[s.end], label=[s.label])))
    for r in stats:
        rec.write(keys.stats("r", r.service, r.instance), encode_message(r))
    for e in events:
        rec.write(keys.events("r", e.service), encode_message(e))
    if garbage:
        rec.write(keys.spans("r", "gen"), b"\xc1not msgpack")
        rec.write(keys.stats("r", "sim", 0), encode_message(events[0]))  # an event on a stats key: wrong type
    rec.close()


def test_recording_round_trip_counts_malformed_and_survives_a_cut_file(tmp_path):
    spans, stats, events = scripted_stream()
    path = tmp_path / record.FILENAME
    write_recording(path, spans, stats, events)
    with open(path, "ab") as fh:
        fh.write(b"\x93\xcb")  # a record cut short by a crash
    got = record.read(tmp_path)
    assert len(got.spans) == len(spans) and len(got.stats) == len(stats) and got.events == events
    assert got.malformed == 2
    assert got.lanes == ["sim.g0", "sim.g1", "gen", "train", "weights"]
    assert [s.start for s in got.spans] == sorted(s.start for s in spans)


def test_report_numbers_and_files(tmp_path):
    spans, stats, events = scripted_stream()
    write_recording(tmp_path / record.FILENAME, spans, stats, events, garbage=False)
    rec = record.read(tmp_path)
    lo, hi = T0, T0 + 10.0
    rows = {r["lane"]: r for r in report.lane_table(rec, lo, hi)}
    assert rows["sim.g0"]["busy"] == pytest.approx(0.5) and rows["sim.g0"]["waiting"] == pytest.approx(0.5)
    assert rows["sim.g0"]["idle"] == pytest.approx(0.0, abs=1e-9)
    assert rows["train"]["busy"] == pytest.approx(0.3) and rows["train"]["spans"] == 2
    ov = report.overlap(rec, lo, hi)
    # train 2-4 and 6-7; sim busy [t, t+0.75] each second -> 0.75 s per second of training
    assert ov["train_busy_s"] == pytest.approx(3.0) and ov["both_s"] == pytest.approx(2.25)
    assert ov["of_training"] == pytest.approx(0.75)
    assert report.window_of(rec, None, None, 2.0) == pytest.approx((T0 + 8.01, T0 + 10.01))
    with pytest.raises(ValueError, match="empty window"):
        report.window_of(rec, 5.0, 4.0, None)

    paths = report.write(tmp_path, start=0.0, end=10.0)
    for key in ("gantt", "gantt_zoom", "throughput", "markdown"):
        assert paths[key].exists() and paths[key].stat().st_size > 1000, key
    text = paths["markdown"].read_text()
    assert "| sim.g0 | 20 | 50.0% | 50.0% | 0.0% |" in text
    assert "75% of training ran while rollout went on" in text and "launcher/0 live: all live" in text


def learning_recording(path, with_eval: bool) -> None:
    """A recording of a short run: sim reports (env steps, windowed return and success), one EpisodeBatch per
    second, training losses, and (``with_eval``) two eval results with their intervals."""
    rec = record.Recorder(path)
    for i in range(10):
        t = T0 + i
        sim = StatsReport(run="r", service="sim", instance=0, time=t, seq=i, metrics={
            "sim/env_steps": 500.0 * (i + 1), "sim/episode_return_mean": 10.0 * i, "sim/success_rate": i / 10})
        train = StatsReport(run="r", service="train", instance=0, time=t, seq=i, metrics={
            "train/policy_version": float(i), "train/policy_loss": -0.01 * i, "train/value_loss": 5.0 / (i + 1),
            "train/approx_kl": 0.001 * i})
        batch = EpisodeBatch(service="sim", instance=0, env_id=[0, 1], episode=[i, i], returns=[10.0 * i, 10.0 * i + 5],
                             length=[50, 60], success=[i > 4, False], policy_version=[i, i],
                             env_steps=[500 * i + 100, 500 * i + 400], end_time=[t - 0.5, t - 0.1])
        rec.write(keys.stats("r", "sim", 0), encode_message(sim))
        rec.write(keys.stats("r", "train", 0), encode_message(train))
        rec.write(keys.episodes("r", "sim"), encode_message(batch))
    for version, success in ((3, 0.2), (8, 0.9)) if with_eval else ():
        rec.write(keys.stats("r", "eval", 0), encode_message(StatsReport(
            run="r", service="eval", instance=0, time=T0 + version + 0.5, seq=version, metrics={
                "eval/version": float(version), "eval/return": 100.0 * success, "eval/success_rate": success,
                "eval/success_rate_lo": success - 0.15, "eval/success_rate_hi": min(1.0, success + 0.1),
                "eval/episode_length": 77.0})))
    rec.close()


def red_pixels(png) -> int:
    """Pixels in the colour of the eval curves (tab:red, and its interval band blended over white)."""
    import matplotlib.image

    img = (matplotlib.image.imread(png)[..., :3] * 255).astype(int)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return int(((r > 200) & (g < 215) & (b < 215) & (r - g > 30) & (abs(g - b) < 25)).sum())


@pytest.mark.parametrize("with_eval", [True, False])
def test_learning_curves_from_a_recording(tmp_path, with_eval):
    learning_recording(tmp_path / record.FILENAME, with_eval)
    rec = record.read(tmp_path)
    assert len(rec.episodes) == 10 and rec.malformed == 0
    series = report.learning_curves(rec)
    # every episode at the run's env steps when it ended, each eval at the steps its version was published
    assert [(p.step, p.value) for p in series["episode/return"][:4]] == [(100, 0.0), (400, 5.0), (600, 10.0), (900, 15.0)]
    assert [p.value for p in series["episode/success"]][9:12] == [0.0, 1.0, 0.0]  # env 0 succeeds from i = 5
    if with_eval:
        assert [(p.step, p.value) for p in series["eval/success_rate"]] == [(2000, 0.2), (4500, 0.9)]
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "report", str(tmp_path)], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    png = tmp_path / "report" / "learning.png"
    assert str(png) in proc.stdout.split() and png.stat().st_size > 20_000
    import matplotlib.image

    height, width = matplotlib.image.imread(png).shape[:2]
    assert width > 1000 and height > 1000  # two columns (env steps, wall-clock), four panels each
    if with_eval:
        assert red_pixels(png) > 2000  # the eval success with its interval band, and the eval return
    else:
        assert red_pixels(png) < 50
    text = (tmp_path / "report" / "report.md").read_text()
    assert "![learning curves](learning.png)" in text and "20 episodes recorded over 4,900 env steps" in text
    if with_eval:
        assert "| 8 | 4,500 | 0.9 | 0.75 - 1 | 90 | 77 |" in text


def test_report_command_errors_clearly(tmp_path):
    out = subprocess.run([sys.executable, "-m", "ebrl.cli", "report", str(tmp_path)], capture_output=True, text=True)
    assert out.returncode == 2 and "stats.msgpack not found" in out.stderr


def hue_pixels(png) -> dict[str, int]:
    """Pixels of each bar colour family in a screenshot (rendered colours are dimmed and blended with the
    dark background where spans are thin, so match by dominant channel, not by exact value)."""
    import matplotlib.image

    img = (matplotlib.image.imread(png)[..., :3] * 255).astype(int)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return {"chunk": int(((b > 60) & (b > 1.15 * r) & (b > 1.1 * g)).sum()),  # blue
            "forward": int(((r > 25) & (r > 1.3 * g) & (g > 1.5 * b)).sum()),  # orange
            "update": int(((g > 60) & (g > 1.3 * r) & (g > 1.3 * b)).sum())}  # green


# --- end to end ----------------------------------------------------------------------------------

TWO_GROUPS = ("sim.groups=2", "sim.envs_per_group=4")


@pytest.mark.slow
def test_up_with_viz_save_writes_timeline_and_report(tmp_path):
    # Two groups of 4 (the quickstart runs one group of 8), so the record has a lane per group.
    with helpers.up(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=3", 'viz.rerun="save"',
                    *TWO_GROUPS, name="vizsave") as run:
        code = run.wait(300)
    out = run.output
    assert code == 0, out
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert (run_dir / "timeline.rrd").exists(), out
    from ebrl.viz.rerun_bridge import describe_recording

    entities = describe_recording(str(run_dir / "timeline.rrd"))
    for lane in ("/timeline/1_sim/g00", "/timeline/1_sim/g01", "/timeline/2_gen", "/timeline/3_train",
                 "/timeline/4_weights", "/plots/traj_per_s", "/events"):
        assert entities.get(lane, 0) > 2, (lane, sorted(entities))
    rec = record.read(run_dir)
    assert rec.lanes[:5] == ["sim.g0", "sim.g1", "gen", "train", "weights"] and rec.malformed == 0
    assert {e.kind for e in rec.events} >= {"live", "viz", "stopping"}
    assert {r.service for r in rec.stats} >= {"sim", "gen", "train", "viz"}
    md = (run_dir / "report" / "report.md").read_text()
    for lane in ("sim.g0", "sim.g1", "gen", "train", "weights"):
        assert f"| {lane} |" in md
    assert "report:" in out and (run_dir / "report" / "gantt.png").exists()


# --- slow: a real headless viewer -------------------------------------------------------------------


@pytest.fixture
def viewer(tmp_path, monkeypatch):
    icd = "/usr/share/vulkan/icd.d"
    if not (os.path.isdir(icd) and os.listdir(icd)):
        pytest.skip("no Vulkan driver: install mesa-vulkan-drivers and libvulkan1 (.ci/run does)")
    from rerun.experimental import ViewerClient

    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path))
    monkeypatch.setenv("RUST_LOG", "error")
    exe = os.path.join(os.path.dirname(sys.executable), "rerun")
    client = ViewerClient.spawn(headless=True, port=helpers.free_port(), hide_welcome_screen=True,
                                executable_path=exe if os.path.exists(exe) else None)
    try:
        client.get_state()
    except ConnectionError as exc:
        client.quit()
        pytest.skip(f"headless rerun viewer unusable here: {exc}")
    yield client
    client.quit()


ITERATIONS_SHOWN = 12


@pytest.mark.slow
def test_live_gantt_in_a_headless_viewer_shows_every_lane(tmp_path, viewer):
    port = int(viewer.url.rsplit(":", 1)[1].split("/")[0])
    # Two groups of 4: twice the forward passes of one group of 8, enough gen bars for the pixel count below.
    with helpers.up(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=0", f"viz.port={port}",
                    'viz.rerun="spawn"', *TWO_GROUPS, name="vizlive") as run:
        # Wait on progress, not on time: a loaded machine's first seconds hold few updates (CI's once drew 220
        # green pixels at 8 s), so the screenshot waits until training has made ITERATIONS_SHOWN updates.
        run.wait_for_line(lambda line: (m := re.match(r"iter (\d+)", line)) is not None
                          and int(m.group(1)) >= ITERATIONS_SHOWN, 300, f"iteration {ITERATIONS_SHOWN}")
        deadline = time.monotonic() + 300
        view = None
        while time.monotonic() < deadline:  # wait for the run's spans to reach the viewer
            state = viewer.get_state()
            view = next((v for v in state.views if v.view_class == "StateTimeline"), None)
            wall = [t for r in state.recordings for t in r.timelines if t.name == "wall" and t.end]
            if view is not None and wall and wall[0].end - wall[0].start > 8e9:
                break
            time.sleep(0.5)
        assert view is not None, "no StateTimeline view in the live viewer"
        time.sleep(1.0)
        png = tmp_path / "gantt.png"
        png.write_bytes(viewer.take_screenshot(view.view_id))
        (tmp_path / "viewer.png").write_bytes(viewer.take_screenshot())  # the whole layout, for a human look
        lags = []  # how far behind the run the newest data the viewer holds is, read 10 times a second apart
        for _ in range(10):
            ends = [t.end for r in viewer.get_state().recordings for t in r.timelines if t.end]
            lags.append(time.time() - max(ends) / 1e9)
            time.sleep(1.0)
        code = run.stop(60)
    assert sorted(lags)[len(lags) // 2] < 2.0, f"the live viewer is behind the run: {[round(x, 2) for x in lags]} s"
    assert "streaming to the viewer already listening" in (run.run_dir / "logs" / "viz-0.log").read_text()
    # Every stage's bars are on screen: sim chunks (blue), gen forwards (orange), train updates (green).
    pixels = hue_pixels(png)
    for state, count in pixels.items():
        assert count > 300, f"no {state} bars in the live Gantt ({png}): {pixels}"
    assert code in (0, 130), run.output


@pytest.mark.slow
def test_serve_lets_a_viewer_that_connects_late_see_the_whole_run(tmp_path, viewer):
    port = helpers.free_port()
    with helpers.up(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=0", f"viz.port={port}",
                    'viz.rerun="serve"', name="vizserve") as run:
        run.wait_for_line("all services live", 300)
        started = time.time()  # the run's spans begin about now (however long a loaded machine took to start)
        time.sleep(20)  # the run goes on with nobody watching
        run.check_running("a late viewer")
        viewer.open(f"rerun+http://127.0.0.1:{port}/proxy")
        deadline, span = time.monotonic() + 300, None
        while time.monotonic() < deadline:
            state = viewer.get_state()
            wall = [t for r in state.recordings for t in r.timelines if t.name == "wall" and t.end]
            if wall:
                span = (wall[0].start / 1e9 - started, wall[0].end / 1e9 - started)
                if span[1] > 20:
                    break
            time.sleep(0.5)
        code = run.stop(60)
    assert span is not None, "the late viewer got no data"
    assert span[0] < 15 and span[1] > 20, f"the late viewer sees {span[0]:.1f}-{span[1]:.1f} s of the run"
    assert code == 130, run.output


def test_spawn_without_a_display_falls_back_to_saving(tmp_path, monkeypatch):
    from ebrl.viz.rerun_bridge import make_blueprint, open_recording

    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    outlets, where = open_recording("spawn", str(tmp_path / "t.rrd"), "nodisplay", helpers.free_port(), "64MiB",
                                    make_blueprint())
    assert len(outlets) == 1  # the file's alone
    outlets[0].rec.disconnect()
    assert where.startswith("no display") and (tmp_path / "t.rrd").exists()
