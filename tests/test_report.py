"""The session report: every figure present and a real PNG, self-contained, numbers that
match the journal, partial sessions shown as "not yet", damage shown rather than fatal."""
from __future__ import annotations

import base64
import shutil
import struct
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from elastoprobe.controller import report as R
from elastoprobe.controller.journal import Journal

from report_fixture import CHAR_ANGLES_DEG, X_MM, build_session, true_depth_mm, true_region

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class _Page(HTMLParser):
    """Sections (id -> images, not-yet notes, errors) and every URL-bearing attribute."""

    def __init__(self) -> None:
        super().__init__()
        self.sections: dict[str, dict[str, list[str]]] = {}
        self.current: str | None = None
        self.urls: list[str] = []
        self.tags: set[str] = set()
        self._p_class: str | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        self.tags.add(tag)
        if tag == "section":
            self.current = a.get("id") or ""
            self.sections[self.current] = {"img": [], "not_yet": [], "error": []}
        for key in ("src", "href"):
            if a.get(key):
                self.urls.append(a[key] or "")
        if self.current is None:
            return
        if tag == "img":
            self.sections[self.current]["img"].append(a.get("src") or "")
        if tag == "p" and a.get("class") in ("not-yet", "figure-error"):
            self.sections[self.current]["not_yet" if a["class"] == "not-yet" else "error"].append("")


def _parse(path: Path) -> _Page:
    page = _Page()
    page.feed(path.read_text(encoding="utf-8"))
    return page


def _png_size(uri: str) -> tuple[int, int]:
    assert uri.startswith("data:image/png;base64,"), uri[:40]
    data = base64.b64decode(uri.split(",", 1)[1], validate=True)
    assert data[:8] == PNG_MAGIC
    width, height = struct.unpack(">II", data[16:24])    # IHDR follows the signature
    return width, height


def _check_self_contained(page: _Page) -> None:
    assert "script" not in page.tags and "link" not in page.tags and "iframe" not in page.tags
    for url in page.urls:
        assert url.startswith("data:image/png;base64,") or url.startswith("#"), url[:60]


