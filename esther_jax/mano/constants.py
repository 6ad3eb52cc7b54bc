"""Joint orders and index maps of MANO (one place; docs/architecture.md, "Conventions").

MANO joints (16, MANO order): 0 wrist; 1-3 index; 4-6 middle; 7-9 pinky;
10-12 ring; 13-15 thumb. Keypoints (21, MediaPipe/OpenPose/FreiHAND order):
0 wrist; 1-4 thumb (CMC, MCP, IP, tip); 5-8 index (MCP, PIP, DIP, tip); 9-12 middle;
13-16 ring; 17-20 pinky.
"""

MANO_PARENTS: tuple[int, ...] = (-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14)
"""Parent of each MANO joint (-1 for the wrist)."""

MANO_JOINT_NAMES: tuple[str, ...] = (
    "wrist",
    "index1", "index2", "index3",
    "middle1", "middle2", "middle3",
    "pinky1", "pinky2", "pinky3",
    "ring1", "ring2", "ring3",
    "thumb1", "thumb2", "thumb3",
)  # fmt: skip

KEYPOINT_NAMES: tuple[str, ...] = (
    "wrist",
    "thumb_cmc", "thumb_mcp", "thumb_ip", "thumb_tip",
    "index_mcp", "index_pip", "index_dip", "index_tip",
    "middle_mcp", "middle_pip", "middle_dip", "middle_tip",
    "ring_mcp", "ring_pip", "ring_dip", "ring_tip",
    "pinky_mcp", "pinky_pip", "pinky_dip", "pinky_tip",
)  # fmt: skip
"""Name of each of the 21 keypoints (MediaPipe order)."""

KEYPOINT_PARENTS: tuple[int, ...] = (-1, 0, 1, 2, 3, 0, 5, 6, 7, 0, 9, 10, 11, 0, 13, 14, 15, 0, 17, 18, 19)
"""Parent of each of the 21 keypoints (bones of the 21-keypoint skeleton); -1 for the wrist."""

KEYPOINT_FINGERS: dict[str, tuple[int, int, int, int]] = {
    "thumb": (1, 2, 3, 4),
    "index": (5, 6, 7, 8),
    "middle": (9, 10, 11, 12),
    "ring": (13, 14, 15, 16),
    "pinky": (17, 18, 19, 20),
}
"""Keypoints of each finger, proximal to distal (thumb CMC..tip, others MCP..tip), thumb to pinky."""

PALM_KEYPOINTS: tuple[int, ...] = (0, 1, 5, 9, 13, 17)
"""Wrist, thumb CMC, index/middle/ring/pinky MCP: rigid with the wrist in MANO."""

FINGERTIP_IDS_SMPLX: tuple[int, ...] = (744, 320, 443, 554, 671)
"""Fingertip vertex ids (thumb, index, middle, ring, pinky) of smplx, HOT3D and HaMeR."""

FINGERTIP_IDS_MANOPTH: dict[str, tuple[int, ...]] = {
    "right": (745, 317, 444, 556, 673),
    "left": (745, 317, 445, 556, 673),
}
"""manopth/manotorch fingertip ids (thumb, index, middle, ring, pinky) per side."""

KEYPOINT_FROM_MANO: tuple[int, ...] = (0, 13, 14, 15, 16, 1, 2, 3, 17, 4, 5, 6, 18, 10, 11, 12, 19, 7, 8, 9, 20)
"""Keypoint k is row KEYPOINT_FROM_MANO[k] of concat(16 MANO joints, 5 tips T,I,M,R,P)."""

FINGER_CHAINS: dict[str, tuple[int, int, int]] = {
    "thumb": (13, 14, 15),
    "index": (1, 2, 3),
    "middle": (4, 5, 6),
    "ring": (10, 11, 12),
    "pinky": (7, 8, 9),
}
"""MANO joints of each finger, proximal to distal (the tip vertex follows the last)."""

FINGER_ORDER: tuple[str, ...] = ("thumb", "index", "middle", "ring", "pinky")
"""Order of the fingertip ids and of the five tip keypoints."""

NUM_JOINTS = 16
NUM_KEYPOINTS = 21
NUM_BETAS = 10
NUM_POSE_FEATURES = 135
