# ---
# jupyter:
#   jupytext:
#     formats: py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Ablations (paper table 5)
#
# Every row of table 5 (`model.ABLATIONS`, except the size-depth study's pure-monocular
# model) trained under one budget (the scale's two stages on the same clips, the same
# seed) and scored on the same held-out windows by absolute MPJPE (rig frame), with
# appendix-J intervals. The paper's claims: geometry matters most (dropping the Plücker
# rays, +14.0 mm, or cross-view attention, +9.1 mm, hurts most), the flow token helps
# (+2.5 mm), masking and the absolute wrist cost a little clean accuracy (-0.3 and
# -3.5 mm) but buy robustness. The smoke scale trains two rows.
#
# `ESTHER_STUDY_SCALE=smoke|full python notebooks/07_ablations.py`; the full run writes
# `docs/studies/ablations.{md,json}`. Each row is a separate training run (at the full
# scale about half an hour to an hour each on a 2-core CPU), so the table can be built
# over several sittings: `ESTHER_ABLATION_ROWS=no-plucker,no-cross-view` trains and scores
# only those rows next to the full model, and keeps the rows of the earlier report when
# the full model, trained again, reproduces that report's full model
# (`studies.earlier_rows`: each mean inside the other's interval); each row names the
# revision it was trained at. Trained rows are also kept under the study root and reused.

# %%
import os
import time

import numpy as np

import esther_jax
from esther_jax import model as M
from esther_jax import studies
from esther_jax.eval.reports import plot_metric_vs_condition

esther_jax.enable_compilation_cache()  # compiled programs are kept between runs (~/.cache/esther_jax)

PAPER_MPJPE = {
    "esther": 19.60, "no-plucker": 33.60, "no-cross-view": 28.70, "no-guidance-masking-augmentation": 23.10, "no-flow-token": 22.10,
    "no-2d-guidance": 20.99, "no-image-augmentation": 20.40, "uniform-gate": 19.86, "no-triangulation-guidance": 19.72,
    "no-motion-masking": 19.31, "anchored-wrist": 16.12,
}  # fmt: skip
"""Table 5 of the paper: absolute MPJPE (mm) on its pseudo-labelled validation split."""

start = time.perf_counter()
scale = studies.scale_from_env()
out = studies.report_dir(scale)
TABLE_ROWS = [r for r in M.ABLATIONS if r != "monocular"]
chosen = [r for r in os.environ.get(studies.ABLATION_ROWS_ENV, "").split(",") if r]
if unknown := sorted(set(chosen) - set(TABLE_ROWS)):
    raise ValueError(f"{studies.ABLATION_ROWS_ENV}: unknown rows {unknown}; choose from {TABLE_ROWS}")
rows = ["esther", *(chosen or (["anchored-wrist"] if scale.name == "smoke" else TABLE_ROWS))]
windows = studies.heldout_windows(scale, studies.dataset(scale, "heldout"))

# %%
scored = {}
for row in rows:
    scored[row] = studies.condition_table(studies.trained(scale, row), windows, scale, {"clean": {}})["clean"]
    print(f"{row:<36} MPJPE {scored[row]['mpjpe_mm']:.1f} mm")
kept, trained_at = studies.earlier_rows(out, "ablations", scale, "esther", scored["esther"])
trained_at |= {r: studies.trained_at(scale, r) for r in rows}
carried = [r for r in TABLE_ROWS if r in kept and r not in scored]
results = {r: scored.get(r) or kept[r] for r in ["esther", *TABLE_ROWS] if r in scored or r in carried}
print(f"kept from the earlier report: {', '.join(carried) or 'none'}")

# %%
full = results["esther"]
minutes = {r: studies.training_minutes(scale, r) for r in results}  # None: trained under another root, an earlier sitting
short = lambda rev: rev[:7] + rev[40:] if rev else "unknown"  # noqa: E731  (a commit's first 7 hex digits, and " or earlier")
table_rows = [{"variant": r, **v, "trained_at": short(trained_at[r]), "delta_mm": v["mpjpe_mm"] - full["mpjpe_mm"], "paper_mm": PAPER_MPJPE[r],
               "paper_delta_mm": PAPER_MPJPE[r] - PAPER_MPJPE["esther"], "train_min": minutes[r],
               "separated": studies.separated(v["intervals"]["mpjpe_mm"], full["intervals"]["mpjpe_mm"]) if r != "esther" else None}
              for r, v in results.items()]  # fmt: skip
