"""PNG plots: valid files of the requested size, missing values, single points, the image helper."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from calibration.plots import (
    DEFAULT_SIZE_PX,
    plot_disparity,
    plot_focus_curve,
    render_png,
    stretch_to_uint8,
)
from calibration.report import focus_plot

F, L, B = 35.0, 54.6226, 3.0


def _png_size(data: bytes) -> tuple[int, int]:
    """Width, height from the PNG signature and IHDR chunk."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert data[12:16] == b"IHDR"
    w, h = struct.unpack(">II", data[16:24])
    return w, h


def _decode(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None
    return img


def _q_model(u: np.ndarray) -> np.ndarray:
    return B / (L - u * F / (u - F))


def _sweep() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    u = np.arange(250.0, 350.0)
    la = 0.05 + 1e-5 * (u - 300.0) ** 2
    ls = la / 0.02
    lr = ls + 5.0
    return u, la, ls, lr


def test_focus_curve_writes_a_png_of_the_requested_size(tmp_path: Path) -> None:
    u, la, ls, lr = _sweep()
    out = tmp_path / "focus.png"
    data = plot_focus_curve(
        out,
        object_distance_mm=u,
        La_mm=la,
        Ls_px=ls,
        Lr_px=lr,
        fit_curve=lambda x: 0.05 + 1e-5 * (x - 300.0) ** 2,
        focus_mm=300.2,
        size_px=(640, 480),
    )
    assert out.read_bytes() == data
    assert _png_size(data) == (640, 480)
    img = _decode(data)
    assert img.shape[:2] == (480, 640) and img.std() > 10  # something was drawn
    assert _png_size(plot_focus_curve(None, object_distance_mm=u, La_mm=la)) == DEFAULT_SIZE_PX


def test_disparity_plot_with_errors_model_and_v_axis(tmp_path: Path) -> None:
    u = np.arange(250.0, 350.0)
    q = _q_model(u)
    data = plot_disparity(
        str(tmp_path / "q.png"),
        object_distance_mm=u,
        Q=q,
        Q_err=np.full(u.size, 1e-3),
        fit_curve=(u, q),
        focus_mm=300.0,
        main_focal_mm=F,
    )
    assert (tmp_path / "q.png").read_bytes() == data
    assert _png_size(data) == DEFAULT_SIZE_PX
    # the model and the points change the picture
    bare = plot_disparity(None, object_distance_mm=u, Q=q)
    assert bare != data


def test_missing_values_and_single_points_are_drawn(tmp_path: Path) -> None:
    u, la, ls, lr = _sweep()
    la[[3, 10, 50]] = np.nan  # frames where a corner was not found
    ls_list: list[float | None] = list(ls)
    ls_list[7] = None
    q = _q_model(u)
    q[[0, 5]] = np.nan
    qe: list[float | None] = [1e-3] * u.size
    qe[9] = None
    full = plot_focus_curve(None, object_distance_mm=u, La_mm=la, Ls_px=ls_list, Lr_px=lr)
    assert _png_size(full) == DEFAULT_SIZE_PX
    assert _png_size(plot_disparity(None, object_distance_mm=u, Q=q, Q_err=qe)) == DEFAULT_SIZE_PX
    # one frame only, with or without a fit; all values missing
    one = plot_focus_curve(
        None, object_distance_mm=[300.0], La_mm=[0.05], fit_curve=lambda x: 0.05 + 0 * x
    )
    assert _png_size(one) == DEFAULT_SIZE_PX
    one_q = plot_disparity(
        None, object_distance_mm=[300.0], Q=[0.2], Q_err=[None], focus_mm=300.0, main_focal_mm=F
    )
    assert _png_size(one_q) == DEFAULT_SIZE_PX
    none = plot_focus_curve(None, object_distance_mm=[300.0, 301.0], La_mm=[None, np.nan])
    assert _png_size(none) == DEFAULT_SIZE_PX and none != one
    assert _png_size(plot_disparity(None, object_distance_mm=[], Q=[])) == DEFAULT_SIZE_PX


def test_mismatched_lengths_and_tiny_sizes_are_rejected() -> None:
    with pytest.raises(ValueError, match="same length"):
        plot_focus_curve(None, object_distance_mm=[1.0, 2.0], La_mm=[1.0])
    with pytest.raises(ValueError, match="same length"):
        plot_disparity(None, object_distance_mm=[1.0, 2.0], Q=[0.2, 0.2], Q_err=[0.1])
    with pytest.raises(ValueError, match="too small"):
        plot_focus_curve(None, object_distance_mm=[1.0], La_mm=[1.0], size_px=(50, 50))


def test_render_png_stretches_between_percentiles(tmp_path: Path) -> None:
    img = np.tile(np.linspace(0.0, 1000.0, 201, dtype=np.float32), (30, 1))
    img[0, 0] = np.nan
    img[1, 1] = np.inf
    out = tmp_path / "render.png"
    data = render_png(out, img, low_pct=10.0, high_pct=90.0)
    assert out.read_bytes() == data
    assert _png_size(data) == (201, 30)
    back = _decode(data)
    assert back.dtype == np.uint8 and back.shape == (30, 201)
    np.testing.assert_array_equal(back, stretch_to_uint8(img, low_pct=10.0, high_pct=90.0))
    # 10th and 90th percentiles of a linear ramp: columns 20 and 180
    row = back[5].astype(int)
    assert row[:20].max() == 0 and row[181:].min() == 255
    assert row[100] == pytest.approx(127.5, abs=1)
    assert back[0, 0] == 0 and back[1, 1] == 0  # NaN and inf
    assert not stretch_to_uint8(np.full((4, 4), 7.0)).any()  # constant image
    assert not stretch_to_uint8(np.full((4, 4), np.nan)).any()


def test_focus_plot_of_a_result_shows_the_edge_widths_and_both_focus_estimates() -> None:
    u = np.arange(250.0, 350.0)
    la = 0.05 + 1e-5 * (u - 285.0) ** 2
    width = np.sqrt(0.16 + 1e-4 * (u - 300.0) ** 2)
    frames = [
        {"object_distance_mm": x, "La_mm": y, "Ls_px": 1.0, "Lr_px": 1.4, "edge_width_px": w}
        for x, y, w in zip(u, la, width, strict=True)
    ]
    result = {
        "frames": frames,
        "focus": {"object_distance_mm": 300.0, "paper_argmin_La": {"object_distance_mm": 285.0}},
        "curves": {"object_distance_mm": list(u), "edge_width_model_px": list(width)},
    }
    data = focus_plot(result)
    assert _png_size(data) == (DEFAULT_SIZE_PX[0], 850)  # a third panel for the edge widths
    img = _decode(data)
    # the lowest panel is not empty: the edge widths and the model are drawn in colour
    bottom = img[600:820, 80:880].astype(int)
    assert (np.abs(bottom[..., 0] - bottom[..., 2]) > 60).sum() > 200
    without = dict(result, curves={})
    assert focus_plot(without) != data
