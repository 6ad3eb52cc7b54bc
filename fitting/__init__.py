"""fitting: the ESTHER teacher (2D keypoints of any rig -> metric MANO labels).

Built only on the public `esther_jax` names, so teacher and network share one jitted
kinematics. The paper's stages are public, typed functions over `eqx.Module`s:

    fuse -> prefilter -> initialise -> shape_lock -> fit_frames -> refine_motion
         -> reprojection_filter -> label_quality

`label_hand` is their composition for one hand of one clip, `label_hands` for a clip's
hands as one person's (a hand never seen in stereo takes the other's shape); `label_clip` / `label_clips`
label clip folders (atomic, resumable). `refine` is the same composition started from a
network's prediction (the data engine's model-assisted labelling), `refine_clips` its
folders (`esther refine`). Priors are pluggable (`PosePrior`,
`MotionPrior`); the solver is part of `LabelConfig` (`SOLVERS`). `esther_jax.studies.teacher_validation` measures
the teacher against exact ground truth on synthetic held-out clips per rig and detector,
with appendix N's label quality and admissible band (imported on its own: it draws figures).
"""

from .fusion import Fused as Fused
from .fusion import fuse as fuse
from .evidence import Evidence as Evidence
from .evidence import Initial as Initial
from .evidence import PalmPose as PalmPose
from .evidence import initialise as initialise
from .evidence import palm_pose as palm_pose
from .evidence import prefilter as prefilter
from .evidence import template_bones as template_bones
from .label import label_clip as label_clip
from .label import label_clips as label_clips
from .label import refine_clips as refine_clips
from .label import read_reject_list as read_reject_list
from .objectives import FitWeights as FitWeights
from .objectives import Problem as Problem
from .pipeline import LabelConfig as LabelConfig
from .pipeline import label_hand as label_hand
from .pipeline import label_hands as label_hands
from .pipeline import REFINE_CONFIG as REFINE_CONFIG
from .pipeline import REFINE_REVISION as REFINE_REVISION
from .pipeline import TEACHER_REVISION as TEACHER_REVISION
from .pipeline import method_record as method_record
from .pipeline import refine as refine
from .priors import MotionPrior as MotionPrior
from esther_jax.mano import PosePrior as PosePrior
from .quality import depth_per_disparity as depth_per_disparity
from .quality import frame_quality as frame_quality
from .quality import label_quality as label_quality
from .quality import reprojection_filter as reprojection_filter
from .review import review_sheet as review_sheet
from .solve import SOLVERS as SOLVERS
from .stages import Fits as Fits
from .stages import ShapeLock as ShapeLock
from .stages import fit_frames as fit_frames
from .stages import pooled_betas as pooled_betas
from .stages import frame_data as frame_data
from .stages import refine_motion as refine_motion
from .stages import shape_lock as shape_lock
