"""The calibration report (``lfcal report``): self-contained HTML, identity, checks, checksum.

The HTML is read back with the standard library's HTML parser, every embedded
image decoded by OpenCV; the archive checksum is recomputed here from its
definition (SHA-256 over a header, the manifest bytes and one line per file).
"""

from __future__ import annotations

import copy
import hashlib
import json
import shutil
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from lab_support import LabData, lab_data
from test_lab_export import with_priors

from calibration.export_model import designed_patch_px
from calibration.report_archive import report_from_archive
from calibration.report_data import DIGEST_HEADER, archive_digest, camera_record
from calibration.report_html import build_report, result_checks
from station.cli import main


class Page(HTMLParser):
    """Tags, attributes and text of an HTML document."""

    def __init__(self, text: str) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str | None]]] = []
        self.text: list[str] = []
        self.feed(text)

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data: str) -> None:
        self.text.append(data)

    @property
    def words(self) -> str:
        return " ".join(" ".join(self.text).split())

    def find(self, tag: str) -> list[dict[str, str | None]]:
        return [a for t, a in self.tags if t == tag]


@pytest.fixture(scope="module")
def lab(pytestconfig: pytest.Config) -> LabData:
    return lab_data(pytestconfig)


@pytest.fixture
def archive(lab: LabData, tmp_path: Path) -> Path:
    """A copy of the lab archive whose manifest has the camera identity and per-frame
    temperature, exposure and gain that newer station archives record."""
    copy_dir = tmp_path / "sweep"
    shutil.copytree(lab.sweep, copy_dir)
    manifest = json.loads((copy_dir / "sweep.json").read_text())
    manifest["camera"]["identity"] = {
        "vendor": "Gpixel",
        "model": "GMAX0505 test camera",
        "serial": "SN-0042",
        "firmware": "1.2.3",
    }
    for k, frame in enumerate(manifest["frames"]):
        frame.update(temperature_c=21.5 + 0.125 * k, exposure_us=10000.0, gain_db=0.0)
    (copy_dir / "sweep.json").write_text(json.dumps(manifest, indent=2))
    (copy_dir / "result.json").write_text(json.dumps(lab.result()))
    return copy_dir


def _designed() -> float:
    return designed_patch_px(b_mm=2.5, f_mm=2.0, D_mm=0.2, delta_mm=0.0025)


def test_the_report_is_one_self_contained_page_with_everything(lab: LabData, archive: Path) -> None:
    result = lab.result()
    html = report_from_archive(result, archive, designed_px=_designed(), verify=True)
    page = Page(html)
    assert not page.find("script") and not page.find("link") and not page.find("iframe")
    images = page.find("img")
    assert len(images) == 5  # focus, disparity, residual plots; calibrated and designed crops
    for img in images:
        src = img["src"] or ""
        assert src.startswith("data:image/png;base64,")
        decoded = cv2.imdecode(np.frombuffer(_b64(src), np.uint8), cv2.IMREAD_UNCHANGED)
        assert decoded is not None and decoded.size > 0
    for tag, attrs in page.tags:
        for name in ("src", "href"):
            assert not (attrs.get(name) or "").startswith(("http:", "https:", "//")), (tag, attrs)
    words = page.words
    # identity and the conditions during the sweep
    for text in ("GMAX0505 test camera", "SN-0042", "1.2.3", "Gpixel"):
        assert text in words
    assert "21.5 – 22.9 °C (12 of 12 frames)" in words
    assert "Calibration report — GMAX0505 test camera serial SN-0042" in words
    # station and board, values with uncertainties, checks, software, checksum
    assert "squares 10.0 mm, reference gap Cr 0.1 mm" in words
    assert f"{result['b_mm']:.5f} ± {result['uncertainty']['b_mm']:.5f}" in words
    checks = [
        c
        for c in result_checks(result, archive_digest(archive, verify=True))
        if c.passed is not None
    ]
    assert checks and all(c.passed for c in checks)
    assert f"Verdict: PASS ({len(checks)} of {len(checks)} checks passed)" in words
    assert f"lfcal-station {result['software']['version']}" in words
    digest = archive_digest(archive, verify=True)
    assert digest.sha256 in words and "verified: every file re-read" in words
    # crops of the calibrated and designed p with their artefact scores: calibrated is better
    captions = [
        c for c in page.text if "artefact score" in c and c.startswith(("calibrated", "designed"))
    ]
    assert len(captions) == 2
    scores = [float(c.rsplit("artefact score", 1)[1]) for c in captions]
    assert scores[0] < scores[1]
    assert "p = 20.000 px" in captions[1]
    assert len(html.encode()) < 2_000_000


def _b64(src: str) -> bytes:
    import base64

    return base64.b64decode(src.split(",", 1)[1])


def test_older_archives_say_not_recorded_and_no_archive_is_said_too(lab: LabData) -> None:
    rec = camera_record(json.loads((lab.sweep / "sweep.json").read_text()))
    assert (rec.model, rec.serial, rec.firmware, rec.temperature_c) == (
        "not recorded",
        "not recorded",
        "not recorded",
        None,
    )
    assert camera_record(None).vendor == "not recorded"
    odd = {"camera": {"identity": "GMAX"}, "frames": [{"temperature_c": "warm"}, 3]}
    assert camera_record(odd).temperature_c is None  # odd types are not an error
    words = Page(report_from_archive(lab.result(), lab.sweep, designed_px=None)).words
    assert (
        "serial number not recorded" in words
        and "temperature during the sweep not recorded" in words
    )
    assert "only the calibrated patch size is shown" in words
    words = Page(report_from_archive(lab.result(), None)).words
    assert "The sweep archive is not available" in words and "archive not available" in words


