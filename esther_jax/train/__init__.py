"""Training the ESTHER network (appendices B, C, E): the losses term by term
(`losses`), token masking and image augmentation (`masking`), windows of clip folders
and reproducible batches (`data`), cached features of a frozen backbone (`features`),
the optimiser, the jitted step, the steps as a generator with hooks (`StepInfo`,
`Hooks`), data parallelism and run folders that resume bit for bit (`loop`), and
scoring on held-out windows (`validation`)."""

from .data import DataConfig as DataConfig
from .data import Window as Window
from .data import batch_indices as batch_indices
from .data import build_index as build_index
from .data import frame_pools as frame_pools
from .data import frames_apart_example as frames_apart_example
from .data import load_batch as load_batch
from .data import load_example as load_example
from .data import load_index as load_index
from .data import mirror_targets as mirror_targets
from .data import save_index as save_index

from .losses import STAGE_TERMS as STAGE_TERMS
from .losses import STAGES as STAGES
from .losses import LossWeights as LossWeights
from .losses import Targets as Targets
from .losses import Term as Term
from .losses import clip_loss_terms as clip_loss_terms
from .losses import combine as combine
from .losses import onscreen_label as onscreen_label
from .masking import AugmentRates as AugmentRates
from .masking import MaskingRates as MaskingRates
from .masking import anchor_frames as anchor_frames
from .masking import augment_images as augment_images
from .masking import corrupt as corrupt
from .masking import dropped_views as dropped_views
from .masking import example_key as example_key
from .masking import kept_views as kept_views
from .masking import motion_mask as motion_mask
from .loop import Hooks as Hooks
from .loop import NonFiniteLoss as NonFiniteLoss
from .loop import StepInfo as StepInfo
from .loop import TrainConfig as TrainConfig
from .loop import Trainer as Trainer
from .loop import TrainState as TrainState
from .loop import data_mesh as data_mesh
from .loop import process_batch_slice as process_batch_slice
from .loop import decay_mask as decay_mask
from .loop import learning_rate_schedule as learning_rate_schedule
from .loop import load_checkpoint as load_checkpoint
from .loop import make_optimizer as make_optimizer
from .loop import nonfinite_guard as nonfinite_guard
from .loop import save_checkpoint as save_checkpoint
from .loop import stage_spec as stage_spec
from .loop import train as train
from .loop import train_stages as train_stages
from .features import precompute_features as precompute_features
from .validation import drop_frames as drop_frames
from .validation import drop_view as drop_view
from .validation import Predictions as Predictions
from .validation import evaluate_windows as evaluate_windows
from .validation import predict_windows as predict_windows
from .validation import score_predictions as score_predictions
