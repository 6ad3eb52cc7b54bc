"""Optimisation (appendix E) and runs that survive interruption.

- `make_optimizer`: AdamW (learning rate 2e-4, cosine schedule after 500 linear warm-up
  steps), global-norm clipping at 1.0, weight decay only on the weight matrices of
  dense and convolution layers (norms, biases and learned tokens are not decayed). Only
  the stage's trainable weights are optimised: a frozen backbone has no optimiser state
  and no gradient; stage 'image' trains the image encoder (and a trainable backbone)
  alone, stage 'joint' everything trainable.
- `Trainer.step`: one jitted step holds the examples' corruption (appendix C), the
  forward pass, the losses (appendix B), the gradient, clipping, the update and the
  optional EMA of the weights.
- `Trainer.training_steps`: the steps as a generator, one `StepInfo` (step, state, the
  metrics on the host, seconds) per step, the next batch read while a step runs; `Hooks`
  runs functions of it every N steps (levanter's `trainer.add_hook(fn, every=N)`), e.g.
  `nonfinite_guard`. `train`'s loop is these two: its logging, non-finite guard,
  validation, checkpoints and progress bar are hooks.
- `train`: a run folder `RUN/` holding `config.json` (model, training, data, git
  revision), `index.json` (the training windows), `metrics.jsonl` (every logged step:
  each loss term, gradient norm, learning rate, clips/s), `checkpoints/step_<step, 8 digits>/`
  written atomically (a temporary folder renamed into place, then the `checkpoints/latest`
  pointer), the last `keep_checkpoints` kept, and the final network in `RUN/model`
  (`model.save`, what `model.load` reads). `resume=True` continues from the latest
  checkpoint bit for bit (the batch and the corruption of a step are pure functions of
  the seed and the step). With held-out clips, `validation.jsonl` holds the validation
  metrics every `validate_every` steps and `curves.png` the learning curves. A
  non-finite loss stops the run (`NonFiniteLoss`, naming the step and the terms) and
  leaves the last good checkpoint as it was.
- Several devices: `data_mesh` and `Trainer(mesh=)` (data parallelism); several
  processes: `jax.distributed.initialize()` first, then the same code.
"""

import contextlib
import dataclasses
import functools
import json
import os
import pathlib
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from .. import mano
from .. import model as M
from .curves import plot_learning_curves
from ..files import atomic_output, exclusive_lock, file_sha256, git_revision, read_json, write_json
from . import data as data_lib
from .losses import STAGES, LossWeights, clip_loss_terms, combine
from .masking import AugmentRates, MaskingRates, corrupt, example_key
from .features import precompute_features
from .validation import evaluate_windows


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    stage: str = "joint"
    """'image' (stage 1: the image encoder under its guidance) or 'joint' (stage 2)."""
    steps: int = 1000
    """Optimisation steps of the run (the learning rate's cosine ends at the last)."""
    batch: int = 8
    """Windows per step (all devices and processes together)."""
    learning_rate: float = 2e-4
    """Peak learning rate (appendix E: 2e-4)."""
    warmup_steps: int = 500
    """Linear warm-up steps (appendix E: 500)."""
    weight_decay: float = 0.05
    """AdamW's decoupled weight decay (the paper gives none; 0.05 as in DINO-style ViT training)."""
    clip_norm: float = 1.0
    """Global-norm gradient clipping."""
    seed: int = 0
    """Seeds a fresh network's weights and each step's batch, masking and augmentation."""
    ema_decay: float | None = None
    """EMA of the trainable weights (e.g. 0.999), saved beside them and used for validation and the final model."""
    checkpoint_every: int = 100
    """Steps between checkpoints (and one at the end)."""
    keep_checkpoints: int = 3
    """The last this many checkpoints are kept."""
    compute_dtype: str = "float32"
    """'float32', or 'bfloat16': mixed precision, the network computed in bfloat16 from
    float32 master weights (`model.cast`), geometry, forward kinematics and losses in
    float32."""
    validate_every: int = 500
    """Steps between validations on the held-out clips (and one at the end)."""
    validation_windows: int = 64
    """At most this many held-out windows per validation (evenly spread over the clips)."""
    frames_apart: bool = False
    """Stage 'image' only: each example's frames are drawn one by one from every window of
    its hand and rig instead of one window's consecutive frames (`data.load_batch`): a
    batch shows the image encoder B x T hands instead of about B."""

    def __post_init__(self):
        if self.stage not in STAGES:
            raise ValueError(f"stage must be one of {STAGES}, got {self.stage!r}")
        if min(self.steps, self.batch, self.checkpoint_every, self.keep_checkpoints, self.validate_every, self.validation_windows) < 1:
            raise ValueError("steps, batch, checkpoint_every, keep_checkpoints, validate_every and validation_windows must be positive")
        if self.compute_dtype not in ("float32", "bfloat16"):
            raise ValueError(f"compute_dtype must be 'float32' or 'bfloat16', got {self.compute_dtype!r}")
        if self.frames_apart and self.stage != "image":
            raise ValueError("frames_apart is for stage 'image' (per-frame losses); stage 'joint' learns from the windows' motion")
        if self.ema_decay is not None and not 0.0 < self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must lie in (0, 1), got {self.ema_decay}")


