"""fitting: the ESTHER teacher (stereo 2D keypoints -> metric MANO labels).

Built only on the public `esther_jax` names, so teacher and network share one
jitted kinematics (ARCHITECTURE.md, "The teacher").
"""
