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
# # The on-screen gate and jitter (paper appendix L)
#
# The gate's precision / recall / F1 on held-out windows, and jitter three ways: ungated,
# ground-truth-gated and prediction-gated, on clean windows and under the off-screen
# stress test that blanks the middle four frames of every window. The paper's claim: the
# gate is exact on clean data (P = R = F1 = 1.00, the three jitters coincide), and under
# the stress test it flags the blanked frames off-screen (recall 1.00) so that
# prediction-gated jitter holds (3.31 -> 3.35 m/s²) while ungated jitter rises (4.61).
#
# `ESTHER_STUDY_SCALE=smoke|full python notebooks/06_gate.py`; the full run writes
# `docs/studies/gate.{md,json}`.

# %%
import time

import esther_jax
from esther_jax import studies
from esther_jax.eval.reports import Record, plot_metric_vs_condition

esther_jax.enable_compilation_cache()  # compiled programs are kept between runs (~/.cache/esther_jax)

start = time.perf_counter()
scale = studies.scale_from_env()
out = studies.report_dir(scale)
net = studies.trained(scale)
windows = studies.heldout_windows(scale, studies.dataset(scale, "heldout"))

# %%
result = studies.gate_stress_test(net, windows, scale)
rows = [{"condition": name, **{k: v for k, v in result[name].items() if k != "jitter"}, **result[name]["jitter"]} for name in ("clean", "stress")]
summary = studies.table(rows, [("precision", "precision"), ("recall", "recall"), ("f1", "F1"), ("offscreen_recall", "off-screen recall"),
                               ("ungated", "ungated jitter"), ("gt_gated", "GT-gated jitter"), ("prediction_gated", "prediction-gated jitter")],
                        first="condition")
print(summary)
recs = [Record(gating, name, "jitter", result[name]["jitter"][gating], unit="m/s^2") for name in ("clean", "stress") for gating in result[name]["jitter"]]
figures = [plot_metric_vs_condition(recs, "jitter", ["clean", "stress"], out / "gate_jitter.png", xlabel="condition")]

# %%
clean, stress = result["clean"], result["stress"]
holds = stress["offscreen_recall"] >= 0.95 and stress["jitter"]["prediction_gated"] < stress["jitter"]["ungated"]
verdict = (
    f"**{'Reproduces' if holds else 'Does not reproduce'}.** Clean: precision {clean['precision']:.2f}, recall "
    f"{clean['recall']:.2f}, F1 {clean['f1']:.2f} (paper: 1.00 each). Stress test (frames {result['blanked_frames']} "
    f"blanked): the gate withholds {100 * stress['offscreen_recall']:.0f}% of the blanked frames (paper: 100%); "
    f"prediction-gated jitter {stress['jitter']['prediction_gated']:.2f} m/s² against ungated "
    f"{stress['jitter']['ungated']:.2f} and ground-truth-gated {stress['jitter']['gt_gated']:.2f} (paper: 3.35, 4.61, "
    f"clean 3.31)."
)
print(verdict)

# %%
studies.write_report(out, "gate", title="The on-screen gate and jitter (appendix L)", verdict=verdict, scale=scale,
                     seconds=time.perf_counter() - start, results={**result, "reproduces": holds},
                     sections=["## Results (pooled over held-out frames; jitter in m/s²)", summary], figures=figures)
