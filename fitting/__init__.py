"""fitting: the ESTHER teacher (stereo 2D keypoints -> metric MANO labels).

Built only on the public `esther_jax` names, so teacher and network share one jitted
kinematics (ARCHITECTURE.md, "The teacher"). Public names: `label_hand` (one hand of
one clip), `label_clip`, `label_clips` (folders, atomic, resumable), `LabelConfig`,
`FitWeights`, the priors `PosePrior` and `MotionPrior`, `fuse`, and `review_sheet`.
"""

from .fusion import fuse as fuse
from .label import label_clip as label_clip
from .label import label_clips as label_clips
from .label import read_reject_list as read_reject_list
from .objectives import FitWeights as FitWeights
from .pipeline import LabelConfig as LabelConfig
from .pipeline import label_hand as label_hand
from .priors import MotionPrior as MotionPrior
from .priors import PosePrior as PosePrior
from .review import review_sheet as review_sheet
