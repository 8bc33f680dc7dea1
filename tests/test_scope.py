"""The live scope (gateway/scope/): the feed (decimation, order of events, drops counted,
late joiners), the server, `log --scope`, `scope RUN_DIR`, and a `sim --scope` run watched
in a real browser (headless Chromium from Debian's packages, driven by Playwright)."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import can
import pytest

from gateway.buslog import LogOptions, run_log
from gateway.errors import UserError
from gateway.report import Record
from gateway.scope import ScopeFeed, ScopeServer, parse_address
from gateway.scope.feed import CLIENT_QUEUE, LatestValues

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = "/usr/bin/chromium"


def _record(n: int, dt: float = 1e-3) -> Record:
    from typing import NamedTuple

    class Row(NamedTuple):
        t: float
        w_m: float

    rec = Record(Row)
    for k in range(n):
        rec.append(Row(k * dt, math.nan if k == 3 else float(k)))
    return rec


def _events(client) -> list[tuple[str, dict]]:
    out = []
    while not client.queue.empty():
        event, data = client.queue.get_nowait()
        out.append((event, json.loads(data)))
    return out


def test_the_feed_decimates_to_the_display_rate_and_sends_nan_as_null():
    feed = ScopeFeed("t", display_rate=250.0)  # 1 kHz rows: every 4th
    rec = _record(0)
    feed.attach(rec)
    client = feed.subscribe()
    for k in range(20):
        rec.append(rec.row_type(k * 1e-3, math.nan if k == 4 else float(k)))
    stats = feed.stats()  # stops the thread after a last read
    events = _events(client)
    assert [e for e, _ in events][:2] == ["meta", "state"]
    rows = [d for e, d in events if e == "rows"]
    t = [x for d in rows for x in d["columns"]["t"]]
    w = [x for d in rows for x in d["columns"]["w_m"]]
    assert t == pytest.approx([k * 1e-3 for k in range(0, 20, 4)])
    assert w == [0.0, None, 8.0, 12.0, 16.0]
    assert stats == {"sent_rows": 5, "dropped_rows": 0, "decimation": 4, "clients": 1}


def test_a_late_client_gets_meta_history_and_state_first():
    feed = ScopeFeed("t", display_rate=1000.0)
    feed.load({"t": [0.0, 0.001, 0.002], "w_m": [1.0, 2.0, 3.0]})
    events = _events(feed.subscribe())
    assert [e for e, _ in events] == ["meta", "rows", "state"]
    assert events[0][1]["columns"] == ["t", "w_m"]
    assert events[1][1]["columns"]["w_m"] == [1.0, 2.0, 3.0]
    assert events[2][1]["running"] is False


def test_a_slow_client_loses_the_oldest_batches_and_they_are_counted():
    feed = ScopeFeed("t", display_rate=1000.0)
    rec = _record(2)
    feed._start(tuple(rec.columns), rec._rows)
    client = feed.subscribe()  # never reads
    for k in range(2, 2 + 3 * CLIENT_QUEUE):
        rec.append(rec.row_type(k * 1e-3, float(k)))
        feed._take()
    stats = feed.stats()
    assert client.queue.qsize() == CLIENT_QUEUE
    sent = stats["sent_rows"]
    assert stats["dropped_rows"] > 0
    assert stats["dropped_rows"] + CLIENT_QUEUE - 2 <= sent  # meta and state were queued too


def test_latest_values_make_rows_at_most_once_a_period():
    rows = LatestValues(["i_sa", "w_m"], period=0.01)
    rows.update(100.0, {"i_sa": 1.0})
    rows.update(100.004, {"w_m": 5.0})  # within the period: no row, value kept
    rows.update(100.012, {"i_sa": 2.0})
    assert rows.columns == ("t", "i_sa", "w_m")
    assert rows._rows[0][:2] == (0.0, 1.0) and math.isnan(rows._rows[0][2])
    assert rows._rows[1] == pytest.approx((0.012, 2.0, 5.0))


def test_log_feeds_decoded_frames_to_the_scope(tmp_path):
    from dbc import load_codec

    codec = load_codec(1)
    channel = f"scope-log-{time.monotonic_ns()}"
    rx, tx = (can.Bus(interface="virtual", channel=channel) for _ in range(2))
    rows = LatestValues(["i_sa", "i_sb"], period=0.0)
    stop = threading.Event()

    def send():
        for k in range(20):
            data = codec.encode("TPDO1", {"statusword": 0x37, "i_sa": 0.1 * k, "i_sb": -1.0,
                                          "sync_counter": k})
            tx.send(can.Message(arbitration_id=codec.frame_id("TPDO1"), data=data,
                                is_extended_id=False))
            time.sleep(0.002)
        time.sleep(0.1)
        stop.set()

    sender = threading.Thread(target=send)
    sender.start()
    try:
        run_log(rx, tmp_path / "bus.blf", LogOptions(sampler=rows), stop=stop, quiet=True)
    finally:
        sender.join()
        rx.shutdown()
        tx.shutdown()
    assert len(rows._rows) == 20
    assert rows._rows[-1][1:] == pytest.approx((1.9, -1.0))


def test_the_server_serves_the_page_and_its_assets_and_refuses_others():
    feed = ScopeFeed("t")
    server = ScopeServer(feed, "127.0.0.1", 0)
    try:
        page = urllib.request.urlopen(server.url, timeout=5).read().decode()
        assert 'src="scope.js"' in page and "http" not in page.replace(
            "http-equiv", "")  # no asset from elsewhere
        js = urllib.request.urlopen(server.url + "scope.js", timeout=5).read().decode()
        assert "EventSource" in js and "https://" not in js
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(server.url + "nothing", timeout=5)
        assert e.value.code == 404
    finally:
        server.close()


@pytest.mark.parametrize("text, words", [("x", "give [HOST:]PORT"), ("70000", "0..65535"),
                                          ("localhost:abc", "give [HOST:]PORT")])
def test_bad_scope_addresses_are_named(text, words):
    with pytest.raises(UserError, match=re.escape(words)):
        parse_address(text)
    assert parse_address("8765") == ("127.0.0.1", 8765)


def test_scope_of_a_missing_run_is_named(tmp_path, capsys):
    from gateway.cli import main

    assert main(["scope", str(tmp_path), "--hold", "0.1"]) == 2
    assert "not a run directory" in capsys.readouterr().err


# ---------------------------------------------------------------------- in a real browser


def _browser_problem() -> str | None:
    try:
        import playwright  # noqa: F401
    except ImportError:
        return "Playwright for Python is not installed (pip install playwright)"
    if not Path(CHROMIUM).exists():
        return f"no {CHROMIUM} (apt-get install chromium)"
    return None


@pytest.fixture
def browser():
    problem = _browser_problem()
    if problem is not None:
        if os.environ.get("CI", "").lower() in ("true", "1"):
            pytest.fail(f"CI=true and no browser for the scope test: {problem}; "
                        "scripts/bootstrap --test installs both", pytrace=False)
        pytest.skip(problem)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, headless=True,
                              args=["--no-sandbox", "--disable-gpu"])
        try:
            yield b
        finally:
            b.close()


def _start_sim(out: Path) -> tuple[subprocess.Popen, str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "gateway", "sim", "--scope", "127.0.0.1:0", "--duration",
         "300s", "--allow-long", "--out", str(out)], cwd=ROOT, env=env,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    deadline = time.monotonic() + 60
    for line in proc.stderr:
        m = re.search(r"scope: (http://127\.0\.0\.1:\d+/)", line)
        if m:
            return proc, m.group(1)
        assert time.monotonic() < deadline, "no scope address printed"
    raise AssertionError(f"sim ended before serving the scope: {proc.wait()}")


def test_a_sim_run_is_watched_in_a_browser(browser, tmp_path):
    """The done-when: traces appear and move while `sim --scope` runs; a screenshot is
    saved; Ctrl-C ends the run with its files and the scope's account."""
    out = tmp_path / "run"
    proc, url = _start_sim(out)
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(url)
        page.wait_for_function("window.scope.samples > 50 && window.scope.running",
                               timeout=60_000)
        page.wait_for_function("(window.scope.traces.w_m || 0) > 10", timeout=30_000)
        first = page.evaluate("[window.scope.lastT, window.scope.samples]")
        page.wait_for_function(f"window.scope.lastT > {first[0]} + 0.05", timeout=60_000)
        second = page.evaluate("[window.scope.lastT, window.scope.samples]")
        assert second[1] > first[1]
        assert page.locator("canvas[data-panel=speed]").count() == 1
        assert "running" in page.locator("#status").inner_text()
        # the signal choice adds a panel's trace; the trigger pauses at a crossing
        page.locator("input[data-signal=i_sd_ref]").check()
        page.wait_for_function("(window.scope.traces.i_sd_ref || 0) > 10", timeout=30_000)
        page.select_option("#trig-signal", "w_ref")
        page.fill("#trig-level", "-1e9")
        page.select_option("#trig-edge", "falling")
        shot = tmp_path / "scope.png"
        page.screenshot(path=str(shot))
        assert shot.stat().st_size > 10_000
        keep = os.environ.get("SCOPE_SCREENSHOT")
        if keep:
            shutil.copy(shot, keep)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert proc.returncode == 130, proc.stderr.read() if proc.stderr else ""
    summary = json.loads((out / "summary.json").read_text())
    assert summary["run"]["stop"] == "INTERRUPTED"
    assert summary["scope"]["sent_rows"] > 0 and summary["scope"]["clients"] >= 0


