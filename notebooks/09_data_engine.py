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
# # The data engine (paper, "Model-Assisted Labeling and Iterative Enhancement")
#
# The teacher labels a share of a raw collection; the network trained on those labels
# predicts the rest; each prediction is refined against the clip's 2D keypoints and
# screened by the teacher's filter; the accepted refined labels join the next round's
# training, "each round yielding a stronger labeler and cleaner labels". Measured here on
# a synthetic raw collection on two rigs (the paper's and Aria's) whose ground truth is
# held aside, per round: coverage (share of on-screen hand-frames with an accepted label),
# the accepted labels' accuracy against the truth and the filter's misses (accepted labels
# worse than 15 mm), the refined labels against the teacher's on the same frames, the cost
# (hand-frames/s), and the network's held-out accuracy with bootstrap intervals; three
# seeds. Targets: refinement >= 5x the teacher's throughput, refined labels within 1 mm
# P-MPJPE of the teacher's, round 1's network better than round 0's.
#
# `ESTHER_STUDY_SCALE=smoke|full python notebooks/09_data_engine.py`; the full run writes
# `docs/studies/data_engine.{md,json}`.

# %%
import dataclasses
import time

import esther_jax
from esther_jax import studies
from esther_jax.studies import data_engine

esther_jax.enable_compilation_cache()  # compiled programs are kept between runs (~/.cache/esther_jax)

start = time.perf_counter()
scale = studies.scale_from_env()
study = data_engine.ENGINE_STUDIES[scale.name]
out = studies.report_dir(scale)
results = data_engine.run_engine_study(scale, study, studies.study_root(scale) / "engine", progress=True)

# %%
labels_table = data_engine.round_table(results)
networks = data_engine.network_table(results)
print(labels_table)
print(networks)

# %%
check = data_engine.verdict(results)
fmt = lambda xs, f="{:.2f}": ", ".join("n/a" if x is None else f.format(x) for x in xs)  # noqa: E731
met = [check["throughput_target_met"], check["same_frames_target_met"], check["round1_target_met"]]
verdict = (
    f"**{'Reproduces' if all(met) else 'Partly reproduces' if any(met) else 'Does not reproduce'}** "
    f"({sum(met)} of the 3 targets met, {len(results['seeds'])} seed(s), {results['clips']} raw clips: {', '.join(f'{n} on {rig}' for rig, n in results['raw'])}). "
    f"Refinement runs at {fmt(check['throughput_ratio'], '{:.1f}x')} the teacher's hand-frames/s (target 5x: "
    f"{'met' if check['throughput_target_met'] else 'missed'}). Its accepted labels are "
    f"{fmt(check['same_frames_difference_mm'], '{:+.2f}')} mm P-MPJPE from the teacher's on the frames both accepted (target within 1 mm: "
    f"{'met' if check['same_frames_target_met'] else 'missed'}). Round 1's network beats round 0's on held-out windows with intervals apart "
    f"in {sum(check['round1_better'])} of {len(check['round1_better'])} seed(s) (target: every seed; "
    f"{'met' if check['round1_target_met'] else 'missed'})."
)  # fmt: skip
print(verdict)

# %%
report_scale = dataclasses.replace(
    scale, model=study.engine.config, train_clips=results["clips"], heldout_clips=results["heldout_clips"],
    stage1_steps=study.engine.stage1_steps, stage2_steps=study.engine.stage2_steps, batch=study.engine.batch,
    learning_rate=study.engine.learning_rate, windows=None, resamples=2000,  # the engine scores every held-out window (engine.network_accuracy)
)  # fmt: skip
studies.write_report(
    out, "data_engine", title="The data engine (Model-Assisted Labeling and Iterative Enhancement)", verdict=verdict, scale=report_scale,
    seconds=time.perf_counter() - start, results={**results, "targets": check},
    sections=["## Labels per round (mean ± sd over seeds)", labels_table, "## The networks on held-out windows (bootstrap 95 % intervals)",
              networks],
)  # fmt: skip
