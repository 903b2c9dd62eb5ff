"""PNG plots of a calibration: focus curve, disparity, residuals, rendered images.

Every function takes ``out`` (a file path, or ``None``) first and returns the
PNG bytes, so the same call serves the command line (write a file) and the
web API (send the bytes). Figures are drawn with matplotlib's object API on an
Agg canvas (``matplotlib.figure.Figure`` + ``FigureCanvasAgg``): no pyplot, no
``matplotlib.use``, no global state. Plots have exactly ``size_px`` pixels.

Units: object distances ``u`` in mm, corner sizes ``La`` in mm, ``Ls``/``Lr``
in pixels, ``Q`` dimensionless. Values may be ``None`` or NaN (a frame whose
corner was not found): such points are left out and counted in the legend.
"""

from __future__ import annotations

import io
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import ArrayLike, NDArray

Out = str | Path | None
FitCurve = Callable[[NDArray[np.float64]], ArrayLike] | tuple[ArrayLike, ArrayLike]
"""A model curve: a function of ``u`` (mm, array) or sampled points ``(u, value)``."""

DEFAULT_SIZE_PX = (900, 600)
_DPI = 100


def _values(x: ArrayLike | None, n: int | None = None) -> NDArray[np.float64]:
    """Float array with ``None`` as NaN; all-NaN of length ``n`` when ``x`` is ``None``."""
    if x is None:
        return np.full(0 if n is None else n, np.nan)
    arr = np.array([np.nan if v is None else v for v in np.ravel(np.asarray(x, dtype=object))])
    return arr.astype(np.float64)


def _same_length(names: Sequence[str], arrays: Sequence[NDArray[np.float64]]) -> None:
    lengths = {len(a) for a in arrays}
    if len(lengths) > 1:
        sizes = ", ".join(f"{n}={len(a)}" for n, a in zip(names, arrays, strict=True))
        raise ValueError(f"inputs must have the same length: {sizes}")


def _figure(size_px: tuple[int, int], rows: int) -> tuple[Figure, list[Axes]]:
    w, h = size_px
    if w < 100 or h < 100:
        raise ValueError(f"plot size {w}x{h} px is too small (minimum 100x100)")
    fig = Figure(figsize=(w / _DPI, h / _DPI), dpi=_DPI, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 1, sharex=False, squeeze=False)[:, 0]
    return fig, list(axes)


def _finish(fig: Figure, out: Out) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=_DPI)
    data = buf.getvalue()
    if out is not None:
        Path(out).write_bytes(data)
    return data


def _curve(fit_curve: FitCurve | None, u: NDArray[np.float64]) -> tuple[NDArray, NDArray] | None:
    """Model samples ``(u, value)``: a callable is evaluated on 200 points spanning ``u``."""
    if fit_curve is None:
        return None
    if callable(fit_curve):
        finite = u[np.isfinite(u)]
        if finite.size == 0:
            return None
        lo, hi = float(finite.min()), float(finite.max())
        if hi - lo < 1e-9:
            lo, hi = lo - 1.0, hi + 1.0
        grid = np.linspace(lo, hi, 200)
        return grid, _values(fit_curve(grid))
    cu, cv = fit_curve
    cu_a, cv_a = _values(cu), _values(cv)
    _same_length(("fit u", "fit value"), (cu_a, cv_a))
    return cu_a, cv_a


def _no_data(ax: Axes) -> None:
    ax.text(0.5, 0.5, "no valid points", ha="center", va="center", transform=ax.transAxes)


def _legend(ax: Axes) -> None:
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize="small")


def _mark_focus(ax: Axes, focus_mm: float | None, name: str = "focus u0") -> None:
    if focus_mm is not None and np.isfinite(focus_mm):
        label = f"{name} = {focus_mm:.2f} mm"
        ax.axvline(focus_mm, color="tab:red", ls="--", lw=1.2, label=label)