def test_a_finished_run_opens_in_the_same_page(browser, tmp_path):
    from gateway.cli import main

    run = tmp_path / "run"
    assert main(["simulate", "--reference", "profiles/quick.toml", "--out", str(run)]) == 0
    feed = ScopeFeed("finished")
    from gateway.report import load_run

    loaded = load_run(run)
    feed.load(loaded.signals)
    feed.finish(loaded.summary)
    server = ScopeServer(feed, *parse_address("0"))
    try:
        page = browser.new_page()
        page.goto(server.url)
        page.wait_for_function("window.scope.samples >= 250 && window.scope.stop",
                               timeout=30_000)
        assert "stopped: END_OF_PROFILE" in page.locator("#status").inner_text()
        page.select_option("#timebase", "0")  # the whole run
        page.wait_for_function("(window.scope.traces.w_m || 0) >= 200", timeout=30_000)
    finally:
        server.close()


def test_a_campaigns_running_table_feeds_the_scope(tmp_path, capsys):
    """`campaign --scope`: each point's numeric results against its number, as the points
    come back; the scope's address is printed and the campaign ends as usual."""
    from gateway.campaign.command import PointRows
    from gateway.cli import main

    feed = ScopeFeed("campaign")
    view = PointRows(feed)
    client = feed.subscribe()
    view.add([{"hash": "a", "status": "ok", "speed_rms": 0.5, "passed": True},
              {"hash": "b", "status": "ok", "speed_rms": 0.7, "passed": False}])
    view.finish()
    feed.stats()
    events = _events(client)
    metas = [d for e, d in events if e == "meta"]
    assert metas[-1]["columns"] == ["t", "speed_rms"]  # numbers only, not flags or text
    rows = [d for e, d in events if e == "rows"]
    assert [x for d in rows for x in d["columns"]["speed_rms"]] == [0.5, 0.7]
    assert events[-1] == ("state", {"running": False, "cycles": 2, "stop": "CAMPAIGN_DONE",
                                    "stop_reason": "2 points run", "speed_error_rms": None})
    campaign = tmp_path / "c.toml"
    campaign.write_text('[campaign]\nname = "tiny"\ncommand = "simulate"\n[base]\n'
                        'profile = "profiles/quick.toml"\nduration = "10ms"\n'
                        '[grid]\n"plant.motor.Rs" = [0.9, 1.1]\n')
    assert main(["campaign", str(campaign), "--in-process", "--scope", "127.0.0.1:0",
                 "--out", str(tmp_path / "out")]) == 0
    assert re.search(r"scope: http://127\.0\.0\.1:\d+/", capsys.readouterr().err)


