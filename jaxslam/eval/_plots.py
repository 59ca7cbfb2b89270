"""PNG figures of trajectories, APE along the path and residual histograms.

Figures are drawn on :class:`matplotlib.figure.Figure` objects with the Agg canvas, never
through pyplot: nothing is shown, no global backend is switched, and nothing leaks between
calls. Each function writes one PNG and returns its path.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ._align import Track, positions_of
from ._metrics import ApeResult, accumulated_distances


def _figure(width: float, height: float, rows: int, cols: int, **kw: Any):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False, **kw)
    return fig, axes


def _save(fig: Any, path_png: str | Path, dpi: int = 110) -> Path:
    path = Path(path_png)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path


def plot_trajectory(
    path_png: str | Path,
    est: Track,
    gt: Track | None = None,
    title: str = "trajectory",
    side: str = "distance",
    labels: tuple[str, str] = ("estimate", "ground truth"),
) -> Path:
    """Top view (x–y, equal axes) and side view of ``est`` (and ``gt``), positions in m.

    ``side="distance"``: height z over the distance travelled along each path (suits long
    tunnels); ``side="xz"``: z over x. Pass the aligned estimate to overlay it on ``gt``.
    """
    if side not in ("distance", "xz"):
        raise ValueError(f"side must be 'distance' or 'xz', got {side!r}")
    fig, ax = _figure(10, 7.5, 2, 1, gridspec_kw={"height_ratios": [1.4, 1]})
    top, low = ax[0, 0], ax[1, 0]
    tracks = [(gt, labels[1], "k-", 1.6), (est, labels[0], "C0-", 1.1)]
    for track, label, style, lw in tracks:
        if track is None:
            continue
        p = positions_of(track)
        top.plot(p[:, 0], p[:, 1], style, lw=lw, label=label)
        top.plot(p[:1, 0], p[:1, 1], "o", color=style[:-1], ms=4)
        x = accumulated_distances(p) if side == "distance" else p[:, 0]
        low.plot(x, p[:, 2], style, lw=lw, label=label)
    top.set_aspect("equal", adjustable="datalim")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title(f"{title}: top view (o: start)")
    top.grid(alpha=0.3)
    top.legend(loc="best", fontsize=8)
    low.set_xlabel("distance along path [m]" if side == "distance" else "x [m]")
    low.set_ylabel("z [m]")
    low.set_title("side view")
    low.grid(alpha=0.3)
    return _save(fig, path_png)


def plot_ape_over_distance(path_png: str | Path, ape_result: ApeResult, title: str | None = None) -> Path:
    """Per-pose APE (m) over the distance travelled along the reference, with the rmse,
    mean and median as horizontal lines."""
    fig, ax = _figure(10, 4, 1, 1)
    a = ax[0, 0]
    s = ape_result.stats
    a.plot(ape_result.distances, ape_result.errors, "C0-", lw=1.0, label="APE")
    for key, style in (("rmse", "C3--"), ("mean", "C1:"), ("median", "C2-.")):
        a.axhline(s[key], color=style[:2], ls=style[2:], lw=1.0, label=f"{key} {s[key]:.4f} m")
    a.set_xlabel("distance along reference [m]")
    a.set_ylabel("APE [m]")
    a.set_title(title or f"APE after {ape_result.align} alignment ({ape_result.matched} poses)")
    a.set_ylim(bottom=0)
    a.grid(alpha=0.3)
    a.legend(loc="best", fontsize=8)
    return _save(fig, path_png)


def plot_residual_histograms(
    path_png: str | Path,
    residuals: Mapping[str, np.ndarray],
    bins: int = 60,
    unit: str = "",
    title: str | None = None,
    cols: int = 3,
) -> Path:
    """One histogram panel per residual kind (e.g. factor type), log-scaled counts; each
    panel's title holds the kind, the sample count and the RMS.

    Every array is flattened: each residual component is one sample (pass norms for
    per-measurement magnitudes, e.g. reprojection error in px). Non-finite entries are
    dropped and counted in the title.
    """
    if not residuals:
        raise ValueError("residuals is empty: give at least one name -> array")
    n = len(residuals)
    cols = max(1, min(cols, n))
    rows = -(-n // cols)
    fig, ax = _figure(4.2 * cols, 3.2 * rows, rows, cols)
    flat = list(ax.reshape(-1))
    for a, (name, values) in zip(flat, residuals.items()):
        v = np.asarray(values, dtype=np.float64).reshape(-1)
        finite = v[np.isfinite(v)]
        dropped = v.size - finite.size
        rms = float(np.sqrt(np.mean(finite * finite))) if finite.size else float("nan")
        if finite.size:
            a.hist(finite, bins=bins, color="C0", alpha=0.85, log=True)
        head = f"{name}: n={finite.size}, RMS {rms:.4g}{' ' + unit if unit else ''}"
        a.set_title(head + (f" ({dropped} non-finite dropped)" if dropped else ""), fontsize=9)
        a.set_xlabel(f"residual{' [' + unit + ']' if unit else ''}")
        a.set_ylabel("count (log)")
        a.grid(alpha=0.3)
    for a in flat[n:]:
        a.set_visible(False)
    if title:
        fig.suptitle(title)
    return _save(fig, path_png)
