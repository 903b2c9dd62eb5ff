"""Plots of a calibration result (the ``--plots`` option and the web API)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .plots import plot_disparity, plot_focus_curve


def _column(frames: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if f.get(key) is None else f[key] for f in frames], dtype=float)


def focus_plot(result: dict[str, Any], out: str | Path | None = None) -> bytes:
    """La(u) (Eq. 8) with Ls, Lr, the edge widths with the blur model, and the focus
    plane found by the blur model beside the paper's argmin La; PNG bytes."""
    frames = result.get("frames", [])
    focus = result.get("focus") or {}
    curves = result.get("curves") or {}
    width_model = None
    if curves.get("edge_width_model_px"):
        width_model = (
            np.array(curves["object_distance_mm"], dtype=float),
            np.array(
                [np.nan if v is None else v for v in curves["edge_width_model_px"]], dtype=float
            ),
        )
    paper = focus.get("paper_argmin_La") or {}
    return plot_focus_curve(
        out,
        object_distance_mm=_column(frames, "object_distance_mm"),
        La_mm=_column(frames, "La_mm"),
        Ls_px=_column(frames, "Ls_px"),
        Lr_px=_column(frames, "Lr_px"),
        focus_mm=focus.get("object_distance_mm"),
        paper_focus_mm=paper.get("object_distance_mm"),
        edge_width_px=_column(frames, "edge_width_px"),
        width_model=width_model,
    )


def disparity_plot(result: dict[str, Any], out: str | Path | None = None) -> bytes:
    """Q(u) per frame with error bars and the global model ``Q = b/(L - v)``; PNG bytes."""
    frames = result.get("frames", [])
    curves = result.get("curves") or {}
    fit = None
    if curves.get("inv_Q_model"):
        u_model = np.array(curves["object_distance_mm"], dtype=float)
        inv_q = np.array([np.nan if v is None else v for v in curves["inv_Q_model"]], dtype=float)
        fit = (u_model, 1.0 / inv_q)
    return plot_disparity(
        out,
        object_distance_mm=_column(frames, "object_distance_mm"),
        Q=_column(frames, "Q"),
        Q_err=_column(frames, "Q_se"),
        fit_curve=fit,
        focus_mm=(result.get("focus") or {}).get("object_distance_mm"),
        main_focal_mm=((result.get("inputs") or {}).get("optics") or {}).get("main_focal_mm"),
    )


def write_plots(result: dict[str, Any], directory: Path) -> list[Path]:
    """Write ``focus.png`` and ``disparity.png`` into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = [directory / "focus.png", directory / "disparity.png"]
    focus_plot(result, paths[0])
    disparity_plot(result, paths[1])
    return paths
