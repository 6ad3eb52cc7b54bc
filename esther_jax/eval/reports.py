"""Tidy result records, paper-style tables (Markdown, CSV) and figures (PNG)."""

import csv
import dataclasses
import pathlib

import numpy as np
from jaxtyping import Array, Bool, Float, Shaped

from ..figures import figure, save_figure
from ..files import atomic_output
from ..metrics import METRIC_LABELS, Bootstrap, DepthScatter

PAPER_COLUMNS = ("p_mpjpe", "pa_mpjpe", "wrist", "jitter")


@dataclasses.dataclass(frozen=True)
class Record:
    """One number of a results table: a metric of a method under a condition."""

    method: str
    condition: str
    metric: str
    value: float
    std: float | None = None
    ci_low: float | None = None
    ci_high: float | None = None
    unit: str = ""
    num_clips: int = 0

    @classmethod
    def from_bootstrap(cls, method: str, condition: str, metric: str, b: Bootstrap | None, scale: float = 1.0) -> "Record":
        """A record from bootstrap statistics; `scale` converts units (1000 for m -> mm)."""
        unit = METRIC_LABELS.get(metric, (metric, ""))[1]
        if b is None:
            return cls(method, condition, metric, float("nan"), unit=unit)
        spread = [None if not np.isfinite(v) else v * scale for v in (b.std, b.ci_low, b.ci_high)]  # one clip: unknown
        return cls(method, condition, metric, b.mean * scale, *spread, unit, b.num_clips)


def write_csv(records: list[Record], path: str | pathlib.Path) -> pathlib.Path:
    path = pathlib.Path(path)
    with atomic_output(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=[field.name for field in dataclasses.fields(Record)])
        writer.writeheader()
        for r in records:
            writer.writerow(dataclasses.asdict(r))
    return path


def markdown_table(records: list[Record], columns: tuple[str, ...] = PAPER_COLUMNS, condition: str | None = None) -> str:
    """Method x metric table, cells `mean +- std` (bootstrap), as in the paper's tables."""
    rows = [r for r in records if condition is None or r.condition == condition]
    methods = list(dict.fromkeys(r.method for r in rows))
    cell = {(r.method, r.metric): r for r in rows}
    header = "| Method | " + " | ".join(f"{METRIC_LABELS.get(c, (c, ''))[0]} ({METRIC_LABELS.get(c, ('', ''))[1]})" for c in columns) + " |"
    lines = [header, "|---" * (len(columns) + 1) + "|"]
    for method in methods:
        cells = []
        for c in columns:
            r = cell.get((method, c))
            if r is None or not np.isfinite(r.value):
                cells.append("no data")
            elif r.std is None:
                cells.append(f"{r.value:.2f} ± n/a")  # one clip: no interval
            else:
                cells.append(f"{r.value:.2f} ± {r.std:.2f}")
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot_depth_scatter(z_gt: np.ndarray, z_pred: np.ndarray, scatter: DepthScatter, path: str | pathlib.Path, title: str = "") -> pathlib.Path:
    """Predicted vs true wrist depth with the linear fit, as the paper's figure 8."""
    return plot_depth_scatters([(title, z_gt, z_pred, scatter)], path)


