"""Provenance: inputs hashed exactly, everything else best effort (None, never an exception)."""
from __future__ import annotations

import hashlib
import subprocess
from pathlib import Path

import pytest

from elastoprobe.controller import provenance
from elastoprobe.controller.core.errors import InputError
from elastoprobe.controller.provenance import (
    collect_provenance, git_revision, package_versions, sha256_file, sha256_text,
)


def test_hashes_match_file_bytes(tmp_path: Path) -> None:
    text = "name: démo\r\nseed: 1\n"          # non-ASCII and CRLF kept byte for byte
    p = tmp_path / "plan.yaml"
    p.write_bytes(text.encode("utf-8"))
    cal = tmp_path / "cal.json"
    cal.write_bytes(b"{}" * 1_000_000)           # > 1 chunk
    prov = collect_provenance(p, p, cal)
    assert prov["plan"]["text"] == text
    assert prov["plan"]["sha256"] == sha256_text(text) == hashlib.sha256(text.encode()).hexdigest()
    assert prov["calibration"]["sha256"] == sha256_file(cal) == hashlib.sha256(cal.read_bytes()).hexdigest()
    assert prov["python"]["version"].count(".") == 2


def test_best_effort_parts_become_none(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    p = tmp_path / "plan.yaml"
    p.write_text("name: x\n")
    assert package_versions(("surely-not-installed-dist",)) == {"surely-not-installed-dist": None}
    assert git_revision(tmp_path) is None                       # not a repository

    def hung_git(*args: object, **kwargs: object) -> None:
        raise subprocess.TimeoutExpired("git", 5)
    monkeypatch.setattr(provenance.subprocess, "run", hung_git)
    prov = collect_provenance(p, p, tmp_path / "missing-calibration.json")
    assert prov["git"] is None
    assert prov["calibration"]["sha256"] is None and "error" in prov["calibration"]
    assert collect_provenance(p, p, None)["calibration"] is None


def test_unreadable_inputs_are_input_errors(tmp_path: Path) -> None:
    bad = tmp_path / "plan.yaml"
    bad.write_bytes(b"name: \xff\n")
    with pytest.raises(InputError, match="not UTF-8"):
        collect_provenance(bad, bad)
    with pytest.raises(InputError, match="cannot read the cell"):
        collect_provenance(_ok(tmp_path), tmp_path / "nope.yaml")


def _ok(tmp_path: Path) -> Path:
    p = tmp_path / "ok.yaml"
    p.write_text("name: ok\n")
    return p


def test_git_revision_of_this_checkout() -> None:
    rev = git_revision()
    if rev is None:
        pytest.skip("not running from a git checkout")
    assert len(rev["revision"]) == 40 and rev["dirty"] in (True, False, None)