def test_plotjuggler_gets_each_row_as_a_json_datagram_during_a_sim_run(tmp_path, capsys):
    """`sim --plotjuggler PORT`: PlotJuggler's UDP server (JSON) receives the scope's rows,
    one object a row with the time in ``t``; none carries a NaN (left out)."""
    import socket

    from gateway.cli import main

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.2)
    port = sock.getsockname()[1]
    got: list[dict] = []
    done = threading.Event()

    def receive():
        while not done.is_set():
            try:
                data, _ = sock.recvfrom(65536)
            except TimeoutError:
                continue
            got.append(json.loads(data))

    thread = threading.Thread(target=receive, daemon=True)
    thread.start()
    try:
        status = main(["sim", "--reference", "profiles/quick.toml", "--duration", "300ms",
                       "--plotjuggler", str(port), "--no-figures", "--out",
                       str(tmp_path / "run")])
        time.sleep(0.5)  # the last datagrams on their way
    finally:
        done.set()
        thread.join(2)
        sock.close()
    err = capsys.readouterr().err
    assert status == 0
    assert f"plotjuggler: streaming to udp://127.0.0.1:{port}" in err
    sent = int(re.search(r"plotjuggler: (\d+) rows sent", err).group(1))
    # UDP: a receiver's full buffer drops datagrams (about 100 fit in Linux's default)
    assert sent >= 100 and sent // 2 <= len(got) <= sent
    t = [row["t"] for row in got]
    assert t == sorted(set(t)) and t[0] < 0.01
    assert all("w_m" in row and "i_sa" in row for row in got[5:])
    assert not any(isinstance(v, float) and math.isnan(v) for row in got for v in row.values())
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["scope"]["sent_rows"] == sent