def plot_depth_scatters(panels: list[tuple[str, np.ndarray, np.ndarray, DepthScatter]], path: str | pathlib.Path) -> pathlib.Path:
    """Figure 8 side by side: one panel (title, true depth, predicted depth (m), its
    `metrics.depth_scatter`) per model, on shared axes."""
    fig, axes = figure(1, len(panels), figsize=(4.2 * len(panels), 4.0), squeeze=False)
    everything = np.concatenate([np.concatenate([np.ravel(z_gt), np.ravel(z_pred)]) for _, z_gt, z_pred, _ in panels])
    everything = everything[np.isfinite(everything)]
    lo, hi = (float(everything.min()), float(everything.max())) if everything.size else (0.0, 1.0)
    pad = 0.05 * max(hi - lo, 1e-3)
    for ax, (title, z_gt, z_pred, scatter) in zip(axes[0], panels):
        ax.set_xlim(lo - pad, hi + pad)
        ax.set_ylim(lo - pad, hi + pad)
        ax.set_aspect("equal", adjustable="box")
        if not np.isfinite(np.asarray(z_gt, float)).any():  # nothing scored (e.g. a prediction that emits no frame)
            ax.set_title(f"{title}\nno frame scored", fontsize=9)
            continue
        ax.scatter(z_gt, z_pred, s=3, alpha=0.35, color="#2b6cb0", linewidths=0)
        xs = np.linspace(float(np.nanmin(z_gt)), float(np.nanmax(z_gt)), 2)
        ax.plot(xs, xs, "k--", lw=0.8, label="ideal")
        ax.plot(xs, float(scatter.slope) * xs + float(scatter.intercept), color="#c53030", lw=1.2, label="linear fit")
        ax.set_xlabel("true wrist depth (m)")
        ax.set_title(
            f"{title}\ncorr {float(scatter.correlation):.2f}, random {float(scatter.random_mm):.1f} mm, "
            f"systematic {float(scatter.systematic_mm):.1f} mm",
            fontsize=9,
        )
        ax.legend(fontsize=8, loc="upper left")
    axes[0][0].set_ylabel("predicted wrist depth (m)")
    return save_figure(fig, path)


def plot_metric_vs_condition(
    records: list[Record], metric: str, conditions: list[str], path: str | pathlib.Path, xlabel: str = "frames dropped of 16"
) -> pathlib.Path:
    """One line per method of a metric across ordered conditions (e.g. error vs dropped
    frames), with bootstrap 95% intervals as error bars."""
    crowded = sum(len(c) for c in conditions) > 40  # long names (e.g. table 5's rows) would overlap on the axis
    fig, ax = figure(figsize=(max(4.6, 0.55 * len(conditions)), 4.6 if crowded else 3.4))
    for method in dict.fromkeys(r.method for r in records):
        pts = [next((r for r in records if r.method == method and r.metric == metric and r.condition == c), None) for c in conditions]
        y = np.asarray([p.value if p else np.nan for p in pts])
        lo = np.asarray([p.value - p.ci_low if p and p.ci_low is not None else 0.0 for p in pts])
        hi = np.asarray([p.ci_high - p.value if p and p.ci_high is not None else 0.0 for p in pts])
        ax.errorbar(range(len(conditions)), y, yerr=[lo, hi], marker="o", capsize=3, label=method)
    ax.set_xticks(range(len(conditions)), conditions, rotation=40 if crowded else 0, ha="right" if crowded else "center", fontsize=8 if crowded else None)
    label, unit = METRIC_LABELS.get(metric, (metric, ""))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(f"{label} ({unit})")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_pck(thresholds_m: np.ndarray, curve: np.ndarray, path: str | pathlib.Path, label: str = "") -> pathlib.Path:
    fig, ax = figure(figsize=(4.2, 3.2))
    ax.plot(np.asarray(thresholds_m) * 1000, curve, label=label or None)
    ax.set_xlabel("threshold (mm)")
    ax.set_ylabel("PCK")
    ax.set_ylim(0, 1)
    if label:
        ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_intervals(
    names: list[str],
    lower: list[float],
    upper: list[float],
    path: str | pathlib.Path,
    *,
    outer: list[float] | None = None,
    points: dict[str, list[float]] | None = None,
    ylabel: str = "",
    title: str = "",
) -> pathlib.Path:
    """One interval per category (a bar from `lower` to `upper`, a dashed line on to
    `outer` where given) and, per series of `points`, one marker per category: e.g.
    measured errors against the band they should fall in. NaN values are left out."""
    fig, ax = figure(figsize=(max(3.6, 1.1 * len(names) + 1.5), 3.6))
    x = np.arange(len(names), dtype=float)
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    ax.bar(x, hi - lo, bottom=lo, width=0.5, color="#cbd5e0", edgecolor="#718096", label="interval")
    if outer is not None:
        ax.vlines(x, hi, np.asarray(outer, float), colors="#718096", linestyles="--", lw=1.0, label="outer limit")
    series = list((points or {}).items())
    for i, (label, values) in enumerate(series):
        offset = (i - (len(series) - 1) / 2) * 0.12
        ax.scatter(x + offset, np.asarray(values, float), zorder=3, s=24, marker="os^Dv"[i % 5], label=label)
    ax.set_xticks(x, names, rotation=30 if len(names) > 3 else 0, ha="right" if len(names) > 3 else "center", fontsize=8)
    values = np.concatenate([lo, hi] + [np.asarray(v, float) for _, v in series])
    if np.all(values[np.isfinite(values)] >= 0):
        ax.set_ylim(bottom=0.0)  # magnitudes: show their distance from zero
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7)
    return save_figure(fig, path)