class NonFiniteLoss(RuntimeError):
    """The loss of a step is NaN or infinite; the message names the step and the terms."""


def stage_spec(net: M.ESTHER, stage: str):
    """Filter spec of the weights a stage trains (`M.trainable`, narrowed for stage 'image'
    to the image encoder and a trainable backbone)."""
    spec = M.trainable(net)
    if stage == "image":
        off = lambda tree: jax.tree.map(lambda _: False, tree)  # noqa: E731
        spec = eqx.tree_at(lambda m: (m.motion_encoder, m.fusion_decoder), spec, (off(net.motion_encoder), off(net.fusion_decoder)))
    return spec


def decay_mask(params):
    """True for the weight matrices of dense and convolution layers (`.weight`, 2+ axes);
    norms, biases and learned tokens are not decayed."""
    def decays(path, leaf):
        return leaf is not None and jax.tree_util.keystr(path).endswith(".weight") and jnp.ndim(leaf) >= 2

    return jax.tree_util.tree_map_with_path(decays, params)


def learning_rate_schedule(cfg: TrainConfig) -> optax.Schedule:
    """Linear warm-up to the peak, then cosine decay to 0 at the last step."""
    return optax.warmup_cosine_decay_schedule(
        init_value=0.0, peak_value=cfg.learning_rate, warmup_steps=cfg.warmup_steps,
        decay_steps=max(cfg.steps, cfg.warmup_steps + 1), end_value=0.0,
    )  # fmt: skip


def make_optimizer(cfg: TrainConfig, params) -> optax.GradientTransformation:
    return optax.chain(
        optax.clip_by_global_norm(cfg.clip_norm),
        optax.adamw(learning_rate_schedule(cfg), weight_decay=cfg.weight_decay, mask=decay_mask(params)),
    )


class TrainState(eqx.Module):
    step: jax.Array
    params: M.ESTHER
    """The trainable weights (other leaves None)."""
    opt_state: optax.OptState
    ema: M.ESTHER | None


def data_mesh(devices=None) -> jax.sharding.Mesh:
    """A one-axis mesh named 'batch' over `devices` (default: every device of every
    process, `jax.devices()`): data parallelism, the batch split over it, the weights
    replicated."""
    devices = jax.devices() if devices is None else list(devices)
    return jax.sharding.Mesh(np.asarray(devices), ("batch",))


def _put(tree, sharding):
    return jax.tree.map(lambda x: jax.device_put(x, sharding) if eqx.is_array(x) else x, tree)


def _host(tree):
    """Replicated arrays as this process's copy (numpy), e.g. to serialise them: a
    replicated array of a multi-process run is not addressable as a whole."""
    return jax.tree.map(lambda x: np.asarray(x.addressable_data(0)) if isinstance(x, jax.Array) else x, tree)


def process_batch_slice(batch: int) -> slice:
    """The examples of a global batch that this process loads (all of them in a
    single-process run): equal consecutive shares in process order."""
    count, index = jax.process_count(), jax.process_index()
    if batch % count:
        raise ValueError(f"a batch of {batch} does not split over {count} processes")
    share = batch // count
    return slice(index * share, (index + 1) * share)


