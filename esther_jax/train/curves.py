"""A training run's learning curves (`<run>/curves.png`, redrawn at every validation)."""

import pathlib

import matplotlib
import numpy as np

from ..figures import figure, save_figure
from ..metrics import METRIC_LABELS


def plot_learning_curves(steps: list[dict], validation: list[dict], path: str | pathlib.Path) -> pathlib.Path:
    """A training run's curves: every logged loss term (`loss/<term>`, moving median over
    about 2 % of the run, log scale) against the step, and beside it the validation
    P-MPJPE and wrist error (mm) per condition (`views`) when there is any."""
    panels = 2 if validation else 1
    fig, axes = figure(1, panels, figsize=(5.2 * panels, 3.8), squeeze=False)
    ax = axes[0, 0]
    ax.set_prop_cycle(color=matplotlib.colormaps["tab20"].colors)
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
    return save_figure(fig, path)
