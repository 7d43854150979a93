"""The report in a real headless browser (Debian's chromium, installed by .ci/run):
a screenshot that shows the figures, every image decoded, no console errors.

Skipped when /usr/bin/chromium is absent. The screenshot is kept in the test's tmp dir
(``report.png``) for a human to look at. The report itself has no script; to ask the
browser whether every image decoded, the test loads a copy with a small probe script
that writes the answer into the DOM, which ``--dump-dom`` prints after the load event.
"""
from __future__ import annotations

import json
import os
import re
import signal
import subprocess
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller.report import write_report

from report_fixture import build_session

CHROMIUM = Path("/usr/bin/chromium")
WINDOW = (1200, 3000)
TIMEOUT_S = 120.0

pytestmark = pytest.mark.skipif(not CHROMIUM.exists(),
                                reason="needs Debian's chromium at /usr/bin/chromium "
                                       "(apt-get install -y --no-install-recommends chromium)")

PROBE = ("<script>window.addEventListener('load', () => {"
         " const ok = [...document.images].map(i => i.complete && i.naturalWidth > 0 && i.naturalHeight > 0);"
         " document.body.setAttribute('data-probe', JSON.stringify({n: ok.length, ok: ok.filter(Boolean).length,"
         " sections: [...document.querySelectorAll('section')].map(s => s.id)}));"
         " console.info('probe-done'); });</script>")


def _chromium(user_data_dir: Path, *args: str) -> tuple[str, str]:
    """Run headless chromium (own process group, killed whole on timeout); (stdout, stderr)."""
    argv = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
            "--disable-background-networking", "--disable-component-update", "--disable-sync",
            f"--user-data-dir={user_data_dir}", "--enable-logging=stderr", "--v=0", *args]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        pytest.fail(f"chromium did not finish within {TIMEOUT_S:g} s")
    assert proc.returncode == 0, err.decode(errors="replace")[-2000:]
    return out.decode("utf-8", errors="replace"), err.decode("utf-8", errors="replace")


def _console_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if ":CONSOLE" in line]


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    session = build_session(tmp_path_factory.mktemp("browser") / "session", "final")
    return write_report(session)


def test_screenshot_shows_the_figures(report: Path, tmp_path: Path) -> None:
    from PIL import Image

    shot = tmp_path / "report.png"
    _, err = _chromium(tmp_path / "profile", f"--screenshot={shot}", f"--window-size={WINDOW[0]},{WINDOW[1]}",
                       report.as_uri())
    assert shot.exists() and shot.stat().st_size > 50_000
    with Image.open(shot) as im:
        assert im.size == WINDOW
        pixels = np.asarray(im.convert("RGB"))
    # Text alone paints a few hundred distinct colours; the antialiased figures thousands.
    colours = np.unique(pixels.reshape(-1, 3), axis=0).shape[0]
    assert colours > 2000, f"only {colours} distinct colours: the figures did not render"
    assert (pixels.min(axis=2) < 200).mean() > 0.02, "the page is (nearly) blank"
    assert not [line for line in _console_lines(err) if "error" in line.lower()]
    assert "net::ERR" not in err


def test_every_image_decodes_and_nothing_complains(report: Path, tmp_path: Path) -> None:
    page = report.read_text(encoding="utf-8")
    assert "<script" not in page                     # the product page is script-free
    n_img = len(re.findall(r"<img ", page))
    assert n_img >= 10
    probe = report.parent / "probe.html"             # beside the report: same relative context
    probe.write_text(page.replace("</body>", PROBE + "</body>"), encoding="utf-8")
    try:
        dom, err = _chromium(tmp_path / "profile", "--dump-dom", probe.as_uri())
    finally:
        probe.unlink()
    match = re.search(r'data-probe="([^"]*)"', dom)
    assert match, "the probe did not run (page load never completed?)"
    result = json.loads(match.group(1).replace("&quot;", '"'))
    assert result["n"] == n_img and result["ok"] == n_img, result
    assert {"numbers", "region-map", "profiles", "measured-vs-model", "predictions", "disagreement", "training",
            "timeline", "faults", "provenance"} <= set(result["sections"])
    console = _console_lines(err)
    assert any("probe-done" in line for line in console)
    assert [line for line in console if "probe-done" not in line] == []
    assert "net::ERR" not in err
