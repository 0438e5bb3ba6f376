"""The local rerun web viewer a recorder streams to: its ports, its process, and stopping it whatever happens."""

from __future__ import annotations

import atexit
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from urllib.parse import quote

from mca.capture.recording.rerun_env import child_environment, rerun_executable

DEFAULT_GRPC_PORT = 9876  # rerun's own defaults
DEFAULT_WEB_PORT = 9090


def port_in_use(host: str, port: int) -> bool:
    """True when `port` cannot be bound on `host` (another program listens there)."""
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((host, port))
        except OSError:
            return True
    return False


def free_port(host: str) -> int:
    """A port the system says is free on `host` now."""
    import socket

    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as probe:
        probe.bind((host, 0))
        return int(probe.getsockname()[1])


def choose_port(
    host: str, wanted: int | None, default: int, what: str, taken: set[int] | frozenset = frozenset()
) -> int:
    """`wanted` if free (else an error naming it), or `default` if free, or a free port."""
    if wanted is not None:
        if wanted in taken or port_in_use(host, wanted):
            raise RuntimeError(
                f"port {wanted} on {host} is already in use (another `mca --serve`, `mca view --web` or rerun "
                f"viewer?); choose another for {what}, or leave it out to take a free one"
            )
        return wanted
    if default not in taken and not port_in_use(host, default):
        return default
    while True:
        port = free_port(host)
        if port not in taken:
            return port


def die_with_parent(command: list[str]) -> list[str]:
    """`command` run so that the kernel stops it when this process dies, however it dies (Linux `setpriv`)."""
    setpriv = shutil.which("setpriv") if sys.platform.startswith("linux") else None
    if setpriv is None:
        return command
    return [setpriv, "--pdeathsig", "TERM", "--", *command]


def wait_for_port(host: str, port: int, process: subprocess.Popen[bytes], timeout_s: float) -> None:
    """Wait until the server `process` listens on `port`; the port was free before it started, so a listener
    there is the server (checked to be still running), not somebody else's."""
    import socket

    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(
                f"the rerun server exited (code {process.returncode}) before listening on {host}:{port}; "
                "is the port in use? Choose another"
            )
        try:
            with socket.create_connection((host, port), timeout=0.2):
                pass
        except OSError:
            time.sleep(0.1)
            continue
        if process.poll() is None:
            return
    raise RuntimeError(f"the rerun server did not listen on {host}:{port} within {timeout_s:.0f} s")


@dataclass
class ViewerServer:
    """A running `rerun --serve-web` child: where it listens and how to stop it (`stop` is idempotent)."""

    process: subprocess.Popen[bytes]
    grpc_url: str  # where a recording stream sends its data
    viewer_url: str  # what a browser opens
    ports: tuple[int, int]  # (data, web page)
    stopped: bool = field(default=False)

    def poll(self) -> int | None:
        """None while the server runs, else its exit code (as `Popen.poll`)."""
        return self.process.poll()

    def stop(self) -> None:
        """Stop the server (terminate, then kill after 5 s); safe to call again."""
        if self.stopped:
            return
        self.stopped = True
        atexit.unregister(self.stop)
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(timeout=5)


def start_viewer_server(bind: str, grpc_port: int | None, web_port: int | None) -> ViewerServer:
    """Start `rerun --serve-web` bound to `bind` and wait until it listens on both ports.

    Ports left out are 9876 (data) and 9090 (web page) when free, else free ones; a port asked for that
    is in use is an error, never a false claim to serve. The server is stopped by `ViewerServer.stop`, at
    interpreter exit, and (on Linux) by the kernel when this process dies, even by SIGKILL.
    """
    exe = rerun_executable()
    if exe is None:
        raise RuntimeError("--serve needs the `rerun` command of rerun-sdk; reinstall with `pip install rerun-sdk`")
    grpc_port = choose_port(bind, grpc_port, DEFAULT_GRPC_PORT, "the data port (--grpc-port)")
    web_port = choose_port(bind, web_port, DEFAULT_WEB_PORT, "the web viewer port (--web-port)", {grpc_port})
    command = [exe, "--serve-web", "--bind", bind, "--port", str(grpc_port), "--web-viewer-port", str(web_port)]
    process = subprocess.Popen(
        die_with_parent(command),
        env=child_environment(),
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    host = "127.0.0.1" if bind in ("0.0.0.0", "::", "127.0.0.1") else bind
    grpc_url = f"rerun+http://{host}:{grpc_port}/proxy"
    server = ViewerServer(
        process, grpc_url, f"http://{host}:{web_port}/?url={quote(grpc_url, safe='')}", (grpc_port, web_port)
    )
    atexit.register(server.stop)
    try:
        for port in (grpc_port, web_port):
            wait_for_port(host, port, process, timeout_s=10.0)
    except BaseException:
        server.stop()
        raise
    return server