def _points(ax: Axes, u: NDArray, y: NDArray, label: str, **kw: object) -> int:
    """Plot the finite points; returns how many were missing."""
    ok = np.isfinite(u) & np.isfinite(y)
    missing = int((~ok).sum())
    if missing:
        label = f"{label} ({missing} missing)"
    if ok.any():
        ax.plot(u[ok], y[ok], ls="none", label=label, **kw)  # type: ignore[arg-type]
    return missing


def plot_focus_curve(
    out: Out,
    *,
    object_distance_mm: ArrayLike,
    La_mm: ArrayLike,
    Ls_px: ArrayLike | None = None,
    Lr_px: ArrayLike | None = None,
    fit_curve: FitCurve | None = None,
    focus_mm: float | None = None,
    paper_focus_mm: float | None = None,
    edge_width_px: ArrayLike | None = None,
    width_model: FitCurve | None = None,
    title: str = "Focus-plane confirmation: corner size La(u)",
    size_px: tuple[int, int] | None = None,
) -> bytes:
    """La(u) (ESIF Eq. 8) with the focus plane; Ls, Lr below; edge widths and blur model last.

    Top panel: ``La`` (mm) against ``u`` (mm), the model ``fit_curve`` as a line,
    the focus plane ``focus_mm`` as a dashed vertical line and the paper's
    ``argmin La`` (``paper_focus_mm``) as a dotted one. Middle panel: the
    standard and reference corner sizes ``Ls``, ``Lr`` (px). With
    ``edge_width_px`` a third panel shows the edge spread per frame (RMS width
    of its line-spread function, px) and the whole-sweep defocus model
    ``width_model`` that places the focus plane.
    Default size 900×600 px (900×850 with the third panel). Writes ``out`` when
    it is a path; returns the PNG bytes.
    """
    u = _values(object_distance_mm)
    la = _values(La_mm)
    ls = _values(Ls_px, len(u)) if Ls_px is not None else np.full(len(u), np.nan)
    lr = _values(Lr_px, len(u)) if Lr_px is not None else np.full(len(u), np.nan)
    widths = _values(edge_width_px, len(u)) if edge_width_px is not None else None
    _same_length(("u", "La", "Ls", "Lr"), (u, la, ls, lr))
    if widths is not None:
        _same_length(("u", "edge width"), (u, widths))
    if size_px is None:
        size_px = DEFAULT_SIZE_PX if widths is None else (DEFAULT_SIZE_PX[0], 850)
    fig, axes = _figure(size_px, 2 if widths is None else 3)
    ax, ax2 = axes[0], axes[1]
    _points(ax, u, la, "La (measured)", marker="o", ms=4, color="tab:blue")
    curve = _curve(fit_curve, u)
    if curve is not None:
        ax.plot(curve[0], curve[1], color="tab:orange", lw=1.5, label="model")
    _mark_focus(ax, focus_mm)
    if paper_focus_mm is not None and np.isfinite(paper_focus_mm):
        ax.axvline(
            paper_focus_mm,
            color="tab:gray",
            ls=":",
            lw=1.2,
            label=f"paper's argmin La = {paper_focus_mm:.2f} mm",
        )
    if not np.any(np.isfinite(u) & np.isfinite(la)):
        _no_data(ax)
    ax.set_ylabel("La (mm)")
    ax.set_title(title)
    _legend(ax)
    ax.grid(True, alpha=0.3)
    n_ls = _points(ax2, u, ls, "Ls standard", marker="s", ms=3, color="tab:green")
    n_lr = _points(ax2, u, lr, "Lr reference", marker="^", ms=3, color="tab:purple")
    _mark_focus(ax2, focus_mm)
    if n_ls == len(u) and n_lr == len(u):
        _no_data(ax2)
    ax2.set_ylabel("corner size (px)")
    _legend(ax2)
    ax2.grid(True, alpha=0.3)
    last = ax2
    if widths is not None:
        ax3 = last = axes[2]
        missing = _points(ax3, u, widths, "edge spread", marker="o", ms=3, color="tab:cyan")
        model = _curve(width_model, u)
        if model is not None:
            ax3.plot(model[0], model[1], color="tab:orange", lw=1.5, label="defocus model")
        _mark_focus(ax3, focus_mm)
        if missing == len(u):
            _no_data(ax3)
        ax3.set_ylabel("edge spread RMS (px)")
        _legend(ax3)
        ax3.grid(True, alpha=0.3)
    last.set_xlabel("object distance u (mm)")
    return _finish(fig, out)


