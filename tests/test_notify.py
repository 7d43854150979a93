"""Notifier: a real command gets the JSON payload; failures, hangs and missing programs are
results, never exceptions; a hung command's whole process group is killed.
DiskWatch: ok / warn / pause thresholds through a fake statvfs."""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from elastoprobe.controller.core.config import NotifySpec
from elastoprobe.controller.notify import DiskWatch, Notifier, run_command

PY = sys.executable
COUNTS = {"planned": 3, "in_progress": 0, "done": 40, "failed": 1, "skipped": 0}


def _spec(command: list[str], on: list[str] | None = None, timeout_s: float = 10.0) -> NotifySpec:
    doc: dict[str, Any] = {"command": command, "timeout_s": timeout_s}
    if on is not None:
        doc["on"] = on
    return NotifySpec.model_validate(doc)


def _writer(out: Path) -> list[str]:
    """A command that writes its stdin and its ELASTOPROBE_EVENT to ``out`` (as JSON)."""
    code = ("import json, os, sys; data = sys.stdin.read(); "
            "open(sys.argv[1], 'w').write(json.dumps({'stdin': data, 'env': os.environ.get('ELASTOPROBE_EVENT')}))")
    return [PY, "-c", code, str(out)]


def _dead(pid: int) -> bool:
    """Gone or a zombie (a killed grandchild waits for init to reap it)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return True
    return state in ("Z", "X")


def test_command_gets_the_payload_on_stdin(tmp_path: Path) -> None:
    out = tmp_path / "payload.json"
    logged: list[tuple[str, dict]] = []
    n = Notifier(_spec(_writer(out)), log=lambda kind, rec: logged.append((kind, dict(rec))))
    result = n.notify("fault", tmp_path / "session", plan="ball", counts=COUNTS, message="force spike at step 41",
                      t_robot_s=1234.5, extra={"kind": "force_spike", "step_id": 41})
    assert result.ok and result.ran and result.returncode == 0 and not result.timed_out
    got = json.loads(out.read_text())
    assert got["env"] == "fault"
    payload = json.loads(got["stdin"])
    assert payload["event"] == "fault" and payload["plan"] == "ball"
    assert payload["session_dir"] == str(tmp_path / "session")
    assert payload["counts"] == COUNTS and payload["message"] == "force spike at step 41"
    assert payload["t_robot_s"] == 1234.5 and payload["extra"] == {"kind": "force_spike", "step_id": 41}
    assert payload["time_utc"].endswith("+00:00")
    assert logged == [("notify", result.to_dict())]


def test_unsubscribed_event_and_no_spec_run_nothing(tmp_path: Path) -> None:
    out = tmp_path / "payload.json"
    n = Notifier(_spec(_writer(out), on=["finish"]))
    r = n.notify("pause", tmp_path, message="operator pause")
    assert not r.ran and r.skipped and not out.exists()
    assert n.wants("finish") and not n.wants("fault")
    r = Notifier(None).notify("fault", tmp_path, message="x")
    assert not r.ran and r.skipped == "no notify command configured"
    r = Notifier(_spec(_writer(out))).notify("exploded", tmp_path)
    assert not r.ran and not r.ok and "unknown event" in (r.error or "")


def test_failing_and_missing_commands_are_results(tmp_path: Path) -> None:
    failing = [PY, "-c", "import sys; sys.stdin.read(); sys.stderr.write('mail server down\\n'); sys.exit(3)"]
    r = Notifier(_spec(failing)).notify("finish", tmp_path, message="done")
    assert r.ran and not r.ok and r.returncode == 3 and "mail server down" in r.stderr_tail
    assert "status 3" in (r.error or "")
    r = Notifier(_spec([str(tmp_path / "no-such-program")])).notify("finish", tmp_path)
    assert not r.ran and not r.ok and "cannot run" in (r.error or "")
    # A command that does not read its stdin at all still counts as delivered when it exits 0.
    r = Notifier(_spec([PY, "-c", "import os; os.close(0)"])).notify("finish", tmp_path)
    assert r.ok


def test_a_hanging_command_is_killed_with_its_children(tmp_path: Path) -> None:
    pids = tmp_path / "pids"
    code = ("import subprocess, sys, time; "
            f"c = subprocess.Popen([{PY!r}, '-c', 'import time; time.sleep(120)']); "
            "open(sys.argv[1], 'w').write(f'{__import__(\"os\").getpid()} {c.pid}'); "
            "time.sleep(120)")
    r = Notifier(_spec([PY, "-c", code, str(pids)], timeout_s=1.5)).notify("pause", tmp_path)
    assert r.ran and r.timed_out and not r.ok and "killed" in (r.error or "")
    parent, child = (int(v) for v in pids.read_text().split())
    deadline = time.monotonic() + 10.0
    while not (_dead(parent) and _dead(child)) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert _dead(parent) and _dead(child)


def test_bad_payload_and_a_broken_log_do_not_raise(tmp_path: Path) -> None:
    def broken_log(kind: str, record: Any) -> None:
        raise RuntimeError("journal closed")

    n = Notifier(_spec(_writer(tmp_path / "p.json")), log=broken_log)
    r = n.notify("fault", tmp_path, extra={"value": float("nan")})     # NaN is not JSON
    assert not r.ran and not r.ok and "ValueError" in (r.error or "")
    assert n.notify("finish", tmp_path).ok


def test_run_command_feeds_large_payloads(tmp_path: Path) -> None:
    out = tmp_path / "big"
    data = b"x" * 300_000          # larger than a pipe buffer: must not deadlock
    code = "import sys; open(sys.argv[1], 'wb').write(sys.stdin.buffer.read())"
    r = run_command([PY, "-c", code, str(out)], data, timeout_s=20.0)
    assert r.ok and out.read_bytes() == data


# ---------------------------------------------------------------------------- disk watch
class FakeStatvfs:
    def __init__(self, free_bytes: int, block: int = 4096) -> None:
        self.free_bytes, self.block = free_bytes, block
        self.paths: list[str] = []
        self.error: OSError | None = None

    def __call__(self, path: str) -> Any:
        self.paths.append(path)
        if self.error is not None:
            raise self.error
        return SimpleNamespace(f_bavail=self.free_bytes // self.block, f_frsize=self.block, f_blocks=10**9)


MIB = 2**20


def test_disk_watch_levels(tmp_path: Path) -> None:
    fs = FakeStatvfs(1000 * MIB)
    w = DiskWatch(tmp_path, min_free_bytes=100 * MIB, warn_free_bytes=300 * MIB, statvfs=fs)
    assert w.check().level == "ok" and w.check().free_bytes == 1000 * MIB
    fs.free_bytes = 300 * MIB
    assert w.check().level == "ok"                     # at the warning line, not below
    fs.free_bytes = 300 * MIB - 4096
    assert w.check().level == "warn"
    fs.free_bytes = 150 * MIB
    assert w.check().level == "warn"
    assert w.check(next_write_bytes=60 * MIB).level == "pause"     # the next step would cross the floor
    fs.free_bytes = 99 * MIB
    s = w.check()
    assert s.level == "pause" and "99 MiB" in s.message and w.last == s
    fs.error = OSError(5, "Input/output error")
    s = w.check()
    assert s.level == "pause" and s.free_bytes is None and "Input/output" in s.message


def test_disk_watch_preflight_and_paths(tmp_path: Path) -> None:
    fs = FakeStatvfs(500 * MIB)
    w = DiskWatch(tmp_path / "not" / "yet", min_free_bytes=100 * MIB, statvfs=fs)
    assert w.warn_free_bytes == 200 * MIB
    assert w.preflight(expected_bytes=300 * MIB).level == "ok"
    s = w.preflight(expected_bytes=450 * MIB)
    assert s.level == "warn" and "pause part-way" in s.message
    assert fs.paths[-1] == str(tmp_path)               # the nearest existing parent's disk
    fs.free_bytes = 50 * MIB
    assert w.preflight().level == "pause"
    with pytest.raises(ValueError):
        DiskWatch(tmp_path, min_free_bytes=10, warn_free_bytes=5)
    real = DiskWatch(tmp_path, min_free_bytes=0, warn_free_bytes=0)
    assert real.check().level == "ok" and (real.check().free_bytes or 0) > 0
