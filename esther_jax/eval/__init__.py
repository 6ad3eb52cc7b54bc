"""Evaluation: robustness protocols, the HOT3D-compatible preset, reports, label-folder evaluation."""

from .folders import evaluate_folders as evaluate_folders
from .hot3d import evaluate_hot3d_folders as evaluate_hot3d_folders
from .hot3d import hot3d_dataset_metrics as hot3d_dataset_metrics
from .hot3d import hot3d_sequence_metrics as hot3d_sequence_metrics
from .protocols import CORRUPTIONS as CORRUPTIONS
from .protocols import corrupt as corrupt
from .protocols import corrupt_clip as corrupt_clip
from .protocols import drop_frames_images as drop_frames_images
from .protocols import drop_frames_keypoints as drop_frames_keypoints
from .protocols import drop_view_images as drop_view_images
from .protocols import drop_view_keypoints as drop_view_keypoints
from .protocols import frame_drop_mask as frame_drop_mask
from .reports import Record as Record
