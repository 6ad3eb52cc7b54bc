"""Tidy result records, paper-style tables (Markdown, CSV) and figures (PNG)."""

import csv
import dataclasses
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..files import atomic_output  # noqa: E402
from ..metrics import Bootstrap, DepthScatter  # noqa: E402

METRIC_LABELS = {
    "p_mpjpe": ("P-MPJPE", "mm"),
    "pa_mpjpe": ("PA-MPJPE", "mm"),
    "wrist": ("Wrist", "mm"),
    "jitter": ("Jitter", "m/s^2"),
    "mpjpe": ("MPJPE", "mm"),
    "gt_jitter": ("GT jitter", "m/s^2"),
}
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


def _save(fig, path: pathlib.Path) -> pathlib.Path:
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def plot_depth_scatter(z_gt: np.ndarray, z_pred: np.ndarray, scatter: DepthScatter, path: str | pathlib.Path, title: str = "") -> pathlib.Path:
    """Predicted vs true wrist depth with the linear fit, as the paper's figure 8."""
    fig, ax = plt.subplots(figsize=(4.2, 4.0))
    ax.scatter(z_gt, z_pred, s=3, alpha=0.35, color="#2b6cb0", linewidths=0)
    lo, hi = float(np.nanmin(z_gt)), float(np.nanmax(z_gt))
    xs = np.linspace(lo, hi, 2)
    ax.plot(xs, xs, "k--", lw=0.8, label="ideal")
    ax.plot(xs, float(scatter.slope) * xs + float(scatter.intercept), color="#c53030", lw=1.2, label="linear fit")
    ax.set_xlabel("true wrist depth (m)")
    ax.set_ylabel("predicted wrist depth (m)")
    ax.set_title(
        f"{title}\ncorr {float(scatter.correlation):.2f}, random {float(scatter.random_mm):.1f} mm, "
        f"systematic {float(scatter.systematic_mm):.1f} mm",
        fontsize=9,
    )
    ax.legend(fontsize=8, loc="upper left")
    ax.set_aspect("equal", adjustable="datalim")
    return _save(fig, pathlib.Path(path))


def plot_metric_vs_condition(
    records: list[Record], metric: str, conditions: list[str], path: str | pathlib.Path, xlabel: str = "frames dropped of 16"
) -> pathlib.Path:
    """One line per method of a metric across ordered conditions (e.g. error vs dropped
    frames), with bootstrap 95% intervals as error bars."""
    fig, ax = plt.subplots(figsize=(4.6, 3.4))
    for method in dict.fromkeys(r.method for r in records):
        pts = [next((r for r in records if r.method == method and r.metric == metric and r.condition == c), None) for c in conditions]
        y = np.asarray([p.value if p else np.nan for p in pts])
        lo = np.asarray([p.value - p.ci_low if p and p.ci_low is not None else 0.0 for p in pts])
        hi = np.asarray([p.ci_high - p.value if p and p.ci_high is not None else 0.0 for p in pts])
        ax.errorbar(range(len(conditions)), y, yerr=[lo, hi], marker="o", capsize=3, label=method)
    ax.set_xticks(range(len(conditions)), conditions)
    label, unit = METRIC_LABELS.get(metric, (metric, ""))
    ax.set_xlabel(xlabel)
    ax.set_ylabel(f"{label} ({unit})")
    ax.legend(fontsize=8)
    return _save(fig, pathlib.Path(path))


def plot_learning_curves(steps: list[dict], validation: list[dict], path: str | pathlib.Path) -> pathlib.Path:
    """A training run's curves: every logged loss term (`loss/<term>`, moving median over
    about 2 % of the run, log scale) against the step, and beside it the validation
    P-MPJPE and wrist error (mm) per condition (`views`) when there is any."""
    panels = 2 if validation else 1
    fig, axes = plt.subplots(1, panels, figsize=(5.2 * panels, 3.8), squeeze=False)
    ax = axes[0, 0]
    ax.set_prop_cycle(color=plt.cm.tab20.colors)
    x = np.asarray([row["step"] for row in steps])
    width = max(len(steps) // 50, 1)
    for key in ["loss"] + sorted(k for k in (steps[0] if steps else {}) if k.startswith("loss/")):
        y = np.asarray([row.get(key) if row.get(key) is not None else np.nan for row in steps], float)
        if not np.any(y > 0):
            continue
        smooth = np.asarray([np.nanmedian(y[max(0, i - width + 1) : i + 1]) for i in range(len(y))])
        ax.plot(x, smooth, lw=2.0 if key == "loss" else 0.9, color="k" if key == "loss" else None, label=key.split("/")[-1])
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss (moving median)")
    ax.legend(fontsize=6, ncol=2)
    if validation:
        ax = axes[0, 1]
        for views in dict.fromkeys(row["views"] for row in validation):
            rows = [row for row in validation if row["views"] == views]
            for metric, style in (("p_mpjpe_mm", "-o"), ("wrist_mm", "--s")):
                ax.plot([r["step"] for r in rows], [r.get(metric) if r.get(metric) is not None else np.nan for r in rows], style, ms=3,
                        label=f"{METRIC_LABELS[metric[:-3]][0]}, {views}")  # fmt: skip
        ax.set_xlabel("step")
        ax.set_ylabel("validation error (mm)")
        ax.legend(fontsize=7)
    return _save(fig, pathlib.Path(path))


def plot_pck(thresholds_m: np.ndarray, curve: np.ndarray, path: str | pathlib.Path, label: str = "") -> pathlib.Path:
    fig, ax = plt.subplots(figsize=(4.2, 3.2))
    ax.plot(np.asarray(thresholds_m) * 1000, curve, label=label or None)
    ax.set_xlabel("threshold (mm)")
    ax.set_ylabel("PCK")
    ax.set_ylim(0, 1)
    if label:
        ax.legend(fontsize=8)
    return _save(fig, pathlib.Path(path))