@pytest.fixture(scope="module")
def full_session(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_session(tmp_path_factory.mktemp("full") / "session", "final")


def test_full_report_has_every_figure(full_session: Path) -> None:
    out = R.write_report(full_session)
    assert out == full_session / "report" / "index.html"
    page = _parse(out)
    assert set(R.SECTION_IDS) <= set(page.sections)
    _check_self_contained(page)
    expected_images = {"region-map": 1, "profiles": 2, "measured-vs-model": 2, "predictions": 2,
                       "disagreement": 1, "training": 1, "timeline": 1, "faults": 1}
    for sid, n in expected_images.items():
        sec = page.sections[sid]
        assert len(sec["img"]) == n, (sid, len(sec["img"]))
        assert not sec["not_yet"] and not sec["error"], sid
        for uri in sec["img"]:
            w, h = _png_size(uri)
            assert w > 100 and h > 100
    assert not any(s["error"] for s in page.sections.values())
    # No temporary file left beside the report.
    assert [p.name for p in out.parent.iterdir()] == ["index.html"]


def test_numbers_match_the_journal(full_session: Path) -> None:
    with Journal.open_readonly(full_session) as j:
        numbers = R.report_numbers(j)
        steps = j.steps()
        robot = j.robot_time_s()
    assert numbers["force_steps_done"] == len(steps) == 64
    # 14 targets surveyed at one angle; 4 of them also at the two other characterization angles.
    assert numbers["probes_done"] == 14 + 4 * (len(CHAR_ANGLES_DEG) - 1)
    assert numbers["targets_probed"] == 14
    assert numbers["attempts"] == 65                     # one step was retried after a fault
    assert numbers["faults"] == 2 and numbers["faults_by_kind"] == {"force_spike": 1, "scanner_timeout": 1}
    assert numbers["regions"] == 2 and numbers["regions_round"] == 1 and numbers["model_round"] == 0
    assert numbers["robot_time_s"]["total"] == pytest.approx(robot["total"], abs=0.1)
    errs = {e["region"]: e for e in numbers["model_errors"]}
    assert set(errs) == {0, 1}
    for region, e in errs.items():
        # The fit error is judged against the data in mm: a unit slip (normalised vs mm)
        # or a wrong (F, angle) order would make it a sizeable fraction of the depth.
        assert e["fit_rmse_mm"] < 0.03 * e["depth_scale_mm"], e
        assert e["train_rmse_mm"] is not None and e["train_rmse_mm"] < 0.03 * e["depth_scale_mm"]


def test_models_in_the_report_predict_the_ground_truth(full_session: Path) -> None:
    """The models the report draws are the session's (loaded from the latest models phase)
    and are close to the synthetic truth at an unseen force between the probed levels."""
    with Journal.open_readonly(full_session) as j:
        data = R.collect(j)
    assert sorted(data.models) == [0, 1] and data.model_round == 0
    for region, model in data.models.items():
        pred = model.predict_mm(4.5, 90.0)
        truth = true_depth_mm(region, 4.5, 90.0, X_MM)
        assert np.sqrt(np.mean((pred - truth) ** 2)) < 0.1 * truth.max()


def test_disagreement_edges_index_the_labelled_targets(full_session: Path) -> None:
    with Journal.open_readonly(full_session) as j:
        data = R.collect(j)
    assert len(data.densify) == 1
    view = data.densify[0]
    assert len(view.positions_mm) == 12 and len(view.new_points_mm) == 2
    edges = view.outputs["record"]["disagreeing_edges"]
    assert edges
    for a, b in edges:
        # The fixture's disagreeing edges cross the material boundary at x = 60 mm.
        assert true_region(view.positions_mm[a]) != true_region(view.positions_mm[b])
        assert view.labels[a] != view.labels[b]


@pytest.mark.parametrize("upto, not_yet", [
    ("created", {"region-map", "profiles", "measured-vs-model", "predictions", "disagreement", "training"}),
    ("cloud", {"profiles", "measured-vs-model", "predictions", "disagreement", "training"}),
    ("survey", {"profiles", "measured-vs-model", "predictions", "disagreement", "training"}),
    ("characterize", {"measured-vs-model", "predictions", "disagreement", "training"}),
])
def test_partial_sessions_show_not_yet(tmp_path: Path, upto: str, not_yet: set[str]) -> None:
    session = build_session(tmp_path / "s", upto)
    page = _parse(R.write_report(session))
    assert set(R.SECTION_IDS) <= set(page.sections)
    _check_self_contained(page)
    for sid in R.SECTION_IDS:
        sec = page.sections[sid]
        assert not sec["error"], sid
        for uri in sec["img"]:
            assert min(_png_size(uri)) > 50
        if sid in not_yet:
            assert sec["not_yet"] and not sec["img"], sid
    assert page.sections["region-map"]["img"] or upto == "created"
    if upto == "characterize":
        assert len(page.sections["profiles"]["img"]) == 2


def test_report_while_the_writer_holds_the_journal(tmp_path: Path) -> None:
    """Regenerated after each phase: the report reads while the session's writer is open."""
    session = build_session(tmp_path / "s", "survey")
    writer = Journal.open(session, min_free_bytes=0)
    try:
        writer.log_event("progress", {"n": 1})
        page = _parse(R.write_report(session))
        assert page.sections["region-map"]["img"]
    finally:
        writer.close()


def test_a_damaged_model_file_is_reported_not_fatal(full_session: Path, tmp_path: Path) -> None:
    copy = tmp_path / "copy"
    shutil.copytree(full_session, copy, ignore=shutil.ignore_patterns("session.lock"))
    npz = copy / "models" / "round0" / "region1.npz"
    npz.write_bytes(npz.read_bytes()[:-40] + b"\0" * 40)
    out = R.write_report(copy)
    page = _parse(out)
    assert len(page.sections["measured-vs-model"]["img"]) == 1          # region 0 only
    assert page.sections["measured-vs-model"]["not_yet"]
    assert "cannot load models/round0/region1.npz" in out.read_text()


def test_training_curves_when_the_metadata_has_a_history(full_session: Path) -> None:
    with Journal.open_readonly(full_session) as j:
        data = R.collect(j)
    fig, curve = R.fig_training(data)
    assert fig is not None and curve                       # training records its loss history
    for model in data.models.values():
        del model.meta["training"]["extra"]["loss_history"]
    fig, curve = R.fig_training(data)
    assert fig is not None and not curve                   # without one: the final error per region
    for model in data.models.values():
        model.meta["training"]["history"] = [[1.0, 1.1], [0.1, 0.12], [0.01, 0.02]]
    fig, curve = R.fig_training(data)
    assert curve
    figs = R._Figures()
    section = R._section_training(figs, data)
    assert not figs.errors and "Loss history from the model metadata" in section and "<img" in section


def test_loss_history_shapes() -> None:
    assert R.loss_history({}) is None
    assert R.loss_history({"training": {"history": "garbage"}}) is None
    assert R.loss_history({"loss_history": [3.0, 2.0]}).shape == (2, 1)
    assert R.loss_history({"training": {"extra": {"loss_history": [[1, 2, 3]] * 4}}}).shape == (4, 3)


def test_unseen_queries_avoid_the_measured_levels() -> None:
    forces, angles = R.unseen_queries([1.0, 3.0, 6.0, 3.0], [60.0, 90.0, 120.0], (1.0, 6.0))
    assert np.allclose(forces, [2.0, 4.5]) and np.allclose(angles, [75.0, 105.0])
    forces, angles = R.unseen_queries([2.0], [90.0], (2.0, 2.0))
    assert np.allclose(forces, [2.0]) and np.allclose(angles, [67.5, 112.5])


def test_runs_are_laid_end_to_end_on_the_timeline() -> None:
    tr = [{"run_id": 1, "t_robot_s": 0.0}, {"run_id": 1, "t_robot_s": 100.0},
          {"run_id": 2, "t_robot_s": 0.0}, {"run_id": 2, "t_robot_s": 50.0}, {"run_id": 3, "t_robot_s": 5.0}]
    assert R._run_offsets(tr) == {1: 0.0, 2: 100.0, 3: 150.0}