def plot_disparity(
    out: Out,
    *,
    object_distance_mm: ArrayLike,
    Q: ArrayLike,
    Q_err: ArrayLike | None = None,
    fit_curve: FitCurve | None = None,
    focus_mm: float | None = None,
    main_focal_mm: float | None = None,
    title: str = "Disparity ratio Q(u) = b / a(u)",
    size_px: tuple[int, int] = DEFAULT_SIZE_PX,
) -> bytes:
    """Q(u) per frame with error bars and the global model; 1/Q below.

    Top panel: ``Q`` against ``u`` (mm) with ``Q_err`` (1σ; NaN or ``None``:
    no bar) and the model ``fit_curve`` (``Q`` as a function of ``u``). Bottom
    panel: ``1/Q``, which the model makes linear in ``v(u) = uF/(u - F)``: with
    ``main_focal_mm`` (F) it is drawn against ``v`` (mm), else against ``u``.
    Writes ``out`` when it is a path; returns the PNG bytes.
    """
    u = _values(object_distance_mm)
    q = _values(Q)
    qe = _values(Q_err, len(u)) if Q_err is not None else np.full(len(u), np.nan)
    _same_length(("u", "Q", "Q_err"), (u, q, qe))
    fig, (ax, ax2) = _figure(size_px, 2)
    ok = np.isfinite(u) & np.isfinite(q)
    missing = int((~ok).sum())
    label = "Q per frame" + (f" ({missing} missing)" if missing else "")
    if ok.any():
        err = np.where(np.isfinite(qe[ok]) & (qe[ok] >= 0), qe[ok], 0.0)
        ax.errorbar(u[ok], q[ok], yerr=err, fmt="o", ms=3, capsize=2, label=label)
    else:
        _no_data(ax)
    curve = _curve(fit_curve, u)
    if curve is not None:
        ax.plot(curve[0], curve[1], color="tab:orange", lw=1.5, label="global 1/Q-vs-v model")
    _mark_focus(ax, focus_mm)
    ax.set_xlabel("object distance u (mm)")
    ax.set_ylabel("Q")
    ax.set_title(title)
    _legend(ax)
    ax.grid(True, alpha=0.3)

    def to_x(uu: NDArray[np.float64]) -> NDArray[np.float64]:
        if main_focal_mm is None:
            return uu
        with np.errstate(divide="ignore", invalid="ignore"):
            return uu * main_focal_mm / (uu - main_focal_mm)

    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / q
    _points(ax2, to_x(u), inv, "1/Q per frame", marker="o", ms=3, color="tab:blue")
    if curve is not None:
        with np.errstate(divide="ignore", invalid="ignore"):
            ax2.plot(to_x(curve[0]), 1.0 / curve[1], color="tab:orange", lw=1.5, label="model")
    if not ok.any():
        _no_data(ax2)
    if focus_mm is not None and np.isfinite(focus_mm):
        name = "focus v0" if main_focal_mm else "focus u0"
        _mark_focus(ax2, float(to_x(np.array([focus_mm]))[0]), name)
    ax2.set_xlabel("main-image distance v (mm)" if main_focal_mm else "object distance u (mm)")
    ax2.set_ylabel("1/Q = a/b")
    _legend(ax2)
    ax2.grid(True, alpha=0.3)
    return _finish(fig, out)