def test_priors_outside_their_tolerance_fail_the_report(lab: LabData) -> None:
    result = with_priors(lab.result())
    checks = {c.name: c for c in result_checks(result, None)}
    assert checks["prior: main-lens focal length F"].passed is True  # |50 - 50.12| <= 0.5
    assert checks["prior: microlens focal length f"].passed is False  # |2 - 2.09| > 0.05
    assert checks["prior: rail zero object distance"].passed is True
    assert checks["prior: main lens to MLA L"].passed is None  # no data sheet, no tolerance
    page = Page(build_report(result))
    counted = [c for c in checks.values() if c.passed is not None]
    passed = sum(c.passed for c in counted)
    assert passed == len(counted) - 1  # only f fails
    assert f"Verdict: FAIL ({passed} of {len(counted)} checks passed)" in page.words
    assert "main lens to MLA (L_mm)" in page.words  # the calibrated L is the one shown
    # a result without a priors section (older software) lists the priors it used, as given
    old = {k: v for k, v in lab.result().items() if k != "priors"}
    assert "used as given" in Page(build_report(old)).words


def test_the_archive_checksum_follows_its_definition_and_catches_changes(archive: Path) -> None:
    manifest_bytes = (archive / "sweep.json").read_bytes()
    manifest = json.loads(manifest_bytes)
    h = hashlib.sha256(DIGEST_HEADER + manifest_bytes)
    h.update(f"white {manifest['white']} {manifest['white_sha256']}\n".encode())
    for f in manifest["frames"]:
        h.update(f"{f['index']} {f['file']} {f['sha256']}\n".encode())
    fast = archive_digest(archive)
    assert fast.sha256 == h.hexdigest() and fast.files == 13 and fast.verified is None
    assert archive_digest(archive, verify=True).verified is True
    frame = archive / manifest["frames"][4]["file"]
    data = bytearray(frame.read_bytes())
    data[-20] ^= 0x01
    frame.write_bytes(bytes(data))
    broken = archive_digest(archive, verify=True)
    assert broken.verified is False and broken.sha256 == fast.sha256  # the record is unchanged
    assert broken.problems == [
        f"{manifest['frames'][4]['file']}: SHA-256 differs from the manifest's"
    ]
    result = json.loads((archive / "result.json").read_text())
    words = Page(report_from_archive(result, archive, verify=True)).words
    assert "Verdict: FAIL" in words and "SHA-256 differs" in words


def _run(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def test_lfcal_report_of_an_archive_directory_and_of_a_result_file(
    lab: LabData, archive: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "report.html"
    code, stdout, err = _run(
        capsys, "report", str(archive), "--out", str(out), "--designed-b-mm", "2.5"
    )
    assert code == 0, err
    assert f"wrote {out}" in stdout
    words = Page(out.read_text()).words
    assert "SN-0042" in words and "designed p: p = 20.000 px" in words
    assert "verified: every file re-read" in words
    code, stdout, err = _run(
        capsys, "report", str(archive / "result.json"), "--out", str(out), "--no-verify"
    )
    assert code == 0, err
    assert "as recorded in the manifest (files not re-read)" in Page(out.read_text()).words
    # a result file away from its archive: the numbers, and the note that the archive is missing
    lone = tmp_path / "lone" / "result.json"
    lone.parent.mkdir()
    lone.write_text(json.dumps(lab.result()))
    code, stdout, err = _run(capsys, "report", str(lone), "--out", str(out))
    assert code == 0 and "the sweep archive was not found" in stdout
    assert "The sweep archive is not available" in Page(out.read_text()).words


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("job-without-config", "is a job id: give the station configuration (--config FILE)"),
        ("missing", "no such result file, archive directory or job"),
        ("failed", "the calibration failed, there is nothing to report"),
        ("not-a-result", "not an lfcal-result/1 calibration result"),
        ("no-result-in-dir", "has no result.json"),
        ("bad-config", "none.toml: file not found"),
    ],
)
def test_lfcal_report_bad_input_is_one_line_and_exit_2(
    lab: LabData, tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str, message: str
) -> None:
    args: list[str] = []
    if case == "job-without-config":
        args = ["7"]
    elif case == "missing":
        args = [str(tmp_path / "nothing.json")]
    elif case == "failed":
        partial: dict[str, Any] = copy.deepcopy(lab.result())
        for key in ("a_mm", "b_mm", "Q", "patch_size_px", "focus"):
            partial.pop(key)
        partial["error"] = "a board corner was found in only 2 of 12 frames"
        (tmp_path / "partial.json").write_text(json.dumps(partial))
        args = [str(tmp_path / "partial.json")]
    elif case == "not-a-result":
        args = [str(lab.sweep / "sweep.json")]
    elif case == "no-result-in-dir":
        args = [str(lab.sweep)]
    elif case == "bad-config":
        args = ["7", "--config", str(tmp_path / "none.toml")]
    out_html = tmp_path / "r.html"
    code, out, err = _run(capsys, "report", *args, "--out", str(out_html))
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("lfcal report: ") and message in err, err
    assert not out_html.exists()
