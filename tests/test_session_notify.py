"""The operator's notify command runs on finish with a JSON payload; the report shows the final status."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from elastoprobe.controller.cli import main

HERE = Path(__file__).parent
TINY = HERE / "data" / "session" / "tiny.yaml"


def test_finish_notifies_and_the_report_says_done(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setenv("ELASTOPROBE_LOCK_DIR", str(tmp_path / "locks"))
    inbox = tmp_path / "inbox.jsonl"
    hook = f"import sys; open({str(inbox)!r}, 'a').write(sys.stdin.read() + '\\n')"
    plan = tmp_path / "tiny_notify.yaml"
    text = TINY.read_text().replace("../../../config/", str(HERE.parent / "config") + "/")
    text += f"notify:\n  command: [{json.dumps(sys.executable)}, -c, {json.dumps(hook)}]\n  on: [finish, pause]\n"
    plan.write_text(text)
    out = tmp_path / "session"
    assert main(["run", str(plan), "--out", str(out), "--seed", "2", "--quiet"]) == 0
    payloads = [json.loads(line) for line in inbox.read_text().splitlines() if line.strip()]
    assert [p["event"] for p in payloads] == ["finish"]
    assert payloads[0]["plan"] == "tiny" and payloads[0]["counts"]["done"] > 0
    report = (out / "report" / "index.html").read_text()
    assert "done" in report.split("</h1>")[0]