def plot_attention_shares(
    shares: dict[str, Float[np.ndarray | Array, "layers"]],
    chance: dict[str, float | Float[np.ndarray | Array, ""]],
    path: str | pathlib.Path,
    title: str = "",
) -> pathlib.Path:
    """The share (0 to 1) of the cross-attention into the kept view that lands on the
    hand, across the stereo blocks L1..Ln: one line per model
    (`studies.attention.HandAttention.share`, e.g. stereo, view-mask, pure-monocular) and,
    dotted in its colour, the share uniform attention would give (its `chance`), as the
    paper's size-depth binding study (figure 7)."""
    fig, ax = figure(figsize=(4.6, 3.4))
    layers = max(len(np.atleast_1d(s)) for s in shares.values())
    for i, (name, share) in enumerate(shares.items()):
        y = np.asarray(share, float)
        ax.plot(np.arange(1, len(y) + 1), y, "-o", color=f"C{i}", label=name)
        if name in chance:
            ax.axhline(float(chance[name]), color=f"C{i}", ls=":", lw=1.0)
    ax.set_xticks(np.arange(1, layers + 1), [f"L{i}" for i in range(1, layers + 1)])
    ax.set_ylim(0, 1)
    ax.set_xlabel("stereo block")
    ax.set_ylabel("attention on hand patches (share)")
    ax.set_title(f"{title}\ndotted: uniform attention" if title else "dotted: uniform attention", fontsize=9)
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def plot_attention_maps(
    crop_image: Shaped[np.ndarray | Array, "S S *channels"],
    maps: dict[str, Float[np.ndarray | Array, "layers grid grid"]],
    path: str | pathlib.Path,
    hand_mask: Bool[np.ndarray | Array, "grid grid"] | None = None,
    title: str = "",
) -> pathlib.Path:
    """Cross-attention maps over a crop, as the paper's figure 7: one row per model, one
    column per stereo block L1..Ln.

    Args:
        crop_image: the kept view's crop, (S, S, 3) RGB or (S, S) gray, in [0, 1] or uint8
            (a `ClipInput` crop is channels first: move the axis).
        maps: per model, a (layers, grid, grid) map over the crop's patches
            (`studies.attention.attention_map` of one frame, rows = v: the share of the
            attention on each patch); the colour scale is shared by all panels.
        hand_mask: optional (grid, grid) hand patches (`studies.attention.hand_patch_mask`),
            outlined in white.
    """
    image = np.asarray(crop_image)
    size = image.shape[0]
    layers = max(np.asarray(m).shape[0] for m in maps.values())
    top = max(float(np.max(m)) for m in maps.values())
    extent = (-0.5, size - 0.5, size - 0.5, -0.5)  # pixel centres at integers
    outline = None
    if hand_mask is not None and 0 < np.sum(hand_mask) < np.size(hand_mask):  # some and not all: a boundary to draw
        outline = np.asarray(hand_mask, float)
        centres = (np.arange(outline.shape[0]) + 0.5) * size / outline.shape[0] - 0.5  # patch centres (px)
    fig, axes = figure(len(maps), layers, figsize=(2.0 * layers, 2.0 * len(maps)), squeeze=False)
    for row, (name, per_layer) in enumerate(maps.items()):
        for col in range(layers):
            ax = axes[row, col]
            ax.imshow(image, cmap="gray" if image.ndim == 2 else None, extent=extent)
            if col < len(per_layer):
                ax.imshow(np.asarray(per_layer[col], float), cmap="inferno", alpha=0.55, vmin=0.0, vmax=top,
                          interpolation="nearest", extent=extent)  # fmt: skip
            if outline is not None:
                ax.contour(centres, centres, outline, levels=[0.5], colors="w", linewidths=0.8)
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"L{col + 1}", fontsize=9)
            if col == 0:
                ax.set_ylabel(name, fontsize=9)
    if title:
        fig.suptitle(title, fontsize=10)
    return save_figure(fig, path)