class Trainer:
    """The optimiser and the jitted step of one (model, training) configuration.

    With a `mesh` (`data_mesh`), the step runs data-parallel: the weights, optimiser
    state and hand model are replicated over the mesh's devices, each batch is split
    along its leading axis (`shard`), and the compiled step's reductions over the batch
    (the loss terms' sums and counts, hence the gradient) run across devices. The batch
    must divide evenly over the devices. In a multi-process run every process passes
    its own share of the global batch to `shard` (`process_batch_slice`).
    """

    def __init__(self, net: M.ESTHER, cfg: TrainConfig, hand_model: mano.ManoModel, weights: LossWeights = LossWeights(),
                 masking: MaskingRates = MaskingRates(), augment: AugmentRates = AugmentRates(), *,
                 mesh: jax.sharding.Mesh | None = None):  # fmt: skip
        if mesh is not None and cfg.batch % mesh.size:
            raise ValueError(f"a batch of {cfg.batch} does not split over {mesh.size} devices: choose a multiple of {mesh.size}")
        self.cfg, self.model_cfg, self.hand, self.mesh = cfg, net.config, hand_model, mesh
        params, self.static = eqx.partition(net, stage_spec(net, cfg.stage))
        with jax.numpy_dtype_promotion("standard"):
            opt_state = make_optimizer(cfg, params).init(params)  # the step rebuilds the same optimiser from cfg
        self._initial = TrainState(jnp.zeros((), jnp.int32), params, opt_state, params if cfg.ema_decay else None)
        if mesh is not None:
            replicated = jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec())
            self._initial, self.static, self.hand = _put((self._initial, self.static, self.hand), replicated)
        self._weights, self._masking, self._augment = weights, masking, augment

    def init(self) -> TrainState:
        return self._initial

    def network(self, state: TrainState, *, ema: bool = False) -> M.ESTHER:
        return eqx.combine(state.ema if ema and state.ema is not None else state.params, self.static)

    def shard(self, batch):
        """This process's share of a batch (leading axis) as global arrays split over
        the mesh's 'batch' axis; the batch unchanged without a mesh."""
        if self.mesh is None:
            return batch
        sharding = jax.sharding.NamedSharding(self.mesh, jax.sharding.PartitionSpec("batch"))
        return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), batch)

    def place(self, state: TrainState) -> TrainState:
        """A state (e.g. read from a checkpoint) replicated over the mesh; unchanged without one."""
        if self.mesh is None:
            return state
        return _put(state, jax.sharding.NamedSharding(self.mesh, jax.sharding.PartitionSpec()))

    def step(self, state: TrainState, clips: M.ClipInput, targets) -> tuple[TrainState, dict]:
        """One optimisation step over a batch (leading axis): (new state, metrics)."""
        clips, targets = self.shard((clips, targets))
        return _train_step(self.static, self.hand, state, clips, targets, self._settings())

    def training_steps(self, state: TrainState, load: Callable[[int], tuple]) -> Iterator["StepInfo"]:
        """The steps from `state`'s to `cfg.steps`, one `StepInfo` each (levanter's
        `trainer.training_steps`); `load(step)` is the step's batch (this process's share,
        `process_batch_slice`), read on a worker thread while the previous step runs. Close
        the generator (`contextlib.closing`) when a hook may raise: the worker ends with it."""
        start, last = int(state.step), time.perf_counter()
        with ThreadPoolExecutor(1) as loader:
            pending = loader.submit(load, start)
            for step in range(start, self.cfg.steps):
                clips, targets = pending.result()
                state, metrics = self.step(state, clips, targets)
                if step + 1 < self.cfg.steps:
                    pending = loader.submit(load, step + 1)
                values = {k: float(v) for k, v in jax.device_get(metrics).items()}  # the one wait for the device per step
                now = time.perf_counter()
                info = StepInfo(step + 1, state, values, now - last)
                last = now
                yield info

    def _settings(self):
        return (_step_settings(self.cfg), self.model_cfg, self._weights, self._masking, self._augment)


@dataclasses.dataclass(frozen=True)
class StepInfo:
    """One optimisation step as `Trainer.training_steps` yields it and hooks see it
    (levanter's `StepInfo`)."""

    step: int
    """Steps done: the state's step after this update (1 after the first)."""
    state: TrainState
    """The state after the update (a non-finite loss's too: `nonfinite_guard` stops there)."""
    metrics: dict[str, float]
    """The step's metrics on the host: loss, loss/<term>, grad_norm, grad_norm/<part>, learning_rate."""
    seconds: float
    """Wall time since the previous step's metrics arrived (so its hooks count: validations,
    checkpoints), or since the steps began (the first step's compilation and batch)."""

    @property
    def loss(self) -> float:
        return self.metrics["loss"]


class Hooks:
    """Functions of a `StepInfo` run after steps in the order they were added, each every
    `every` steps (`info.step % every == 0`) and at any step run with `force=True` (a run's
    last): levanter's `trainer.add_hook(fn, every=N)`.

        hooks = Hooks()
        hooks.add(nonfinite_guard(run))
        hooks.add(lambda info: print(info.step, info.loss), every=10)
        with contextlib.closing(trainer.training_steps(state, load)) as steps:
            for info in steps:
                hooks.run(info, force=info.step == cfg.steps)
    """

    def __init__(self):
        self._hooks: list[tuple[Callable[[StepInfo], None], int]] = []

    def add(self, fn: Callable[[StepInfo], None], *, every: int = 1) -> Callable[[StepInfo], None]:
        if every < 1:
            raise ValueError(f"a hook runs every 1 or more steps, got every={every}")
        self._hooks.append((fn, every))
        return fn

    def run(self, info: StepInfo, *, force: bool = False) -> None:
        for fn, every in self._hooks:
            if force or info.step % every == 0:
                fn(info)


