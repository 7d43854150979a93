"""Atomic writes: after a kill -9 at any moment the target is the old file or the new one."""
from __future__ import annotations

import hashlib
import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.core import atomic
from elastoprobe.controller.core.atomic import (
    atomic_dir_replace, atomic_write_bytes, atomic_write_json, atomic_write_text, make_staging_dir,
    remove_stale_temps,
)
from elastoprobe.controller.core.errors import DiskError

# Writes self-checking versions of one file forever (until killed); with KILL_BEFORE_REPLACE
# it kills itself after the temporary is complete but before the rename.
WRITER = textwrap.dedent("""
    import hashlib, json, os, signal, sys
    from elastoprobe.controller.core import atomic
    target, start = sys.argv[1], int(sys.argv[2])
    if os.environ.get("KILL_BEFORE_REPLACE"):
        def replace(src, dst):
            os.kill(os.getpid(), signal.SIGKILL)
        atomic.os.replace = replace
    print("ready", flush=True)
    for version in range(start, start + 100000):
        payload = "x" * (1000 + (version * 7919) % 300000)
        body = json.dumps({"version": version, "payload": payload})
        sha = hashlib.sha256(body.encode()).hexdigest()
        atomic.atomic_write_text(target, json.dumps({"body": body, "sha256": sha}))
""")


def _read_version(target: Path) -> int:
    doc = json.loads(target.read_text())
    assert hashlib.sha256(doc["body"].encode()).hexdigest() == doc["sha256"], "torn file"
    return int(json.loads(doc["body"])["version"])


def _writer(target: Path, start: int, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(target), str(start)], stdout=subprocess.PIPE,
                            text=True, env={**os.environ, **(env or {})})
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    return proc


def test_kill9_leaves_old_or_new_file(tmp_path: Path) -> None:
    target = tmp_path / "model.json"
    atomic_write_text(target, json.dumps({"body": json.dumps({"version": 0}),
                                          "sha256": hashlib.sha256(json.dumps({"version": 0}).encode()).hexdigest()}))
    rng = random.Random(4)
    last = 0
    for k in range(12):
        proc = _writer(target, start=(k + 1) * 100000)
        time.sleep(rng.uniform(0.0, 0.15))
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        version = _read_version(target)                 # complete and consistent, never torn
        assert version == last or version >= (k + 1) * 100000
        last = version
        remove_stale_temps(tmp_path)
        assert sorted(p.name for p in tmp_path.iterdir()) == ["model.json"]
    assert last > 0, "no write ever completed: the test did not exercise replacement"


def test_kill_before_rename_keeps_old_file(tmp_path: Path) -> None:
    target = tmp_path / "report.json"
    atomic_write_json(target, {"old": True})
    proc = _writer(target, start=1, env={"KILL_BEFORE_REPLACE": "1"})
    assert proc.wait(timeout=30) == -signal.SIGKILL
    assert json.loads(target.read_text()) == {"old": True}
    stale = remove_stale_temps(tmp_path)
    assert len(stale) == 1 and stale[0].name.startswith(".report.json.")
    assert [p.name for p in tmp_path.iterdir()] == ["report.json"]


def test_write_variants_and_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    p = atomic_write_bytes(tmp_path / "b.bin", b"\x00\x01", mode=0o600)
    assert p.read_bytes() == b"\x00\x01" and (p.stat().st_mode & 0o777) == 0o600
    atomic_write_json(tmp_path / "m.json", {"rmse_mm": np.float32(0.5), "n": np.int64(3), "v": np.arange(2)})
    assert json.loads((tmp_path / "m.json").read_text()) == {"rmse_mm": 0.5, "n": 3, "v": [0, 1]}
    with pytest.raises(ValueError):
        atomic_write_json(tmp_path / "m.json", {"x": float("inf")})   # null, never Infinity
    # A failing rename leaves the old file and no temporary behind, and says which path.
    def broken_replace(src: str, dst: str) -> None:
        raise OSError(28, "No space left on device")
    monkeypatch.setattr(atomic.os, "replace", broken_replace)
    with pytest.raises(DiskError, match=r"m\.json: cannot write: No space left on device \(the disk is full\)"):
        atomic_write_text(tmp_path / "m.json", "new")
    monkeypatch.undo()
    assert json.loads((tmp_path / "m.json").read_text())["n"] == 3
    assert sorted(q.name for q in tmp_path.iterdir()) == ["b.bin", "m.json"]


@pytest.mark.parametrize("exchange", [True, False])
def test_dir_replace(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, exchange: bool) -> None:
    if not exchange:
        monkeypatch.setattr(atomic, "_rename_exchange", lambda a, b: False)
    models = tmp_path / "models"
    for version in (1, 2):
        stage = make_staging_dir(models)
        (stage / "r0.pt").write_text(f"v{version}")
        (stage / "sub").mkdir()
        (stage / "sub" / "x").write_text(f"v{version}")
        atomic_dir_replace(stage, models)
        assert (models / "r0.pt").read_text() == f"v{version}"
        assert (models / "sub" / "x").read_text() == f"v{version}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["models"]
