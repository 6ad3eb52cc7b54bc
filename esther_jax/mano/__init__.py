"""MANO hand model: arrays, parameters, forward kinematics, conventions, I/O.

Public names: `ManoModel`, `ManoParams`, `ManoOutput`, `forward`, `forward_batch`, `forward_joints`,
`joints_jacobian`, `forward_joints_with_jacobian`, `JointsJacobian`, `forward_rotations`, `with_shape`, `with_pose`, `with_rotations`,
`rest_joints`, `load_builtin`, `load_mano_pkl`, `save_mano_pkl`, `model_id`, `mirror_params`, `mirror_hand_pose`,
`mirror_points`, `to_smplx`, `from_smplx`, `transform_params`, `pca_to_hand_pose`, `hand_pose_to_pca`,
`export_mesh`, `anatomical_frames`, `JOINT_LIMITS`, `PosePrior`, `GMMPosePrior`, `fit_gmm_pose_prior`, and the joint-order constants.
"""

from .anatomy import JOINT_LIMITS as JOINT_LIMITS
from .anatomy import anatomical_frames as anatomical_frames
from .anatomy import anatomical_to_hand_pose as anatomical_to_hand_pose
from .anatomy import hand_pose_to_anatomical as hand_pose_to_anatomical
from .constants import FINGERTIP_IDS_MANOPTH as FINGERTIP_IDS_MANOPTH
from .constants import FINGERTIP_IDS_SMPLX as FINGERTIP_IDS_SMPLX
from .constants import KEYPOINT_FINGERS as KEYPOINT_FINGERS
from .constants import KEYPOINT_FROM_MANO as KEYPOINT_FROM_MANO
from .constants import KEYPOINT_NAMES as KEYPOINT_NAMES
from .constants import KEYPOINT_PARENTS as KEYPOINT_PARENTS
from .constants import MANO_JOINT_NAMES as MANO_JOINT_NAMES
from .constants import MANO_PARENTS as MANO_PARENTS
from .constants import PALM_KEYPOINTS as PALM_KEYPOINTS
from .conventions import from_smplx as from_smplx
from .conventions import mirror_hand_pose as mirror_hand_pose
from .conventions import mirror_params as mirror_params
from .conventions import mirror_points as mirror_points
from .conventions import to_smplx as to_smplx
from .conventions import transform_params as transform_params
from .export import export_mesh as export_mesh
from .io import ManoFileError as ManoFileError
from .io import load_builtin as load_builtin
from .io import load_mano_pkl as load_mano_pkl
from .io import save_mano_pkl as save_mano_pkl
from .kinematics import forward as forward
from .kinematics import forward_batch as forward_batch
from .kinematics import forward_joints as forward_joints
from .kinematics import JointsJacobian as JointsJacobian
from .kinematics import forward_rotations as forward_rotations
from .kinematics import forward_joints_with_jacobian as forward_joints_with_jacobian
from .kinematics import joints_jacobian as joints_jacobian
from .kinematics import rest_joints as rest_joints
from .kinematics import with_pose as with_pose
from .kinematics import with_rotations as with_rotations
from .kinematics import with_shape as with_shape
from .model import ManoModel as ManoModel
from .model import ManoOutput as ManoOutput
from .model import ManoParams as ManoParams
from .model import model_id as model_id
from .pca import hand_pose_to_pca as hand_pose_to_pca
from .pca import pca_to_hand_pose as pca_to_hand_pose
from .priors import GMMPosePrior as GMMPosePrior
from .priors import PosePrior as PosePrior
from .priors import fit_gmm_pose_prior as fit_gmm_pose_prior