def nonfinite_guard(run: pathlib.Path) -> Callable[[StepInfo], None]:
    """A hook (every step, added first) raising `NonFiniteLoss` at a NaN or infinite loss,
    naming the step, the terms and the checkpoints of `run` (before any other hook has
    logged or saved the step)."""

    def guard(info: StepInfo) -> None:
        values = info.metrics
        if not np.isfinite(values["loss"]):
            bad = sorted(k.split("/", 1)[1] for k, v in values.items() if k.startswith("loss/") and not np.isfinite(v))
            raise NonFiniteLoss(
                f"step {info.step - 1}: the loss is {values['loss']} (non-finite terms: {', '.join(bad) or 'none; the weighted sum overflowed'}); "
                f"the run stopped, its last good checkpoint is kept in {run / CHECKPOINTS}"
            )

    return guard


def _step_settings(cfg: TrainConfig) -> TrainConfig:
    """`cfg` with the fields the step does not read reset: runs that differ only in
    checkpointing share one compiled step."""
    return dataclasses.replace(cfg, checkpoint_every=1, keep_checkpoints=1, validate_every=1, validation_windows=1)


@eqx.filter_jit
def _train_step(static: M.ESTHER, hand: mano.ManoModel, state: TrainState, clips: M.ClipInput, targets, settings):
    """One optimisation step over a batch (leading axis). The arrays (state, frozen
    weights, hand model, batch) are arguments, not constants of the program; `settings`
    (configs, hashable) are static, so every Trainer of the same settings shares it."""
    cfg, mcfg, weights, masking, augment = settings
    batch = clips.flow.shape[0]
    keys = jax.vmap(lambda i: example_key(cfg.seed, state.step, i))(jnp.arange(batch))
    seen, masks = jax.vmap(lambda k, c: corrupt(k, c, mcfg, masking, augment))(keys, clips)

    def loss_fn(params):
        net = eqx.combine(params, static)
        if cfg.compute_dtype != "float32":
            net = M.cast(net, jnp.dtype(cfg.compute_dtype))

        def one(clip, target, mask):
            out = net(clip, hand, motion_mask=mask)
            return clip_loss_terms(out, clip, target, mask, hand, mcfg, weights, crop_size=mcfg.crop_size)

        terms = jax.vmap(one)(seen, targets, masks)
        return combine(terms, mcfg, cfg.stage, weights)

    (loss, means), grads = eqx.filter_value_and_grad(loss_fn, has_aux=True)(state.params)
    optimizer = make_optimizer(cfg, state.params)
    with jax.numpy_dtype_promotion("standard"):  # optax mixes its int32 step count with Python floats
        updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
        learning_rate = learning_rate_schedule(cfg)(state.step)  # the rate this update used
    params = eqx.apply_updates(state.params, updates)
    ema = state.ema
    if ema is not None:
        d = cfg.ema_decay
        ema = jax.tree.map(lambda e, p: d * e + (1 - d) * p, ema, params)
    # squared norms of the parts the stage trains (the four modules partition the weights):
    # each gradient array is squared once, for the parts and the whole
    squares = {part: optax.tree.norm(getattr(grads, part), squared=True) for part in ("backbone", "image_encoder", "motion_encoder", "fusion_decoder")
               if jax.tree.leaves(getattr(grads, part))}  # fmt: skip
    metrics = {"loss": loss, **{f"loss/{k}": v for k, v in means.items()}, "grad_norm": jnp.sqrt(sum(squares.values())),
               **{f"grad_norm/{part}": jnp.sqrt(sq) for part, sq in squares.items()}, "learning_rate": learning_rate}  # fmt: skip
    return TrainState(state.step + 1, params, opt_state, ema), metrics


# ----------------------------------------------------------------------------- run folders

CHECKPOINTS = "checkpoints"
LATEST = "latest"