def plot_residuals(
    out: Out,
    *,
    object_distance_mm: ArrayLike,
    Q_residual: ArrayLike,
    Q_err: ArrayLike | None = None,
    edge_width_residual_px: ArrayLike | None = None,
    focus_mm: float | None = None,
    title: str = "Residuals of the whole-sweep models",
    size_px: tuple[int, int] = DEFAULT_SIZE_PX,
) -> bytes:
    """Per-frame residuals: ``Q − Q_model(u)`` with error bars (top) and the edge width
    minus the blur model (px, bottom), against the object distance ``u`` (mm).

    A model that fits leaves residuals scattered around zero within their error
    bars; a trend means the model (or a prior such as the rail zero) is off.
    Writes ``out`` when it is a path; returns the PNG bytes.
    """
    u = _values(object_distance_mm)
    dq = _values(Q_residual)
    qe = _values(Q_err, len(u)) if Q_err is not None else np.full(len(u), np.nan)
    dw = (
        _values(edge_width_residual_px, len(u))
        if edge_width_residual_px is not None
        else np.full(len(u), np.nan)
    )
    _same_length(("u", "Q residual", "Q_err", "edge width residual"), (u, dq, qe, dw))
    fig, (ax, ax2) = _figure(size_px, 2)
    ok = np.isfinite(u) & np.isfinite(dq)
    if ok.any():
        err = np.where(np.isfinite(qe[ok]) & (qe[ok] >= 0), qe[ok], 0.0)
        missing = int((~ok).sum())
        label = "Q − global model" + (f" ({missing} missing)" if missing else "")
        ax.errorbar(u[ok], dq[ok], yerr=err, fmt="o", ms=3, capsize=2, label=label)
    else:
        _no_data(ax)
    ax.axhline(0.0, color="tab:gray", lw=1)
    _mark_focus(ax, focus_mm)
    ax.set_ylabel("Q residual")
    ax.set_title(title)
    _legend(ax)
    ax.grid(True, alpha=0.3)
    if _points(ax2, u, dw, "edge width − blur model", marker="s", ms=3, color="tab:cyan") == len(u):
        _no_data(ax2)
    ax2.axhline(0.0, color="tab:gray", lw=1)
    _mark_focus(ax2, focus_mm)
    ax2.set_xlabel("object distance u (mm)")
    ax2.set_ylabel("edge width residual (px)")
    _legend(ax2)
    ax2.grid(True, alpha=0.3)
    return _finish(fig, out)


def stretch_to_uint8(
    image: ArrayLike, *, low_pct: float = 0.5, high_pct: float = 99.5
) -> NDArray[np.uint8]:
    """Linear stretch of a grey image to 0..255 between two percentiles of its finite values.

    NaN and ±inf become 0; a constant image becomes 0.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"expected a 2-D grey image, got shape {img.shape}")
    if not 0 <= low_pct < high_pct <= 100:
        raise ValueError("percentiles need 0 <= low_pct < high_pct <= 100")
    finite = np.isfinite(img)
    out = np.zeros(img.shape, dtype=np.uint8)
    if not finite.any():
        return out
    lo, hi = np.percentile(img[finite], [low_pct, high_pct])
    if not hi > lo:
        return out
    scaled = np.clip((img[finite] - lo) * (255.0 / (hi - lo)), 0.0, 255.0)
    out[finite] = np.rint(scaled).astype(np.uint8)
    return out


def render_png(
    out: Out, image: ArrayLike, *, low_pct: float = 0.5, high_pct: float = 99.5
) -> bytes:
    """Save a (rendered) grey image as an 8-bit PNG with a percentile stretch; returns the bytes.

    The PNG has the image's size (one pixel per array element); see
    :func:`stretch_to_uint8` for the stretch and NaN handling.
    """
    ok, buf = cv2.imencode(".png", stretch_to_uint8(image, low_pct=low_pct, high_pct=high_pct))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    data = buf.tobytes()
    if out is not None:
        Path(out).write_bytes(data)
    return data
