"""`--serve` never claims a port it does not hold, and never leaves its viewer server behind (issue 13, item 10).

Before the fix a second instance, finding 9876 taken, connected to the other program's port and
reported that it served; SIGTERM to `mca process --serve` left the rerun server running.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_process import make_png

from mca.capture.recording import rerun_executable

pytestmark = pytest.mark.skipif(rerun_executable() is None, reason="the rerun CLI of rerun-sdk is not installed")


def _listener(port: int = 0) -> socket.socket | None:
    """A socket listening on 127.0.0.1:`port` (another program holding it), or None if that port is taken."""
    sock = socket.socket()
    try:
        sock.bind(("127.0.0.1", port))
    except OSError:
        sock.close()
        return None
    sock.listen()
    return sock


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry.name))
    return found


def _gone(pid: int, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            return True
        if state == "Z":
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.05)


SERVE_CHILD = """
import json, socket, sys
from mca.capture.recording import RerunRecorder
ports = json.loads(sys.argv[1])
try:
    recorder = RerunRecorder(None, serve=True, **ports)
except RuntimeError as exc:
    print(json.dumps({"error": str(exc)}))
    sys.exit(0)
try:
    data_port, web_port = recorder.ports
    alive = recorder._server is not None and recorder._server.poll() is None
    with socket.create_connection(("127.0.0.1", data_port), timeout=5):
        pass
    print(json.dumps({"ports": [data_port, web_port], "url": recorder.viewer_url, "alive": alive}))
finally:
    recorder.close()
"""


def _serve_in_a_child(**ports: int) -> dict:
    """Make a serving recorder in a child process: one that took another program's port for its own hangs
    talking to it (in rerun's native code, holding the interpreter), and that must fail the test, not stop it."""
    import json

    proc = subprocess.Popen(
        [sys.executable, "-c", SERVE_CHILD, json.dumps(ports)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, RERUN_ANALYTICS="0"),
    )
    try:
        out, err = proc.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        for pid in _children(proc.pid):  # the server it started, by its id
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        proc.kill()
        proc.communicate()
        pytest.fail("the recorder hung: it took a port another program holds for its own server's")
    assert proc.returncode == 0, err[-2000:]
    return json.loads(out.strip().splitlines()[-1])


def test_a_port_asked_for_that_is_taken_is_an_error_not_a_false_claim():
    holder = _listener()
    port = holder.getsockname()[1]
    try:
        answer = _serve_in_a_child(grpc_port=port)
    finally:
        holder.close()
    assert f"port {port} on 127.0.0.1 is already in use" in answer.get("error", ""), answer


def test_taken_default_ports_are_replaced_by_free_ones_that_it_really_serves():
    holders = [h for h in (_listener(9876), _listener(9090)) if h is not None]  # else someone else holds them
    try:
        answer = _serve_in_a_child()
    finally:
        for holder in holders:
            holder.close()
    assert "ports" in answer, answer
    data_port, web_port = answer["ports"]
    assert data_port != 9876 and web_port != 9090 and answer["alive"]
    assert f"127.0.0.1:{web_port}/" in answer["url"]


@pytest.mark.parametrize("how", [signal.SIGTERM, signal.SIGKILL], ids=["sigterm", "sigkill"])
def test_stopping_mca_process_serve_stops_its_viewer_server(tmp_path, how):
    source = make_png(tmp_path / "a.png")
    proc = subprocess.Popen(
        [sys.executable, "-m", "mca", "process", str(source), "--out", str(tmp_path / "out"), "--serve"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        env=dict(os.environ, RERUN_ANALYTICS="0"),
    )
    servers: list[int] = []
    try:
        lines = []
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stderr.readline()
            lines.append(line)
            if "still serving" in line or not line:
                break
        assert any("still serving" in line for line in lines), "".join(lines)
        servers = [pid for pid in _children(proc.pid) if "rerun" in Path(f"/proc/{pid}/cmdline").read_text()]
        assert servers, "the viewer server should be a child of mca process"
        proc.send_signal(how)
        proc.wait(timeout=30)
        assert all(_gone(pid, 15) for pid in servers), "the rerun server outlived mca process"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for pid in servers:  # on failure: end the server this test started, by its id
            if not _gone(pid, 0):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