summary = studies.table(table_rows, [("mpjpe_mm", "MPJPE mm"), ("delta_mm", "Δ vs full"), ("separated", "interval apart"),
                                     ("p_mpjpe_mm", "P-MPJPE mm"), ("wrist_mm", "wrist mm"), ("paper_mm", "paper MPJPE"),
                                     ("paper_delta_mm", "paper Δ"), ("trained_at", "trained at"), ("train_min", "train min")], first="variant")  # fmt: skip
timed = [m for m in minutes.values() if m is not None]
training_note = (f"The training steps took {sum(timed):.0f} min on this machine for the {len(timed)} rows whose runs are in the study root "
                 f"(column 'train min', both stages); the wall time below is this sitting's (the evaluation, and the rows it trained)."
                 if timed else "No row's training run is in the study root (the smoke scale trains none).")  # fmt: skip
print(summary)
figures = [plot_metric_vs_condition(studies.records("cpu network", results), "mpjpe", list(results), out / "ablations_mpjpe.png", xlabel="variant")]

# %%
ranked = sorted((r for r in results if r != "esther"), key=lambda r: -results[r]["mpjpe_mm"])
paper_ranked = sorted((r for r in results if r != "esther"), key=lambda r: -PAPER_MPJPE[r])
delta = lambda r: results[r]["mpjpe_mm"] - full["mpjpe_mm"]  # noqa: E731
paper_delta = lambda r: PAPER_MPJPE[r] - PAPER_MPJPE["esther"]  # noqa: E731
same_sign = [r for r in ranked if delta(r) * paper_delta(r) > 0]
geometry_first = set(ranked[:2]) == {"no-plucker", "no-cross-view"}
complete = len(results) == len(PAPER_MPJPE)
damaging = [f"{r} ({delta(r):+.1f} mm)" for r in ranked if delta(r) > 0][:2]
paper_damaging = [f"{r} ({paper_delta(r):+.1f} mm)" for r in paper_ranked if paper_delta(r) > 0][:2]
verdict = (
    f"**{'Reproduces' if complete and geometry_first else 'Does not reproduce' if complete else 'Partial run'}.** "
    f"{len(results)} of {len(PAPER_MPJPE)} rows trained under one budget"
    f"{f' ({len(carried)} kept from an earlier sitting whose full model this one reproduces)' if carried else ''}; "
    f"the full model's MPJPE is {full['mpjpe_mm']:.1f} mm. "
    f"{len(same_sign)} of {len(ranked)} ablations move MPJPE in the paper's direction. Most damaging here: "
    f"{', '.join(damaging) or 'none'} (paper, over the same rows: {', '.join(paper_damaging) or 'none'})."
)
if len(ranked) >= 3:  # where the shifts come from: absolute MPJPE (rig frame) holds the wrist's error
    wrist_delta = lambda r: results[r]["wrist_mm"] - full["wrist_mm"]  # noqa: E731
    hand_delta = lambda r: results[r]["p_mpjpe_mm"] - full["p_mpjpe_mm"]  # noqa: E731
    by_hand = sorted(ranked, key=hand_delta, reverse=True)
    follows = np.corrcoef([delta(r) for r in ranked], [wrist_delta(r) for r in ranked])[0, 1]
    verdict += (
        f" Absolute MPJPE holds the wrist's error, and the full model's wrist is {full['wrist_mm']:.1f} mm (its P-MPJPE "
        f"{full['p_mpjpe_mm']:.1f} mm; the paper's full model: MPJPE {PAPER_MPJPE['esther']:.1f} mm in all): "
        f"here the rows' MPJPE shifts follow their wrist shifts (correlation {follows:.2f}; "
        f"{', '.join(f'{r} wrist {wrist_delta(r):+.1f} mm' for r in ranked[:2])}), so the table ranks "
        f"what each ablation does to the wrist. On P-MPJPE, which leaves the wrist out, the most damaging are "
        f"{', '.join(f'{r} ({hand_delta(r):+.1f} mm)' for r in by_hand[:2])}. "
        f"What was tried on the wrist is in docs/training.md."
    )
print(verdict)

# %%
studies.write_report(out, "ablations", title="Ablations (table 5)", verdict=verdict, scale=scale, seconds=time.perf_counter() - start,
                     results={"rows": results, "trained_at": {r: trained_at[r] for r in results}, "training_minutes": minutes,
                              "paper_mpjpe_mm": PAPER_MPJPE, "ranked": ranked},
                     sections=["## Results (absolute MPJPE, rig frame; mean [95% bootstrap interval] over held-out windows)", summary, training_note],
                     figures=figures)