def save_checkpoint(run: pathlib.Path, state: TrainState, keep: int) -> pathlib.Path:
    """`run/checkpoints/step_<step, 8 digits>/state.eqx` (e.g. `step_00000100`), atomically,
    then the `latest` pointer;
    older checkpoints beyond the last `keep` are removed."""
    root = run / CHECKPOINTS
    root.mkdir(parents=True, exist_ok=True)
    step = int(state.step)
    final = root / f"step_{step:08d}"
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".step_{step:08d}.", dir=root))
    try:
        eqx.tree_serialise_leaves(tmp / "state.eqx", state)
        write_json(tmp / "meta.json", {"step": step, "time": time.time()})
        if final.exists():
            shutil.rmtree(final)
        os.replace(tmp, final)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    with atomic_output(root / LATEST) as pointer:
        pointer.write_text(final.name)
    for old in sorted(p for p in root.glob("step_*") if p.is_dir())[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return final


def load_checkpoint(run: pathlib.Path, skeleton: TrainState) -> TrainState | None:
    """The latest checkpoint of `run` read into `skeleton`'s structure; None without one."""
    pointer = run / CHECKPOINTS / LATEST
    if not pointer.is_file():
        return None
    path = run / CHECKPOINTS / pointer.read_text().strip() / "state.eqx"
    try:
        return eqx.tree_deserialise_leaves(path, skeleton)
    except Exception as err:
        raise ValueError(f"{path} does not match this run's model and training config: {err}") from err


def _run_record(model_cfg: M.ModelConfig, cfg: TrainConfig, data_cfg: data_lib.DataConfig, init: str | None) -> dict:
    return {
        "model": {**json.loads(model_cfg.to_json()), M.REVISION_KEY: M.ARCHITECTURE_REVISION},  # resuming checks it
        "train": dataclasses.asdict(cfg),
        "data": dataclasses.asdict(data_cfg),
        "init": init,
        "git_revision": git_revision(),
    }


def _recorded(record: dict, part: str, key: str):
    """A setting of an earlier run's `config.json`; one it does not record (added to the
    library since) had its default then. So a new setting must default to the behaviour
    the library had before it existed."""
    settings = record.get(part, {})
    if key in settings:
        return settings[key]
    fields = {f.name: f for f in dataclasses.fields({"model": M.ModelConfig, "train": TrainConfig, "data": data_lib.DataConfig}[part])}
    field = fields.get(key)
    return None if field is None or field.default is dataclasses.MISSING else json.loads(json.dumps(field.default))


def train(
    run: str | pathlib.Path,
    clip_dirs: list[str | pathlib.Path],
    model_cfg: M.ModelConfig,
    cfg: TrainConfig = TrainConfig(),
    *,
    data_cfg: data_lib.DataConfig | None = None,
    val_dirs: list[str | pathlib.Path] | None = None,
    init: str | pathlib.Path | None = None,
    resume: bool = False,
    progress: bool = True,
    log_every: int = 1,
    mesh: jax.sharding.Mesh | None = None,
    backbone_weights: str | pathlib.Path | None = None,
) -> dict:
    """Train into the run folder `run` (module docstring); returns a summary.

    Args:
        clip_dirs: training clip folders (with crops and targets; `data.build_index`).
        val_dirs: held-out clip folders, validated every `cfg.validate_every` steps and at
            the end (`validation.evaluate_windows`, both views and the right view dropped)
            into `validation.jsonl`; the learning curves go to `curves.png`.
        init: a previous run (e.g. stage 1's) whose final network starts this one.
        backbone_weights: a DINOv3 checkpoint for the (ViT) backbone of a fresh network
            (`model.load_dinov3_weights`), recorded with its sha256 in `config.json`.
        resume: continue `run` from its latest checkpoint (its config must match).
        mesh: data parallelism over a device mesh (`data_mesh`); by default every
            device when there are several (`jax.devices()`, all processes after
            `jax.distributed.initialize()`), none with one. In a multi-process run every
            process loads its share of each batch and process 0 alone writes the run
            folder (a filesystem all processes see).

    A second process training into `run` while one does is refused (a lock in the run
    folder, `.train.lock`), and a run that fails before it starts leaves no folder.
    """
    run = pathlib.Path(run)
    args = (run, clip_dirs, model_cfg, cfg, data_cfg, val_dirs, init, resume, progress, log_every, mesh, backbone_weights)
    if jax.process_index() != 0:  # process 0 alone writes the run folder and holds its lock
        return _train_run(*args)
    if run.exists() and not run.is_dir():
        raise ValueError(f"--out {run} is a file, not a folder")
    fresh = not run.exists()
    run.mkdir(parents=True, exist_ok=True)
    with exclusive_lock(run / ".train.lock", wait=False) as held:
        if not held:
            raise ValueError(f"{run} is being trained by another process: wait for it to end, or choose another --out")
        try:
            return _train_run(*args)
        finally:  # (only the lock's holder cleans up: the folder may be another process's run)
            if fresh and not (run / "config.json").exists():  # the run never started: no empty folder left behind
                shutil.rmtree(run, ignore_errors=True)


def _train_run(
    run: pathlib.Path,
    clip_dirs: list[str | pathlib.Path],
    model_cfg: M.ModelConfig,
    cfg: TrainConfig,
    data_cfg: data_lib.DataConfig | None,
    val_dirs: list[str | pathlib.Path] | None,
    init: str | pathlib.Path | None,
    resume: bool,
    progress: bool,
    log_every: int,
    mesh: jax.sharding.Mesh | None,
    backbone_weights: str | pathlib.Path | None,
) -> dict:
    """`train`'s body (process 0 holds the run folder's lock): the run set up, then
    `Trainer.training_steps` with one hook per duty (`Hooks`), then the final network."""
    from tqdm import tqdm

    data_cfg = data_cfg or data_lib.DataConfig(frames=model_cfg.num_frames, crop_size=model_cfg.crop_size)
    main = jax.process_index() == 0
    record, windows, new_run = _open_run(run, clip_dirs, model_cfg, cfg, data_cfg, init, resume, backbone_weights, main)
    hand = mano.load_builtin("right")
    net = _initial_network(model_cfg, cfg, init, backbone_weights)
    if data_cfg.features:
        if net.backbone is None or not model_cfg.freeze_backbone:
            raise ValueError(f"cached features need a frozen backbone (the paper config); {model_cfg.name}'s is trained")
        precompute_features(net.backbone, list(clip_dirs) + list(val_dirs or []), model_cfg.crop_size, data_cfg.features, progress=progress and main)
    trainer = Trainer(net, cfg, hand, mesh=data_mesh() if mesh is None and jax.device_count() > 1 else mesh)
    state = trainer.init()
    metrics_path, val_path = run / "metrics.jsonl", run / "validation.jsonl"
    if new_run and main:  # written once every setting is checked: a run that fails to set up can be started again
        data_lib.save_index(run / "index.json", windows, data_cfg)
        write_json(run / "config.json", record)
    restored = load_checkpoint(run, _host(state)) if resume else None
    if restored is not None:
        state = trainer.place(restored)
    start = int(state.step)
    if main:
        _truncate_metrics(metrics_path, start)
        _truncate_metrics(val_path, start)
    share = process_batch_slice(cfg.batch)
    val_cfg = dataclasses.replace(data_cfg, stride=data_cfg.frames)  # non-overlapping held-out windows
    val_windows = _validation_windows(val_dirs, val_cfg, cfg.validation_windows) if val_dirs else []

    t0 = time.perf_counter()
    bar = tqdm(total=cfg.steps, initial=start, desc=f"train {cfg.stage}", unit="step", disable=not (progress and main))
    bar.set_postfix_str("compiling the step (the first one waits for it)")
    load = functools.partial(data_lib.load_batch, windows, data_cfg, cfg.batch, cfg.seed, part=share, frames_apart=cfg.frames_apart)
    logs = (open(metrics_path, "a"), open(val_path, "a")) if main else (open(os.devnull, "w"), open(os.devnull, "w"))
    with logs[0] as log, logs[1] as val_log, contextlib.closing(trainer.training_steps(state, load)) as steps:
        hooks = Hooks()  # in this order: a step is checked, logged, validated, saved, then shown
        hooks.add(nonfinite_guard(run))
        hooks.add(_metrics_logger(log, cfg.batch), every=log_every)
        if val_windows:  # (every process runs the validation; process 0 writes it)
            hooks.add(_validator(trainer, val_windows, val_cfg, hand, val_log, main), every=cfg.validate_every)
        if main:
            hooks.add(_checkpointer(run, cfg.keep_checkpoints), every=cfg.checkpoint_every)
        hooks.add(_progress(bar))
        for info in steps:  # the run's last step runs every hook
            hooks.run(info, force=info.step == cfg.steps)
            state = info.state
    bar.close()
    summary = {"run": str(run), "steps": int(state.step), "resumed_from": start, "seconds": time.perf_counter() - t0,
               "model": str(run / "model"), "curves": str(run / "curves.png")}  # fmt: skip
    if main:
        summary.update(_finish_run(run, trainer, state))
    return summary


def _open_run(run: pathlib.Path, clip_dirs, model_cfg: M.ModelConfig, cfg: TrainConfig, data_cfg: data_lib.DataConfig,
              init, resume: bool, backbone_weights, main: bool) -> tuple[dict, list[data_lib.Window], bool]:  # fmt: skip
    """The run's record (`config.json`'s content), its training windows and whether it is
    new: a new run's windows are indexed, a resumed one's read back after its recorded
    settings are checked against these."""
    if data_cfg.frames > model_cfg.num_frames or data_cfg.crop_size != model_cfg.crop_size:
        raise ValueError(f"data windows of {data_cfg.frames} frames at {data_cfg.crop_size} px do not fit {model_cfg.name} "
                         f"({model_cfg.num_frames} frames, {model_cfg.crop_size} px)")  # fmt: skip
    if data_cfg.targets == "labels" and not pathlib.Path(data_cfg.labels).is_dir():
        raise ValueError(f"the labels folder {data_cfg.labels} does not exist (esther label --out)")
    record = _run_record(model_cfg, cfg, data_cfg, None if init is None else str(init))
    if backbone_weights is not None:
        if init is not None:
            raise ValueError("--backbone-weights starts a fresh network; --init brings its own backbone")
        record["backbone_weights"] = {"path": str(backbone_weights), "sha256": file_sha256(backbone_weights)}
    config_path = run / "config.json"
    if not config_path.exists():
        windows = data_lib.build_index(clip_dirs, data_cfg)
        if not windows:
            raise ValueError(f"no training window in {len(clip_dirs)} clip folders (need crops/<side>.npz and targets, "
                             f"at least {data_cfg.frames} frames)")  # fmt: skip
        return record, windows, True
    if not resume and main:  # (the other processes of a new run may see process 0's config.json already)
        raise ValueError(f"{run} already holds a run: resume it (--resume) or choose another --out")
    previous = read_json(config_path)
    now = {part: json.loads(json.dumps(record[part])) for part in ("model", "train", "data")}
    differs = [f"{part}.{key} was {_recorded(previous, part, key)!r}, now {now[part].get(key)!r}"
               for part in now for key in sorted(set(now[part]) | set(previous.get(part, {})))
               if _recorded(previous, part, key) != now[part].get(key)]  # fmt: skip
    if differs:
        steps = any(d.startswith("train.steps") for d in differs)
        hint = " (the learning-rate schedule spans the steps: to train on, start a new run with --init)" if steps else ""
        raise ValueError(f"{run} was started with other settings ({'; '.join(differs)}): resume with the same settings{hint}")
    windows, _ = data_lib.load_index(run / "index.json")
    return record, windows, False


def _initial_network(model_cfg: M.ModelConfig, cfg: TrainConfig, init, backbone_weights) -> M.ESTHER:
    """A fresh network (seeded by `cfg.seed`, with DINOv3 `backbone_weights` if given), or
    the network of `init` (a run folder or a model folder), which must be `model_cfg`'s."""
    net = M.ESTHER(model_cfg, key=jax.random.key(cfg.seed))
    if init is not None:
        net = M.load(pathlib.Path(init) / "model") if (pathlib.Path(init) / "model").is_dir() else M.load(init)
        if net.config != model_cfg:
            differs = [f"{f.name} {getattr(net.config, f.name)!r} vs {getattr(model_cfg, f.name)!r}"
                       for f in dataclasses.fields(model_cfg) if getattr(net.config, f.name) != getattr(model_cfg, f.name)]  # fmt: skip
            raise ValueError(f"--init {init} is another network than this run trains ({'; '.join(differs)})")
    if backbone_weights is not None:
        if not isinstance(net.backbone, M.ViT):
            raise ValueError(f"--backbone-weights loads DINOv3 weights into a ViT backbone; {model_cfg.name} has {model_cfg.backbone}")
        net = eqx.tree_at(lambda m: m.backbone, net, M.load_dinov3_weights(net.backbone, backbone_weights))
    return net


def _finish_run(run: pathlib.Path, trainer: Trainer, state: TrainState) -> dict:
    """After the steps (also of a run resumed at its end): the final network (the EMA
    weights when kept) into `run/model`, the learning curves of the logs into
    `run/curves.png`; returns the last step's validation scores per views, if any."""
    M.save(run / "model", _host(trainer.network(state, ema=trainer.cfg.ema_decay is not None)))
    metrics, validation = _read_jsonl(run / "metrics.jsonl"), _read_jsonl(run / "validation.jsonl")
    plot_learning_curves(metrics, validation, run / "curves.png")
    final_rows = [row for row in validation if row["step"] == int(state.step)]
    if not final_rows:
        return {}
    return {"validation": {row["views"]: {k: v for k, v in row.items() if k not in ("step", "views")} for row in final_rows}}


# the hooks of a run (`_train_run`): each a function of a `StepInfo`

def _metrics_logger(log, batch: int) -> Callable[[StepInfo], None]:
    """`metrics.jsonl`'s line of a step: its metrics and clips/s (over the step's interval)."""

    def write(info: StepInfo) -> None:
        log.write(json.dumps({"step": info.step, **info.metrics, "clips_per_s": batch / max(info.seconds, 1e-9)}) + "\n")
        log.flush()

    return write


def _validator(trainer: Trainer, windows: list[data_lib.Window], val_cfg: data_lib.DataConfig, hand: mano.ManoModel, log,
               main: bool) -> Callable[[StepInfo], None]:  # fmt: skip
    """`validation.jsonl`'s two lines of a step: the held-out windows scored with both
    views and with the right view dropped (the EMA weights when kept)."""
    cfg = trainer.cfg

    def validate(info: StepInfo) -> None:
        net = trainer.network(info.state, ema=cfg.ema_decay is not None)
        for views, dropped in (("both", None), ("right dropped", 1)):
            scores = evaluate_windows(net, windows, val_cfg, hand_model=hand, batch=cfg.batch, view_dropped=dropped)
            if main:
                log.write(json.dumps({"step": info.step, "views": views, **scores}) + "\n")
        log.flush()

    return validate


def _checkpointer(run: pathlib.Path, keep: int) -> Callable[[StepInfo], None]:
    """The step's checkpoint (`save_checkpoint`, the last `keep` kept)."""
    return lambda info: save_checkpoint(run, _host(info.state), keep)


def _progress(bar) -> Callable[[StepInfo], None]:
    """The progress bar one step on, showing the step's loss."""

    def show(info: StepInfo) -> None:
        bar.update(1)
        bar.set_postfix(loss=f"{info.loss:.4f}")

    return show


def train_stages(
    out: str | pathlib.Path,
    clip_dirs: list[str | pathlib.Path],
    model_cfg: M.ModelConfig,
    *,
    stage1_steps: int,
    stage2_steps: int,
    batch: int = 8,
    learning_rate: float = 5e-4,
    stage1_learning_rate: float | None = None,
    stage1_frames_apart: bool = False,
    val_dirs: list[str | pathlib.Path] | None = None,
    validate_every: int = 400,
    validation_windows: int = 48,
    seed: int = 0,
    features: str | pathlib.Path | None = None,
    labels: str | pathlib.Path | None = None,
    init: str | pathlib.Path | None = None,
    progress: bool = True,
) -> pathlib.Path:
    """The two training stages ("Training and Supervision", appendix B): stage 1 ('image') trains the image encoder
    under its 2D, heatmap, triangulation, visibility and depth-bin guidance into
    `out/stage1`; stage 2 ('joint') trains everything from stage 1's network into
    `out/stage2`. A stage with 0 steps is skipped, a stage whose `model/` exists is kept,
    an interrupted one resumes from its checkpoint. Each stage warms up over a tenth of
    its steps (at most 100), then decays along a cosine to 0 from its peak rate
    (`learning_rate`; stage 1's `stage1_learning_rate` if given). `stage1_frames_apart`
    draws stage 1's frames apart (`TrainConfig.frames_apart`). `features`: a feature
    cache of the (frozen) backbone both stages read instead of the crops
    (`DataConfig.features`), filled by the first. `labels`: train on the teacher's label
    folder (`DataConfig.targets = 'labels'`) instead of the clips' ground truth. `init`: a
    run (or model folder) whose network starts the first stage trained, instead of a fresh
    one (the data engine's warm start). Returns the final model folder."""
    out = pathlib.Path(out)
    if stage1_steps < 0 or stage2_steps < 0 or stage1_steps + stage2_steps == 0:
        raise ValueError(f"stage steps must be >= 0 and not both 0, got {stage1_steps} and {stage2_steps}")
    data_cfg = data_lib.DataConfig(frames=model_cfg.num_frames, crop_size=model_cfg.crop_size, features=None if features is None else str(features),
                                   **({} if labels is None else {"targets": "labels", "labels": str(labels)}))  # fmt: skip
    last = init
    stages = (("image", stage1_steps, "stage1", learning_rate if stage1_learning_rate is None else stage1_learning_rate, stage1_frames_apart),
              ("joint", stage2_steps, "stage2", learning_rate, False))  # fmt: skip
    for stage, steps, name, rate, frames_apart in stages:
        if steps == 0:
            continue
        run = out / name
        if not (run / "model").is_dir():
            cfg = TrainConfig(stage=stage, steps=steps, batch=batch, learning_rate=rate, warmup_steps=min(100, steps // 10), frames_apart=frames_apart,
                              validate_every=validate_every, validation_windows=validation_windows, checkpoint_every=100, seed=seed)  # fmt: skip
            train(run, clip_dirs, model_cfg, cfg, data_cfg=data_cfg, val_dirs=val_dirs, init=last, resume=(run / "config.json").exists(), progress=progress)
        last = run
    return last / "model"


def _validation_windows(val_dirs, val_cfg: data_lib.DataConfig, limit: int) -> list[data_lib.Window]:
    """The held-out windows of `val_cfg`, at most `limit`, evenly spread over the clips."""
    windows = data_lib.build_index(val_dirs, val_cfg)
    if not windows:
        raise ValueError(f"no validation window in {len(val_dirs)} held-out clip folders (need crops, targets, {val_cfg.frames} frames)")
    if len(windows) > limit:
        windows = [windows[i] for i in np.linspace(0, len(windows) - 1, limit).round().astype(int)]
    return windows


def _read_jsonl(path: pathlib.Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()] if path.exists() else []


def _truncate_metrics(path: pathlib.Path, step: int) -> None:
    """Drop logged steps after `step` (a resumed run logs them again): no duplicates."""
    if not path.exists():
        return
    kept = [json.dumps(row) for row in _read_jsonl(path) if row["step"] <= step]
    with atomic_output(path) as tmp:
        tmp.write_text("".join(line + "\n" for line in kept))


__all__ = [
    "Hooks", "NonFiniteLoss", "StepInfo", "TrainConfig", "TrainState", "Trainer", "data_mesh", "decay_mask", "nonfinite_guard",
    "process_batch_slice", "learning_rate_schedule", "load_checkpoint", "make_optimizer", "save_checkpoint", "stage_spec", "train",
    "train_stages",
]  # fmt: skip
