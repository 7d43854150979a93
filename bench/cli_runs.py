"""The CLI as the benches call it: ``elastoprobe ARGS`` in a subprocess, a session's status, and
the argument types the benches share.

Shared by the benches that run sessions the way a user does (bench/calibrated_demo.py,
bench/mapping_suite.py), so every one of them goes through the installed entry point's
module with the same working folder and no stdin.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def cli(*args: str, timeout_s: float, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """``elastoprobe ARGS`` in a subprocess (timeout in s; ``env`` None: this process's)."""
    cmd = [sys.executable, "-m", "elastoprobe.controller.cli", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, cwd=ROOT,
                          stdin=subprocess.DEVNULL, env=env)


def session_status(session_dir: Path, timeout_s: float = 120.0) -> dict[str, Any] | None:
    """``elastoprobe status DIR --json`` (None when there is no session or it cannot be read)."""
    if not (session_dir / "journal.sqlite").exists():
        return None
    proc = cli("status", str(session_dir), "--json", timeout_s=timeout_s)
    try:
        return json.loads(proc.stdout) if proc.returncode == 0 else None
    except json.JSONDecodeError:
        return None


def parse_ints(text: str) -> list[int]:
    """An argparse type: comma-separated integers (at least one)."""
    try:
        vals = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not vals:
        raise argparse.ArgumentTypeError("expected at least one integer")
    return vals
