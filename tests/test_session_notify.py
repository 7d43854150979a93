"""The operator's notify command runs on finish with a JSON payload; the report shows the final status.

The run is the shared tiny session (tests/conftest.py), whose plan notifies on finish and pause."""
from __future__ import annotations

import json
from pathlib import Path


def test_finish_notifies_and_the_report_says_done(tiny_session: dict) -> None:
    finished = Path(tiny_session["finished"]).resolve()
    payloads = [json.loads(line) for line in tiny_session["notify_inbox"].read_text().splitlines() if line.strip()]
    # Other tests' runs of the same plan notify into the same file: this run's are its own.
    mine = [p for p in payloads if Path(p["session_dir"]).resolve() == finished]
    assert [p["event"] for p in mine] == ["finish"], payloads
    assert mine[0]["plan"] == "tiny" and mine[0]["counts"]["done"] > 0
    report = (finished / "report" / "index.html").read_text()
    assert "done" in report.split("</h1>")[0]
