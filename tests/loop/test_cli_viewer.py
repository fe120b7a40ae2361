"""`harvest-qp run --viewer meshcat` and `harvest-qp replay --html` through the CLI's own entry point.

Catches a viewer that is not wired into `run` (no URL printed, no server started), a viewer
that outlives the command (orphan meshcat server), and a replay that cannot read the log the
closed loop writes (no offline HTML).
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

from harvest_qp.cli import main
from harvest_qp.robot.paths import tasks_dir


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _meshcat_processes() -> list[int]:
    found = []
    for pid in os.listdir("/proc"):
        if not pid.isdigit():
            continue
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ")
        except OSError:
            continue
        if b"meshcat" in cmdline and b"pytest" not in cmdline:
            found.append(int(pid))
    return found


def test_run_with_live_viewer_then_replay_html(tmp_path, capfd):
    before = set(_meshcat_processes())
    port = _free_port()
    out = tmp_path / "run"
    code = main(["run", str(tasks_dir() / "paper.yaml"), "--duration", "0.3", "--out", str(out), "--no-figures",
                 "--viewer", "meshcat", "--fast", "--port", str(port)])  # fmt: skip
    captured = capfd.readouterr()  # the viewer prints its URL from its own process
    printed = captured.out + captured.err
    assert code in (0, 1)  # a 0.3 s episode does not reach the pre-cut state
    assert f"127.0.0.1:{port}" in printed  # the viewer served on loopback, at the asked port
    assert (out / "episode.npz").is_file() and (out / "metrics.json").is_file()
    assert set(_meshcat_processes()) <= before  # no server left behind
    html = tmp_path / "episode.html"
    assert main(["replay", str(out), "--html", str(html)]) == 0
    text = html.read_text(errors="replace")
    assert html.stat().st_size > 100_000 and "meshcat" in text.lower()
