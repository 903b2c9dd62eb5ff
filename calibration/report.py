"""Plots of a calibration result (the ``--plots`` option and the web API)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .plots import plot_disparity, plot_focus_curve, plot_residuals


def _column(frames: list[dict[str, Any]], key: str) -> np.ndarray:
    return np.array([np.nan if f.get(key) is None else f[key] for f in frames], dtype=float)


def focus_plot(result: dict[str, Any], out: str | Path | None = None) -> bytes:
    """La(u) (Eq. 8) with Ls, Lr, the edge spread of every frame with the defocus model
    that places the focus plane, beside the paper's argmin La; PNG bytes.

    Older results (before the defocus model) carry ``edge_width_model_px`` and
    per-frame ``edge_width_px`` instead: they are drawn the same way."""
    frames = result.get("frames", [])
    focus = result.get("focus") or {}
    curves = result.get("curves") or {}
    measured_key, model_key = "edge_spread_px", "edge_spread_model_px"
    if not curves.get(model_key):
        measured_key, model_key = "edge_width_px", "edge_width_model_px"
    width_model = None
    if curves.get(model_key):
        width_model = (
            np.array(curves["object_distance_mm"], dtype=float),
            np.array([np.nan if v is None else v for v in curves[model_key]], dtype=float),
        )
    if measured_key in curves:
        spread = dict(zip(curves["object_distance_mm"], curves[measured_key], strict=True))
        widths = np.array(
            [
                np.nan if spread.get(u) is None else spread[u]
                for u in _column(frames, "object_distance_mm")
            ]
        )
    else:
        widths = _column(frames, measured_key)
    paper = focus.get("paper_argmin_La") or {}
    return plot_focus_curve(
        out,
        object_distance_mm=_column(frames, "object_distance_mm"),
        La_mm=_column(frames, "La_mm"),
        Ls_px=_column(frames, "Ls_px"),
        Lr_px=_column(frames, "Lr_px"),
        focus_mm=focus.get("object_distance_mm"),
        paper_focus_mm=paper.get("object_distance_mm"),
        edge_width_px=widths,
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


def _model_at(result: dict[str, Any], key: str, u: np.ndarray, transform: Any = None) -> np.ndarray:
    """A ``curves`` model interpolated at the object distances ``u`` (NaN where absent)."""
    curves = result.get("curves") or {}
    values = curves.get(key)
    if not values or not curves.get("object_distance_mm"):
        return np.full(len(u), np.nan)
    cu = np.array(curves["object_distance_mm"], dtype=float)
    cv = np.array([np.nan if v is None else v for v in values], dtype=float)
    if transform is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            cv = transform(cv)
    ok = np.isfinite(cu) & np.isfinite(cv)
    if ok.sum() < 2:
        return np.full(len(u), np.nan)
    order = np.argsort(cu[ok])
    out = np.interp(u, cu[ok][order], cv[ok][order], left=np.nan, right=np.nan)
    return np.asarray(out, dtype=float)


def residual_plot(result: dict[str, Any], out: str | Path | None = None) -> bytes:
    """Per-frame residuals of Q against the global model and of the edge widths against
    the blur model (``curves``), with the focus plane; PNG bytes."""
    frames = result.get("frames", [])
    u = _column(frames, "object_distance_mm")
    q_model = _model_at(result, "inv_Q_model", u, lambda v: 1.0 / v)
    w_model = _model_at(result, "edge_width_model_px", u)
    return plot_residuals(
        out,
        object_distance_mm=u,
        Q_residual=_column(frames, "Q") - q_model,
        Q_err=_column(frames, "Q_se"),
        edge_width_residual_px=_column(frames, "edge_width_px") - w_model,
        focus_mm=(result.get("focus") or {}).get("object_distance_mm"),
    )


def write_plots(result: dict[str, Any], directory: Path) -> list[Path]:
    """Write ``focus.png`` and ``disparity.png`` into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    paths = [directory / "focus.png", directory / "disparity.png"]
    focus_plot(result, paths[0])
    disparity_plot(result, paths[1])
    return paths
