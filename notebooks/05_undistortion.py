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
# # Undistortion strategies (paper table 7, appendix M)
#
# The same held-out motions seen by a fisheye rig (`hot3d_quest3`: Fisheye624, nearly
# parallel) and rectified to pinhole crops four ways (`SynthConfig.crop_strategy`):
# axis-aligned crops of the image undistorted at a virtual focal of 120 px (offbb120, the
# training default), 90 px and 150 px, and ray-aligned hand crops (hc). The network is
# scored under each; what matters is its stability across strategies, not the absolute
# numbers. The paper: ESTHER's P-MPJPE stays within 32.3-32.5 mm and its jitter within
# 16.3-16.8 m/s² across the three offbb focals (hc: 28.9 mm), while anchor-based
# baselines swing by hundreds of millimetres.
#
# Our engine renders every crop from the scene directly, so the offbb focal changes
# nothing but float rounding (the crop window's camera does not depend on it; the paper's
# differences come from resampling a finite wide image): the offbb columns test that the
# pipeline is invariant, hc is the real change of rectification. Our network is trained
# on the pinhole `esther` rig's crops, so this is also a change of rig.
#
# `ESTHER_STUDY_SCALE=smoke|full python notebooks/05_undistortion.py`; the full run
# writes `docs/studies/undistortion.{md,json}`.

# %%
import time

import esther_jax
from esther_jax import studies
from esther_jax.eval.reports import plot_metric_vs_condition

esther_jax.enable_compilation_cache()  # compiled programs are kept between runs (~/.cache/esther_jax)

RIG = "hot3d_quest3"
start = time.perf_counter()
scale = studies.scale_from_env()
STRATEGIES = ("offbb120", "hc") if scale.name == "smoke" else ("offbb120", "offbb90", "offbb150", "hc")  # fisheye crops are slow to render
out = studies.report_dir(scale)
net = studies.trained(scale)

# %%
results = {}
for strategy in STRATEGIES:
    windows = studies.heldout_windows(scale, studies.dataset(scale, "heldout", rig=RIG, crop_strategy=strategy))
    results[strategy] = studies.condition_table(net, windows, scale, {strategy: {}})[strategy]
control = studies.condition_table(net, windows, scale, {"no image (control)": studies.no_image(scale)})
COLUMNS = [("p_mpjpe_mm", "P-MPJPE mm"), ("pa_mpjpe_mm", "PA-MPJPE mm"), ("wrist_mm", "wrist mm"), ("jitter", "jitter m/s²"),
           ("windows", "windows")]
summary = studies.table([{"strategy": k, **v} for k, v in {**results, **control}.items()], COLUMNS, first="strategy")
print(summary)
recs = studies.records("ESTHER", results)
figures = [plot_metric_vs_condition(recs, m, list(STRATEGIES), out / f"undistortion_{m}.png", xlabel="rectification") for m in ("p_mpjpe", "wrist", "jitter")]

# %%
def spread(names, key):
    values = [results[n][key] for n in names if results[n][key] is not None]
    return max(values) - min(values) if values else None


offbb = [s for s in STRATEGIES if s.startswith("offbb")]
spreads = {key: {"offbb": spread(offbb, key), "all": spread(STRATEGIES, key)} for key in ("p_mpjpe_mm", "wrist_mm", "jitter")}
hc_apart = studies.separated(results["hc"]["intervals"]["p_mpjpe_mm"], results["offbb120"]["intervals"]["p_mpjpe_mm"])
blind = control["no image (control)"]
sees = studies.separated(results["hc"]["intervals"]["p_mpjpe_mm"], blind["intervals"]["p_mpjpe_mm"]) or studies.separated(
    results["hc"]["intervals"]["wrist_mm"], blind["intervals"]["wrist_mm"])
stable = spreads["p_mpjpe_mm"]["offbb"] is not None and spreads["p_mpjpe_mm"]["offbb"] < 1.0 and spreads["jitter"]["offbb"] < 1.0
verdict = (
    f"**{('Reproduces' if sees else 'Holds, but vacuously') if stable else 'Does not reproduce'}, trivially for the offbb focals.** Across offbb120/90/150 our "
    f"network's P-MPJPE spans {spreads['p_mpjpe_mm']['offbb']:.2f} mm, its wrist {spreads['wrist_mm']['offbb']:.2f} mm and its "
    f"jitter {spreads['jitter']['offbb']:.2f} m/s² (paper: 0.2 mm, 0.5 m/s²) — but our renderer gives the three focals the same "
    f"crops, so this only shows the pipeline is invariant. The ray-aligned hc crops move P-MPJPE from "
    f"{results['offbb120']['p_mpjpe_mm']:.1f} to {results['hc']['p_mpjpe_mm']:.1f} mm and the wrist from "
    f"{results['offbb120']['wrist_mm']:.1f} to {results['hc']['wrist_mm']:.1f} mm "
    f"({'intervals apart' if hc_apart else 'intervals overlapping'}; paper: 32.4 -> 28.9 mm, wrist 20.8 -> 48.0 mm). The "
    f"network was trained on pinhole offbb crops of another rig; no baseline of the paper's table is run here. Control: with no "
    f"image at all its P-MPJPE is {blind['p_mpjpe_mm']:.1f} mm and its wrist {blind['wrist_mm']:.1f} mm, "
    + ("apart from the hc intervals: the network reads these images." if sees
       else "inside the hc intervals: the network barely reads the images, so any stability here says little.")
)
print(verdict)

# %%
studies.write_report(out, "undistortion", title="Undistortion strategies (table 7, appendix M)", verdict=verdict, scale=scale,
                     seconds=time.perf_counter() - start, results={"rig": RIG, "strategies": results, "control": control, "spreads": spreads, "reads_images": sees},
                     sections=[f"## Results on `{RIG}` (mean [95% bootstrap interval] over held-out windows)", summary], figures=figures)
