"""The printed summary of a calibration says which optics located the focus plane."""

from __future__ import annotations

from station.summary_table import summary_table


def _result(diffraction_px: float) -> dict:
    model = {
        "Q0": 0.2,
        "Q0_se": 1e-4,
        "frames": 50,
        "max_defocus_px": 1.6,
        "static_blur_rms_px": 0.5,
        "diffraction_px": diffraction_px,
    }
    return {"focus": {"defocus_model": model}, "corners_found": {}}


def _focus_line(text: str) -> str:
    return next(line for line in text.splitlines() if line.startswith("focus: Q0"))


def test_the_focus_line_names_wave_optics_and_the_pattern_when_fitted() -> None:
    line = _focus_line(summary_table(_result(2.6234)))
    assert line.endswith("static blur RMS 0.50 px, wave optics: diffraction pattern 2.62 px)")


def test_the_focus_line_is_plain_when_geometric_optics_describes_the_edges() -> None:
    for result in (_result(0.0), {"focus": {"defocus_model": {"Q0": 0.2}}, "corners_found": {}}):
        assert "wave optics" not in _focus_line(summary_table(result))
