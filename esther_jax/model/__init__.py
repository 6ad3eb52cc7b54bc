"""The ESTHER network in Equinox (paper 3.4-3.7, appendices B-E).

Public names: `ESTHER`, `ModelConfig`, `config`, `CONFIGS`, `ABLATIONS`, `BACKBONES`,
`parameter_counts`, `ClipInput`, `ESTHEROutput`, `HandPrediction`, `predict`, `gated`,
`cast` (mixed precision), `mirror_clip`, `unmirror`, `trainable`, `extract_features`, `clip_input_from_crops`,
`crop_projections` (rig-frame joints -> crop pixels, depths and in-crop flags),
`cross_view_attention` (the stereo blocks' cross-view attention probabilities), `save`, `load`,
the backbones (`Backbone`: `ViT`, `ConvStem`, `HandBackbone`; `make_backbone`, `load_dinov3_weights`, `dinov3_state_dict`), the parts (`StereoImageEncoder`,
`MotionEncoder`, `FusionDecoder`) and their outputs (`ImageEvidence`,
`MotionEvidence`, `Decoded`), `evidence_statistics`, `decode_kinematic_tree`,
`depth_bin_centres`; MediaPipe's pretrained hand network (`load_mediapipe_hand`,
`MediaPipeHand`, `HandLandmarks`) and the TFLite converter behind it (`load_tflite`, `TFLiteGraph`).
"""

from .backbones import Backbone as Backbone
from .backbones import ConvStem as ConvStem
from .backbones import HandBackbone as HandBackbone
from .backbones import ViT as ViT
from .backbones import dinov3_state_dict as dinov3_state_dict
from .backbones import load_dinov3_weights as load_dinov3_weights
from .backbones import make_backbone as make_backbone
from .config import ABLATIONS as ABLATIONS
from .config import BACKBONES as BACKBONES
from .config import CONFIGS as CONFIGS
from .config import ModelConfig as ModelConfig
from .config import config as config
from .esther import ESTHER as ESTHER
from .esther import ClipInput as ClipInput
from .esther import cast as cast
from .esther import cross_view_attention as cross_view_attention
from .esther import gated as gated
from .esther import ESTHEROutput as ESTHEROutput
from .esther import HandPrediction as HandPrediction
from .esther import clip_input_from_crops as clip_input_from_crops
from .esther import crop_projections as crop_projections
from .esther import extract_features as extract_features
from .esther import ARCHITECTURE_REVISION as ARCHITECTURE_REVISION
from .esther import REVISION_KEY as REVISION_KEY
from .esther import load as load
from .esther import mirror_clip as mirror_clip
from .esther import parameter_counts as parameter_counts
from .esther import predict as predict
from .esther import save as save
from .esther import trainable as trainable
from .esther import unmirror as unmirror
from .fusion_decoder import Decoded as Decoded
from .fusion_decoder import FusionDecoder as FusionDecoder
from .fusion_decoder import decode_kinematic_tree as decode_kinematic_tree
from .fusion_decoder import evidence_statistics as evidence_statistics
from .motion_encoder import MotionEncoder as MotionEncoder
from .motion_encoder import MotionEvidence as MotionEvidence
from .stereo_encoder import ImageEvidence as ImageEvidence
from .stereo_encoder import StereoImageEncoder as StereoImageEncoder
from .stereo_encoder import depth_bin_centres as depth_bin_centres
from .mediapipe_hand import HandLandmarks as HandLandmarks
from .mediapipe_hand import MediaPipeHand as MediaPipeHand
from .mediapipe_hand import load_mediapipe_hand as load_mediapipe_hand
from .tflite import TFLiteGraph as TFLiteGraph
from .tflite import load_tflite as load_tflite
